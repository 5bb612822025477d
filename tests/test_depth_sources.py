"""Depth sources (``d2f_core.depth.sources``): parsing, conversions, hub models loaded from
local folders (tiny random models, never downloaded), the clear errors, and the refinement
that every source's map goes through in ``D2F.prepare``."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from d2f_core.depth import sources as ds
from d2f_core.depth.refine import box_mean
from d2f_core.io import Photo
from d2f_core.pipeline import D2F
from d2f_core.sizing import resize

pytestmark = pytest.mark.usefixtures("one_thread")


def _photo(h: int = 40, w: int = 64, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    ra = np.argsort(np.argsort(a.ravel())).astype(np.float64)
    rb = np.argsort(np.argsort(b.ravel())).astype(np.float64)
    return float(np.corrcoef(ra, rb)[0, 1])


@pytest.fixture(autouse=True)
def _fresh_models():
    """No hub model stays loaded from one test to the next."""
    ds._LOADED.clear()
    yield
    ds._LOADED.clear()


# ------------------------------------------------------------------------------ parsing


class TestParse:
    def test_names(self):
        assert ds.parse_source("d2f") == ds.DepthSource("d2f")
        assert ds.parse_source(" Embedded ") == ds.DepthSource("embedded")
        assert ds.parse_source("file:/a/b.png").arg == "/a/b.png"
        src = ds.parse_source("transformers:depth-anything/Depth-Anything-V2-Small-hf")
        assert (src.kind, src.arg) == ("transformers", "depth-anything/Depth-Anything-V2-Small-hf")
        assert src.name == "transformers:depth-anything/Depth-Anything-V2-Small-hf"
        assert ds.parse_source("file:C:/maps/x.png").arg == "C:/maps/x.png"  # one split only

    @pytest.mark.parametrize(
        "bad, match",
        [
            ("midas", "unknown depth source"),
            ("transformers", "needs a model id"),
            ("transformers:", "needs a model id"),
            ("file", "needs a map file"),
            ("d2f:big", "takes no argument"),
        ],
    )
    def test_bad(self, bad, match):
        with pytest.raises(ValueError, match=match):
            ds.parse_source(bad)
        with pytest.raises(TypeError):
            ds.parse_source(3)


# ------------------------------------------------------------------------------ conversions


class TestConversions:
    def test_relative(self):
        # larger = nearer, any scale and shift: min-max to [0, 1] (under 1000 px: extremes)
        got = ds.relative_to_disparity(np.array([[3.0, 5.0], [7.0, 11.0]]))
        np.testing.assert_allclose(got, [[0.0, 0.25], [0.5, 1.0]], atol=1e-6)
        # scale and shift do not matter
        again = ds.relative_to_disparity(np.array([[3.0, 5.0], [7.0, 11.0]]) * 40 - 9)
        np.testing.assert_allclose(again, got, atol=1e-6)

    def test_metric(self):
        # metres, larger = farther: 1/z, then min-max; nearest is 1
        got = ds.metric_to_disparity(np.array([[1.0, 2.0], [4.0, 4.0]]))
        np.testing.assert_allclose(got, [[1.0, 1 / 3], [0.0, 0.0]], atol=1e-6)
        # a zero is a hole, filled from its neighbours, never the nearest point
        holed = ds.metric_to_disparity(np.array([[1.0, 0.0], [4.0, 4.0]]))
        assert np.all(np.isfinite(holed)) and holed[0, 0] == pytest.approx(1.0)
        assert 0.0 <= holed[0, 1] < 1.0

    def test_robust_on_large_maps(self):
        # with 1000 pixels or more the 0.5/99.5 percentiles bound the range: one wild
        # value cannot squash the rest
        ramp = np.linspace(1.0, 2.0, 40 * 50).reshape(40, 50)
        ramp[0, 0] = 1e6
        got = ds.relative_to_disparity(ramp)
        assert got.min() == 0.0 and got.max() == 1.0
        assert got[20, 25] == pytest.approx(0.5, abs=0.02)

    def test_tensor_input_and_bad_shapes(self):
        got = ds.relative_to_disparity(torch.tensor([[[0.0, 2.0]]]))
        np.testing.assert_allclose(got, [[0.0, 1.0]])
        with pytest.raises(ValueError, match="H x W"):
            ds.relative_to_disparity(np.zeros((2, 3, 4)))

    def test_model_output_kind(self):
        kind = ds.model_output_kind
        ns = SimpleNamespace
        assert (
            kind(ns(model_type="depth_anything", depth_estimation_type="relative")) == ds.RELATIVE
        )
        assert kind(ns(model_type="depth_anything", depth_estimation_type="metric")) == ds.METRIC
        assert kind(ns(model_type="dpt", backbone_config=None)) == ds.RELATIVE
        assert kind(ns(model_type="dpt", backbone_config=ns(model_type="dinov2"))) == ds.METRIC
        for metric in ("zoedepth", "depth_pro", "glpn"):
            assert kind(ns(model_type=metric)) == ds.METRIC


# ------------------------------------------------------------------------------ sources


class TestLocalSources:
    def test_embedded(self):
        image = _photo()
        disp = np.tile(np.linspace(0, 1, 32, dtype=np.float32), (20, 1))  # half size
        photo = Photo(image=image, info=None, disparity=disp, focus=0.4)
        photo.depth_info = {"source": "apple_mpo"}
        got = ds.depth_map("embedded", image, photo=photo)
        assert got.disparity.shape == (40, 64) and got.focus == 0.4
        assert got.source == "embedded" and got.output == "apple_mpo phone depth"
        assert got.disparity[:, 0].mean() < 0.05 and got.disparity[:, -1].mean() > 0.95
        with pytest.raises(ValueError, match="no phone depth"):
            ds.depth_map("embedded", image, photo=Photo(image=image, info=None))
        # phone depth of another shape than the photo is refused, not stretched onto it
        turned = Photo(image=image, info=None, disparity=np.ascontiguousarray(disp.T))
        with pytest.raises(ValueError, match=r"embedded depth: depth map is 20x32 .* rotated"):
            ds.depth_map("embedded", image, photo=turned)
        with pytest.raises(ValueError, match="no phone depth"):
            ds.depth_map("embedded", image)

    def test_file(self, tmp_path):
        image = _photo()
        depth = np.tile(np.linspace(1.0, 5.0, 64), (40, 1))  # metres: left is near
        np.save(tmp_path / "d.npy", depth)
        got = ds.depth_map(f"file:{tmp_path / 'd.npy'}", image, file_kind="depth")
        assert got.disparity.shape == (40, 64) and got.output == "depth map"
        assert got.disparity[:, 0].mean() > 0.95 and got.disparity[:, -1].mean() < 0.05
        with pytest.raises(ValueError, match="no such file"):
            ds.depth_map(f"file:{tmp_path / 'missing.png'}", image)

    def test_d2f(self, tiny_checkpoint):
        model = D2F.from_checkpoint(tiny_checkpoint)
        image = _photo(48, 64)
        got = ds.depth_map("d2f", image, model=model)
        scene = model.prepare(image, refine=False)
        assert got.source == "d2f" and got.disparity.shape == (48, 64)
        expected = resize(scene.disparity_lr, (48, 64))[0, 0].numpy()
        np.testing.assert_allclose(got.disparity, expected, atol=1e-5)
        with pytest.raises(ValueError, match="needs the D2F model"):
            ds.depth_map("d2f", image)


# ------------------------------------------------------------------------------ hub models

transformers = pytest.importorskip("transformers", reason="the hub extra is not installed")

from _tiny_hub import save_depth_anything, save_dpt  # noqa: E402


def _reference(folder, image: np.ndarray) -> np.ndarray:
    """The model's own prediction at the photo's size, straight from transformers."""
    processor = transformers.AutoImageProcessor.from_pretrained(
        folder, **ds._processor_options(transformers)
    )
    model = transformers.AutoModelForDepthEstimation.from_pretrained(folder).eval()
    pixels = np.round(image * 255).astype(np.uint8)
    with torch.no_grad():
        out = model(**processor(images=pixels, return_tensors="pt"))
    post = processor.post_process_depth_estimation(out, target_sizes=[image.shape[:2]])
    return post[0]["predicted_depth"].numpy()


@pytest.fixture(scope="module")
def hub_folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("hub")
    folders = {"da": root / "da", "da_metric": root / "da_metric", "dpt": root / "dpt"}
    save_depth_anything(folders["da"])
    save_depth_anything(folders["da_metric"], metric=True)
    save_dpt(folders["dpt"])
    return folders


class TestHubModels:
    @pytest.mark.parametrize(
        "name, kind, sign",
        [("da", ds.RELATIVE, 1.0), ("dpt", ds.RELATIVE, 1.0), ("da_metric", ds.METRIC, -1.0)],
    )
    def test_local_folder(self, hub_folders, name, kind, sign, monkeypatch):
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # a folder never needs the hub
        folder = hub_folders[name]
        image = _photo(40, 64)
        got = ds.depth_map(f"transformers:{folder}", image)
        assert got.source == f"transformers:{folder}" and got.output == kind
        d = got.disparity
        assert d.shape == (40, 64) and d.dtype == np.float32
        assert d.min() == 0.0 and d.max() == 1.0
        # orientation: 1 = near. Relative inverse depth keeps the model's order, metric
        # depth reverses it (percentile clipping ties only the extremes)
        reference = _reference(folder, image)
        assert np.ptp(reference) > 0
        assert sign * _spearman(d, reference) > 0.98

    def test_large_photo_is_shrunk_first(self, hub_folders, monkeypatch):
        monkeypatch.setattr(ds, "HUB_MAX_SIDE", 32)
        got = ds.depth_map(f"transformers:{hub_folders['da']}", _photo(60, 96))
        assert got.disparity.shape == (60, 96)
        assert 0.0 <= got.disparity.min() < got.disparity.max() <= 1.0

    def test_prepare_records_the_source(self, hub_folders, tiny_checkpoint):
        model = D2F.from_checkpoint(tiny_checkpoint)
        image = _photo(48, 64)
        source = f"transformers:{hub_folders['dpt']}"
        scene = model.prepare(image, depth=source)
        assert scene.disparity_source == source
        assert scene.disparity_output == ds.RELATIVE
        # the same pass and the same refinement as any given map
        expected = ds.depth_map(source, image).disparity
        ref = model.prepare(image, depth=expected)
        torch.testing.assert_close(scene.disparity_lr, ref.disparity_lr)
        assert ref.disparity_source == "given"

    def test_model_stays_loaded(self, hub_folders):
        source = f"transformers:{hub_folders['da']}"
        ds.depth_map(source, _photo())
        first = ds._LOADED[(str(hub_folders["da"]), "cpu")]
        ds.depth_map(source, _photo(seed=1))
        assert ds._LOADED[(str(hub_folders["da"]), "cpu")] is first


class TestHubErrors:
    def test_extra_missing(self, monkeypatch, tmp_path):
        monkeypatch.setitem(sys.modules, "transformers", None)  # import fails
        with pytest.raises(ValueError, match=r"hub extra.*d2f\[hub\]"):
            ds.depth_map(f"transformers:{tmp_path}", _photo())
        assert not ds.hub_available()

    def test_not_cached_while_offline(self, monkeypatch):
        monkeypatch.setenv("HF_HUB_OFFLINE", "1")
        with pytest.raises(ValueError, match="not in the local Hugging Face cache.*HF_HUB_OFFLINE"):
            ds.depth_map("transformers:d2f-tests/no-such-depth-model", _photo())

    def test_folder_without_a_model(self, tmp_path):
        with pytest.raises(ValueError, match="holds no depth-estimation model"):
            ds.depth_map(f"transformers:{tmp_path}", _photo())

    def test_folder_with_another_kind_of_model(self, tmp_path):
        from transformers import BertConfig, BertModel, DPTImageProcessor

        BertModel(
            BertConfig(
                vocab_size=16,
                hidden_size=8,
                num_hidden_layers=1,
                num_attention_heads=2,
                intermediate_size=8,
            )
        ).save_pretrained(tmp_path)
        DPTImageProcessor().save_pretrained(tmp_path)
        with pytest.raises(ValueError, match="holds no depth-estimation model"):
            ds.depth_map(f"transformers:{tmp_path}", _photo())

    def test_missing_folder(self, tmp_path):
        with pytest.raises(ValueError, match="no such folder"):
            ds.depth_map(f"transformers:{tmp_path / 'nothing'}", _photo())


# ------------------------------------------------------------------------------ refinement


class TestRefinement:
    """``D2F.refine_disparity``: what ``prepare`` runs on every source's map."""

    @staticmethod
    def _model() -> D2F:
        return D2F.from_config({"network_size": 64, "max_render_side": 256})

    @staticmethod
    def _step(n: int = 96, edge: int = 40):
        """A photo with a colour edge at column ``edge`` and the depth step as a low-res
        map sees it: 2 px to the right and blurred over 7 px (the refinement window is 3 px
        at this size)."""
        torch.manual_seed(0)
        cols = torch.arange(n)
        near = (cols < edge).float().expand(n, n)
        image = torch.stack([0.2 + 0.6 * near, 0.6 - 0.3 * near, 0.4 + 0 * near])[None]
        image = (image + 0.03 * torch.rand(1, 3, n, n)).clamp(0, 1)
        shifted = (cols < edge + 2).float().expand(n, n)[None, None]
        soft = box_mean(shifted, 3)
        return image, near[None, None], soft

    def test_pulls_a_blurred_step_onto_the_photo_edge(self):
        image, truth, soft = self._step()
        out = self._model().refine_disparity(image, soft)
        err_before = float((soft - truth).abs().mean())
        err_after = float((out - truth).abs().mean())
        assert err_after < 0.35 * err_before  # 0.024 -> 0.007
        # the edge (where the map crosses 0.5) sits on the photo's edge, at column 40
        crossing = (out[0, 0] > 0.5).sum(1).float().median()
        assert abs(float(crossing) - 40) <= 1

    def test_flat_map_unchanged_and_range_kept(self):
        model = self._model()
        image, _, _ = self._step()
        flat = torch.full((1, 1, 96, 96), 0.3)
        torch.testing.assert_close(model.refine_disparity(image, flat), flat)
        noisy = torch.rand(1, 1, 96, 96)
        out = model.refine_disparity(image, noisy)
        assert 0.0 <= float(out.min()) and float(out.max()) <= 1.0

    def test_same_for_every_source_and_switchable(self, tmp_path):
        model = self._model()
        image, _, soft = self._step(64, 24)
        photo = image[0].permute(1, 2, 0).numpy()
        lr = model.pass_size((64, 64), given=True)
        image_lr = resize(image, lr).clamp(0, 1)
        expected = model.refine_disparity(image_lr, resize(soft, lr).clamp(0, 1))
        np.save(tmp_path / "map.npy", soft[0, 0].numpy())
        wrapped = Photo(image=photo, info=None, disparity=soft[0, 0].numpy())
        scenes = {
            "array": model.prepare(photo, depth=soft[0, 0].numpy()),
            "file": model.prepare(photo, depth=f"file:{tmp_path / 'map.npy'}"),
            "embedded": model.prepare(wrapped, depth="embedded"),
        }
        for name, scene in scenes.items():
            assert scene.refined
            torch.testing.assert_close(scene.disparity_lr, expected, msg=name, atol=1e-5, rtol=0)
        off = model.prepare(photo, depth=soft[0, 0].numpy(), refine=False)
        assert not off.refined
        torch.testing.assert_close(off.disparity_lr, resize(soft, lr).clamp(0, 1))
        assert scenes["file"].disparity_source == f"file:{tmp_path / 'map.npy'}"
        assert scenes["embedded"].disparity_source == "embedded"

    def test_prepare_arguments(self):
        model = self._model()
        image = _photo(32, 32)
        with pytest.raises(ValueError, match="not both"):
            model.prepare(image, np.zeros((4, 4)), depth="d2f")
        with pytest.raises(ValueError, match="unknown depth source"):
            model.prepare(image, depth="midas")
        assert model.prepare(image, depth="d2f").disparity_source == "d2f"


