"""The app against hostile and careless clients: hub depth models only from the operator's
list and the local cache (no download, no folder probing, a fast refusal), and the decode
problems of the library shown to the user as ``gr.Error`` or ``gr.Warning``."""

from __future__ import annotations

import time

import numpy as np
import pytest
from PIL import Image

gr = pytest.importorskip("gradio", reason="the app extra is not installed")

from app import loading, sources  # noqa: E402
from app.cache import SceneCache  # noqa: E402
from app.handlers import RefocusApp  # noqa: E402
from d2f_core.depth import sources as depth_sources  # noqa: E402

# depth map, its kind, session, focus, f-number, blades, rotation, highlight, fusion, view,
# quality (the /load inputs before the depth source and the model)
ARGS = (None, "disparity", None, 0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced")
NOT_CACHED = "depth-anything/Depth-Anything-V2-Small-hf"


@pytest.fixture
def logic(tiny_model, tmp_path):
    return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "downloads")


@pytest.fixture
def decodes(monkeypatch):
    """Counts the photos the app decodes."""
    calls = []
    original = loading.imaging.load_photo

    def counted(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(loading.imaging, "load_photo", counted)
    return calls


# ------------------------------------------------------------------------ item 3: hub models


def _empty_hub_cache(monkeypatch, tmp_path):
    import huggingface_hub

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path / "hub"))


class TestHubPolicy:
    def test_no_hub_model_by_default(self, monkeypatch):
        monkeypatch.setattr(sources, "POLICY", sources.HubPolicy())
        assert "transformers" not in [v for _, v in sources.choices()]
        with pytest.raises(ValueError, match="offers no Hugging Face depth model"):
            sources.resolve("transformers", NOT_CACHED, False, False)

    def test_only_the_operators_models(self, monkeypatch):
        policy = sources.HubPolicy(models=("org/listed",))
        monkeypatch.setattr(sources, "POLICY", policy)
        monkeypatch.setattr(depth_sources, "hub_model_cached", lambda name: True)
        if depth_sources.hub_available():
            assert "transformers" in [v for _, v in sources.choices()]
            assert sources.resolve("transformers", "org/listed", False, False)[0] == (
                "transformers:org/listed"
            )
        for name in ("org/other", "/etc", "../models"):  # no download, no folder probing
            with pytest.raises(ValueError, match="not offered here; this server offers: org/"):
                sources.check_hub_model(name)

    def test_not_cached_fails_fast(self, monkeypatch, tmp_path):
        _empty_hub_cache(monkeypatch, tmp_path)
        monkeypatch.setattr(sources, "POLICY", sources.HubPolicy(models=(NOT_CACHED,)))
        t0 = time.perf_counter()
        with pytest.raises(ValueError, match="not available on this server.*hf download"):
            sources.check_hub_model(NOT_CACHED)
        assert time.perf_counter() - t0 < 1.0

    def test_cache_lookup_reads_local_files(self, tmp_path, monkeypatch):
        # a hub cache laid out as huggingface_hub writes it
        import huggingface_hub

        monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(tmp_path))
        repo = tmp_path / "models--org--tiny"
        snap = repo / "snapshots" / "abc"
        snap.mkdir(parents=True)
        (repo / "refs").mkdir()
        (repo / "refs" / "main").write_text("abc")
        for name in ("config.json", "preprocessor_config.json"):
            (snap / name).write_text("{}")
        assert not depth_sources.hub_model_cached("org/tiny")  # no weights
        (snap / "model.safetensors").write_bytes(b"")
        assert depth_sources.hub_model_cached("org/tiny")
        assert not depth_sources.hub_model_cached("x" * 5000)

    def test_long_name_is_clear_in_the_app(self, logic, two_plane_scene, monkeypatch, decodes):
        # was "Something went wrong (OSError)" and a traceback in the log
        monkeypatch.setattr(sources, "POLICY", sources.HubPolicy(any_model=True))
        with pytest.raises(gr.Error, match="5000 characters long; at most 200"):
            logic.load(str(two_plane_scene.photo), *ARGS, "transformers", "x" * 5000)
        assert decodes == []

    def test_refused_before_the_photo_is_decoded(
        self, logic, two_plane_scene, monkeypatch, tmp_path, decodes
    ):
        _empty_hub_cache(monkeypatch, tmp_path)
        monkeypatch.setattr(sources, "POLICY", sources.HubPolicy(models=(NOT_CACHED,)))
        t0 = time.perf_counter()
        with pytest.raises(gr.Error, match="not available on this server"):
            logic.load(str(two_plane_scene.photo), *ARGS, "transformers", NOT_CACHED)
        assert time.perf_counter() - t0 < 1.0
        with pytest.raises(gr.Error, match="not offered here"):
            logic.load(str(two_plane_scene.photo), *ARGS, "transformers", "org/other")
        assert decodes == []  # the render slot was held for the check only

    def test_any_model_is_for_local_use_only(self, capsys):
        from app.main import main

        with pytest.raises(SystemExit) as exit_:
            main(["--allow-any-depth-model", "--host", "0.0.0.0"])
        assert exit_.value.code == 2
        assert "--allow-any-depth-model is for local use only" in capsys.readouterr().err

    def test_model_list_option(self):
        assert sources.parse_models(" a/b, c/d ,,a/b") == ("a/b", "c/d")
        with pytest.raises(ValueError, match="at most 200"):
            sources.parse_models("a" * 300)


# ------------------------------------------------------------------------ item 4 in the app


class TestDecodeProblemsShown:
    def test_npy_bomb_is_a_message(self, logic, two_plane_scene, tmp_path):
        header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 1), np.float32))
        header["shape"] = (100_000, 100_000)
        path = tmp_path / "bomb.npy"
        with path.open("wb") as fh:
            np.lib.format.write_array_header_1_0(fh, header)
            fh.write(b"\x00" * 1000)
        args = (str(path), *ARGS[1:])
        with pytest.raises(gr.Error, match=r"header claims shape \(100000, 100000\)"):
            logic.load(str(two_plane_scene.photo), *args, "auto", "")

    def test_float_tiff_without_light_is_refused(self, logic, tmp_path):
        path = tmp_path / "dark.tif"
        Image.fromarray(np.full((48, 64), -2.0, np.float32)).save(path)
        with pytest.raises(gr.Error, match="no value above 0"):
            logic.load(str(path), *ARGS, "auto", "")

    def test_some_nan_pixels_warn_the_user(self, logic, tmp_path, monkeypatch):
        said = []
        monkeypatch.setattr(gr, "Warning", lambda message, *a, **k: said.append(message))
        values = np.tile(np.linspace(0.1, 0.9, 64, dtype=np.float32), (48, 1))
        values[5:8, 5:8] = np.nan
        path = tmp_path / "holes.tif"
        Image.fromarray(values).save(path)
        logic.load(str(path), *ARGS, "auto", "")
        assert any("9 NaN or infinite pixels" in m and "shown black" in m for m in said), said