def test_import_touches_no_hub():
    """Importing the package and the registry loads neither transformers nor huggingface_hub."""
    import subprocess

    code = (
        "import sys, d2f_core.pipeline, d2f_core.depth.sources, d2f_core.cli; "
        "bad = [m for m in ('transformers', 'huggingface_hub') if m in sys.modules]; "
        "sys.exit(', '.join(bad) or None)"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr


# ------------------------------------------------------------------------------ the CLI


class TestCli:
    @staticmethod
    def _write_photo(path):
        from d2f_core.io import save_image

        save_image(path, _photo(48, 64))
        return path

    def test_render_with_a_local_hub_model(self, hub_folders, tiny_checkpoint, tmp_path, capsys):
        from d2f_core.cli import main
        from d2f_core.io import load_image

        photo = self._write_photo(tmp_path / "p.png")
        out = tmp_path / "out.png"
        source = f"transformers:{hub_folders['da']}"
        argv = ["render", str(photo), "-o", str(out), "--blur", "8", "--focus", "0.5"]
        code = main([*argv, "--depth-model", source, "--weights", str(tiny_checkpoint), "-v"])
        err = capsys.readouterr().err
        assert code == 0, err
        assert f"depth from {source} (relative inverse depth)" in err
        assert load_image(out).shape == (48, 64, 3)

    def test_hub_model_without_weights(self, hub_folders, tmp_path, capsys, monkeypatch):
        from d2f_core.cli import main

        monkeypatch.setenv("D2F_WEIGHTS", str(tmp_path / "none.pt"))
        photo = self._write_photo(tmp_path / "p.png")
        argv = ["render", str(photo), "-o", str(tmp_path / "o.png"), "--blur", "8"]
        code = main([*argv, "--depth-model", f"transformers:{hub_folders['dpt']}"])
        assert code == 0, capsys.readouterr().err
        assert (tmp_path / "o.png").is_file()

    def test_clear_failures(self, tmp_path, capsys, monkeypatch, tiny_checkpoint):
        from d2f_core.cli import main

        photo = self._write_photo(tmp_path / "p.png")
        base = ["render", str(photo), "-o", str(tmp_path / "o.png"), "--blur", "8"]
        base += ["--weights", str(tiny_checkpoint)]
        assert main([*base, "--depth-model", "midas"]) == 2
        assert "unknown depth source 'midas'" in capsys.readouterr().err
        assert main([*base, "--depth-model", "embedded"]) == 1
        err = capsys.readouterr().err.strip()
        assert "carries no phone depth" in err and len(err.splitlines()) == 1
        monkeypatch.setitem(sys.modules, "transformers", None)
        assert main([*base, "--depth-model", f"transformers:{tmp_path}"]) == 1
        err = capsys.readouterr().err.strip()
        assert "d2f[hub]" in err and "Traceback" not in err
        np.save(tmp_path / "d.npy", np.ones((48, 64)))
        file_twice = ["--depth", str(tmp_path / "d.npy"), "--depth-model", "file:x.npy"]
        assert main([*base, *file_twice]) == 2
        for source in ("d2f", "scene"):  # --depth and another source: two maps asked for
            assert main([*base, "--depth", str(tmp_path / "d.npy"), "--depth-model", source]) == 2
            assert "name two depth sources" in capsys.readouterr().err

    @pytest.mark.slow
    def test_d2f_asked_of_weights_whose_own_source_is_scene(self, tmp_path, capsys):
        """``--depth-model d2f`` with weights that default to the scene source renders the
        network's own map: the same picture as the same weights whose own source is d2f. The
        default render of those weights, and the batch manifest, name the scene source."""
        from conftest import TINY_CONFIG

        from d2f_core.batch.manifest import read_rows
        from d2f_core.cli import main
        from d2f_core.io import load_image

        weights = {}
        for own in ("d2f", "scene"):
            torch.manual_seed(0)
            weights[own] = tmp_path / f"{own}.pt"
            D2F.from_config({**TINY_CONFIG, "depth_source": own}).save(weights[own])
        (tmp_path / "in").mkdir()
        photo = self._write_photo(tmp_path / "in" / "p.png")
        base = ["render", str(photo), "--blur", "8", "--focus", "0.5", "-v"]

        def render(name, *extra):
            assert main([*base, "-o", str(tmp_path / name), *extra]) == 0
            return load_image(tmp_path / name), capsys.readouterr().err

        own_d2f, _ = render("own_d2f.png", "--weights", str(weights["d2f"]))
        asked, err = render("asked.png", "--weights", str(weights["scene"]), "--depth-model", "d2f")
        assert "depth from d2f (asked)" in err
        np.testing.assert_array_equal(asked, own_d2f)
        default, err = render("default.png", "--weights", str(weights["scene"]))
        assert "depth from scene (the weights' own source)" in err
        assert np.abs(default - asked).max() > 0.05  # another map, another picture
        out = tmp_path / "batch"
        argv = ["batch", "--workers", "1", str(tmp_path / "in"), "-o", str(out), "--blur", "8"]
        assert main([*argv, "--weights", str(weights["scene"])]) == 0, capsys.readouterr().err
        (row,) = read_rows(out / "manifest.jsonl")
        assert row["depth_source"].startswith("scene (scene teachers' map (parse"), row


# ------------------------------------------------------------------------------ the app


class TestApp:
    """The app's "Depth source" control (app/sources.py, RefocusApp.load)."""

    @pytest.fixture(autouse=True)
    def any_model(self, monkeypatch):
        """The server as ``d2f-app --allow-any-depth-model`` runs it (local use): any id or
        folder may be named (tests/test_app_depth_models.py checks the other policies)."""
        pytest.importorskip("gradio", reason="the app extra is not installed")
        from app import sources

        monkeypatch.setattr(sources, "POLICY", sources.HubPolicy(any_model=True))

    @pytest.fixture
    def logic(self, tiny_model, tmp_path):
        from app.cache import SceneCache
        from app.handlers import RefocusApp

        return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "dl")

    def test_choices(self, monkeypatch):
        from app import sources

        values = [v for _, v in sources.choices()]
        assert values == ["auto", "embedded", "file", "scene", "d2f", "transformers"]
        assert "embedded" not in [v for _, v in sources.choices(has_embedded=False)]
        monkeypatch.setattr(ds, "hub_available", lambda: False)
        assert "transformers" not in [v for _, v in sources.choices()]
        with pytest.raises(ValueError, match=r"d2f\[hub\]"):
            sources.resolve("transformers", "x/y", False, False)

    def test_describe_names_what_ran(self):
        from types import SimpleNamespace

        from app import sources

        ran = "scene teachers' map (parse, depth, objects, network)"
        scene = SimpleNamespace(disparity_source="scene", disparity_output=ran)
        assert sources.describe(scene, "x") == ran
        assert sources.describe(SimpleNamespace(disparity_source="d2f"), "x") == (
            "shipped network (d2f)"
        )
        assert sources.describe(SimpleNamespace(disparity_source="file"), "your map") == (
            "your map"
        )

    def test_resolve(self, monkeypatch):
        from app.sources import resolve

        monkeypatch.setattr(ds, "hub_model_cached", lambda name: name == "org/model")
        assert resolve("auto", "", True, True) == ("file", "")
        assert resolve(None, "", False, True) == ("embedded", "")
        assert resolve("auto", "", False, False) == ("d2f", "")
        # the automatic source ends in the weights' own default (scene for the shipped ones)
        assert resolve("auto", "", False, False, "scene") == ("scene", "")
        assert resolve("auto", "", False, True, "scene") == ("embedded", "")
        assert resolve("d2f", "", True, True) == ("d2f", "")
        assert resolve("scene", "", False, False) == ("scene", "")
        assert resolve("transformers", " org/model ", False, False) == (
            "transformers:org/model",
            "",
        )
        source, note = resolve("embedded", "", False, False)  # falls back, and says so
        assert source == "d2f" and "no phone depth" in note
        with pytest.raises(ValueError, match="Name a Hugging Face depth model"):
            resolve("transformers", "  ", False, False)

    def test_switching_sources(self, logic, two_plane_scene, hub_folders):
        photo, disp = str(two_plane_scene.photo), str(two_plane_scene.disparity)
        args = (disp, "disparity", None, 0.5, 40.0, 0, 0.0, True, True, "Bokeh", "balanced")
        mine = logic.load(photo, *args, "auto", "")
        assert mine[0].scene.disparity_source == "file"
        net = logic.load(photo, *args, "d2f", "")
        assert net[0].scene.disparity_source == "d2f" and "shipped network" in net[-1]
        assert net[0].scene is not mine[0].scene  # the cache keys on the source
        hub = f"transformers:{hub_folders['da']}"
        out = logic.load(photo, *args, "transformers", str(hub_folders["da"]))
        assert out[0].scene.disparity_source == hub
        assert f"depth: {hub} (relative inverse depth)" in out[-1]
        assert "cached scene" not in out[-1]
        back = logic.load(photo, *args, "auto", "")  # back to the user's map: cached
        assert "cached scene" in back[-1] and back[0].scene is mine[0].scene

    def test_clear_errors(self, logic, two_plane_scene, tmp_path):
        import gradio as gr

        photo = str(two_plane_scene.photo)
        args = (None, "disparity", None, 0.5, 40.0, 0, 0.0, True, True, "Bokeh", "balanced")
        with pytest.raises(gr.Error, match="Name a Hugging Face depth model"):
            logic.load(photo, *args, "transformers", "")
        with pytest.raises(gr.Error, match="nor a folder holding a model"):
            logic.load(photo, *args, "transformers", str(tmp_path))
        # the photo's own depth on a photo without any: the network, with a note
        out = logic.load(photo, *args, "embedded", "")
        assert out[0].scene.disparity_source == "d2f"
