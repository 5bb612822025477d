"""The ``d2f`` command: exit statuses, error messages, depth sources, batch behaviour."""

from __future__ import annotations

import io
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from _io_writers import lensblur_jpeg
from PIL import Image, ImageCms

from d2f_core.cli import main
from d2f_core.io import load_image, save_depth
from d2f_core.photo_render import render_with_depth_only

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(autouse=True)
def no_shipped_weights(monkeypatch, tmp_path):
    """Every test starts without default weights, like a fresh clone before training."""
    monkeypatch.setenv("D2F_WEIGHTS", str(tmp_path / "no-such-weights.pt"))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    from d2f_core.pipeline import D2F

    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    D2F.from_config({"network_size": 64}).save(path)
    return path


def _scene(h: int = 48, w: int = 64, seed: int = 0):
    """A textured photo: left half near (disparity 1), right half far (0)."""
    rng = np.random.default_rng(seed)
    img = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    disp = np.zeros((h, w), np.float32)
    disp[:, : w // 2] = 1.0
    return img, disp


def _grad(img: np.ndarray) -> float:
    g = img.mean(axis=2)
    return float(np.mean(np.abs(np.diff(g, axis=1))))


def _write_photo(path: Path, img: np.ndarray, **params) -> Path:
    Image.fromarray(img).save(path, **params)
    return path


def _run(capsys, *argv) -> tuple[int, str]:
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def _batch(capsys, *argv) -> tuple[int, str]:
    """``d2f batch`` with one worker, in this process (tests/test_batch.py runs the pools)."""
    return _run(capsys, "batch", "--workers", 1, *argv)


class TestUsage:
    def test_help(self, capsys):
        assert main(["--help"]) == 0
        assert "render" in capsys.readouterr().out
        assert main(["render", "--help"]) == 0
        assert "--focus-at" in capsys.readouterr().out

    @pytest.mark.parametrize(
        "argv",
        [
            [],
            ["render"],
            ["render", "in.jpg", "--blur", "10"],  # no -o
            ["render", "in.jpg", "-o", "o.jpg"],  # no --blur
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "-1"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "1e9"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--focus", "1.5"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--focus", "0", "--focus-at", "1,2"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--focus-at", "12"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--aperture-blades", "2"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--max-pixels", "-1"],
            ["render", "in.jpg", "-o", "o.jpg", "--blur", "5", "--depth-kind", "metres"],
            ["frobnicate"],
        ],
    )  # fmt: skip
    def test_bad_command_lines_exit_2(self, capsys, argv):
        code, err = _run(capsys, *argv)
        assert code == 2
        # one line, pointing at the help of the command it belongs to; no usage block
        assert err.count("\n") == 1 and err.startswith("d2f: error:"), err
        assert err.rstrip().endswith("--help')")

    def test_output_equal_to_input_refused(self, tmp_path, capsys):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        before = src.read_bytes()
        code, err = _run(capsys, "render", src, "-o", tmp_path / "." / "photo.png", "--blur", 5)
        assert code == 2 and "is the input photo" in err and err.count("\n") == 1
        # refused after parsing, worded as the parser's own refusals
        assert err.startswith("d2f: error: output ")
        assert err.rstrip().endswith("(see 'd2f render --help')"), err
        assert src.read_bytes() == before
        code, err = _run(capsys, "batch", tmp_path, "-o", tmp_path, "--blur", 5)
        assert code == 2 and err.count("\n") == 1, err
        assert err.rstrip().endswith("(see 'd2f batch --help')"), err

    def test_an_output_folder_that_cannot_be_written_is_refused_before_rendering(
        self, tmp_path, capsys, monkeypatch
    ):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        rendered = []
        monkeypatch.setattr(
            "d2f_core.photo_render.render_file", lambda *a: rendered.append(a)
        )  # never reached: each output below is refused first
        code, err = _run(capsys, "render", src, "-o", tmp_path / "photo.png" / "x.png", "--blur", 5)
        assert code == 1 and err.count("\n") == 1, err
        assert "'photo.png' is not a folder" in err.replace(os.fspath(tmp_path) + "/", "")
        code, err = _run(capsys, "render", src, "-o", tmp_path / "none" / "x.png", "--blur", 5)
        assert code == 1 and "does not exist" in err
        if os.geteuid() != 0:  # root writes in any folder whatever its mode
            locked = tmp_path / "locked"
            locked.mkdir(mode=0o555)
            code, err = _run(capsys, "render", src, "-o", locked / "x.png", "--blur", 5)
            assert code == 1 and "cannot write in" in err and "Permission denied" in err, err
            assert ".tmp" not in err  # the output is named, not a temporary file
        assert rendered == []

    def test_batch_with_a_depth_folder_and_a_depth_model_is_refused_up_front(
        self, tmp_path, capsys
    ):
        img, _ = _scene()
        (tmp_path / "in").mkdir()
        (tmp_path / "maps").mkdir()
        _write_photo(tmp_path / "in" / "a.png", img)
        argv = ["--depth", tmp_path / "maps", "--depth-model", "d2f", "--blur", 5]
        code, err = _batch(capsys, tmp_path / "in", "-o", tmp_path / "out", *argv)
        assert code == 2 and err.count("\n") == 1, err
        assert "--depth DIR and --depth-model d2f name two depth sources" in err
        assert not (tmp_path / "out").exists()

    def test_unknown_output_extension(self, tmp_path, capsys):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        code, err = _run(capsys, "render", src, "-o", tmp_path / "out.gif", "--blur", 5)
        assert code == 2 and "extension" in err


class TestOneLine:
    """Each refusal is one line that names the problem as it is."""

    def test_unusable_default_weights_said_once(self, tmp_path, capsys, monkeypatch):
        img, disp = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        (tmp_path / "empty.pt").write_bytes(b"")
        monkeypatch.setenv("D2F_WEIGHTS", str(tmp_path / "empty.pt"))
        code, err = _run(capsys, "render", src, "-o", tmp_path / "o.png", "--blur", 5)
        # no render without weights nor map: the error says why, and nothing else is printed
        assert code == 1 and err.count("\n") == 1 and "empty.pt cannot be read" in err, err
        save_depth(tmp_path / "depth.png", disp)
        argv = ["-o", tmp_path / "o.png", "--blur", 5, "--depth", tmp_path / "depth.png"]
        code, err = _run(capsys, "render", src, *argv, "--focus", 1.0)
        # a render that goes on without them warns, once
        assert code == 0 and err.count("\n") == 1, err
        assert err.startswith("d2f: warning: D2F weights unusable (") and "empty.pt" in err

    def test_each_message_names_the_problem(self, tmp_path, capsys, checkpoint):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        out = ["-o", tmp_path / "o.png", "--blur", 5]
        cases = [
            (["--weights", tmp_path], 1, f"--weights {str(tmp_path)!r}: is a folder"),
            (["--weights", checkpoint, "--focus", 0.5, "--save-maps", src], 1,
             f"--save-maps {src}: a file, not a folder"),
            (["--f-number", -2], 2, "expected an f-number in [0.5, 1000], got '-2'"),
            (["--depth-model", "file:"], 2, "needs a map file: write file:PATH"),
            (["--depth-model", "transformers:"], 2, "a folder: write transformers:MODEL"),
        ]  # fmt: skip
        for extra, status, words in cases:
            code, err = _run(capsys, "render", src, *out, *extra)
            assert code == status and err.count("\n") == 1 and words in err, (extra, err)
        assert not (tmp_path / "o.png").exists()

    def test_a_picture_too_long_for_its_format_is_refused_before_the_render(
        self, tmp_path, capsys, checkpoint, monkeypatch
    ):
        src = _write_photo(tmp_path / "long.png", np.zeros((2, 16384, 3), np.uint8))
        rendered = []
        monkeypatch.setattr(
            "d2f_core.photo_render._render_with_model", lambda *a: rendered.append(a)
        )
        argv = ["-o", tmp_path / "o.webp", "--blur", 5, "--weights", checkpoint, "--focus", 0.5]
        code, err = _run(capsys, "render", src, *argv)
        assert code == 1 and err.count("\n") == 1 and rendered == [], err
        assert "cannot save 'o.webp': WEBP holds at most 16383 px a side" in err
        assert "16384x2; save it as .png or .tif" in err

    def test_ctrl_c_while_the_arguments_are_checked(self, tmp_path, capsys, monkeypatch):
        """The blur's check imports the renderer (torch, about a second): Ctrl-C then is an
        interruption like any other, not a traceback."""
        import d2f_core.cli as cli

        def interrupted(text):
            raise KeyboardInterrupt

        monkeypatch.setattr(cli, "_blur_px", interrupted)
        code, err = _run(
            capsys, "render", tmp_path / "p.png", "-o", tmp_path / "o.png", "--blur", 5
        )
        assert (code, err) == (130, "d2f: interrupted\n")

    def test_a_line_break_in_a_name_stays_in_the_line(self, tmp_path, capsys):
        missing = tmp_path / "a\nb.png"
        code, err = _run(capsys, "render", missing, "-o", tmp_path / "o.png", "--blur", 5)
        assert code == 1 and err.count("\n") == 1 and "a\\nb.png: no such file" in err, err
        src = _write_photo(tmp_path / "p\nq.png", _scene()[0])
        code, err = _run(capsys, "render", src, "-o", tmp_path / "o\n.gif", "--blur", 5)
        assert code == 2 and err.count("\n") == 1 and "o\\n.gif" in err, err


class TestRender:
    def test_with_depth_file_and_no_weights(self, tmp_path, capsys):
        img, disp = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        save_depth(tmp_path / "depth.png", disp)
        out = tmp_path / "out.png"
        code, err = _run(
            capsys, "render", src, "-o", out, "--blur", 12, "--depth", tmp_path / "depth.png",
            "--focus", 1.0, "-v",
        )  # fmt: skip
        assert code == 0, err
        res = load_image(out)
        assert res.shape == (48, 64, 3)
        # near half in focus stays the input, far half is blurred
        np.testing.assert_allclose(res[:, :28], img[:, :28] / 255.0, atol=1 / 255)
        assert _grad(res[:, 36:]) < 0.3 * _grad(img[:, 36:] / 255.0)
        assert "no D2F weights" in err

    def test_placement(self, tmp_path, capsys):
        # a far half 3.6 px of CoC behind focus: "nearest" gives it the 5 px kernel (a 4 px
        # disc), "paper" the 3 px one (gradient energy 0.0056 against 0.0164 measured)
        img, disp = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        save_depth(tmp_path / "depth.png", disp)
        outs = {}
        for placement in ("nearest", "paper"):
            outs[placement] = tmp_path / f"{placement}.png"
            code, err = _run(
                capsys, "render", src, "-o", outs[placement], "--blur", 3.6, "--focus", 1.0,
                "--depth", tmp_path / "depth.png", "--placement", placement, "--no-fusion",
            )  # fmt: skip
            assert code == 0, err
        far = {p: _grad(load_image(o)[:, 40:]) for p, o in outs.items()}
        assert far["nearest"] < 0.9 * far["paper"]
        code, err = _run(
            capsys, "render", src, "-o", tmp_path / "x.png", "--blur", 3, "--focus", 1.0,
            "--depth", tmp_path / "depth.png", "--placement", "middle",
        )  # fmt: skip
        assert code == 2 and "placement" in err

    def test_metric_depth_and_near_dark(self, tmp_path, capsys):
        img, disp = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        np.save(tmp_path / "z.npy", np.where(disp > 0.5, 1.0, 5.0))  # left is 1 m away
        save_depth(tmp_path / "inv.png", 1.0 - disp)  # stored dark = near
        outs = []
        for i, extra in enumerate(
            [
                ["--depth", tmp_path / "z.npy", "--depth-kind", "depth"],
                ["--depth", tmp_path / "inv.png", "--near", "dark"],
            ]
        ):
            out = tmp_path / f"o{i}.png"
            code, err = _run(capsys, "render", src, "-o", out, "--blur", 12, "--focus", 1, *extra)
            assert code == 0, err
            outs.append(load_image(out))
        np.testing.assert_allclose(outs[0], outs[1], atol=2 / 255)
        np.testing.assert_allclose(outs[0][:, :28], img[:, :28] / 255.0, atol=1 / 255)

    def test_no_depth_no_weights_is_a_clear_failure(self, tmp_path, capsys):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        code, err = _run(capsys, "render", src, "-o", tmp_path / "o.png", "--blur", 5)
        assert code == 1
        assert err.startswith("d2f: error:") and "--depth" in err and "--weights" in err
        assert not (tmp_path / "o.png").exists()

    def test_weights_without_depth(self, tmp_path, capsys, checkpoint):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        out = tmp_path / "o.jpg"
        code, err = _run(
            capsys, "render", src, "-o", out, "--blur", 8, "--weights", checkpoint,
            "--focus-at", "10,10", "--aperture-blades", 6, "--rotation", 15,
            "--save-maps", tmp_path / "maps",
        )  # fmt: skip
        assert code == 0, err
        assert load_image(out).shape == (48, 64, 3)
        for name in ("disparity", "defocus", "fusion_mask"):
            assert (tmp_path / "maps" / f"o_{name}.png").is_file()

    def test_save_maps_writes_every_map_at_the_photos_size(self, tmp_path, capsys, checkpoint):
        # 200x150: the network's low-resolution pass (and so the defocus map) is smaller
        img = np.random.default_rng(0).integers(0, 256, (150, 200, 3), dtype=np.uint8)
        src = _write_photo(tmp_path / "photo.png", img)
        depth = tmp_path / "d.npy"
        np.save(depth, np.tile(np.linspace(1, 0, 200, dtype=np.float32), (150, 1)))
        for args in ((), ("--depth", depth)):
            maps = ("--save-maps", tmp_path / "maps")
            code, err = _run(capsys, "render", src, "-o", tmp_path / "o.jpg", "--blur", 8,
                             "--weights", checkpoint, *maps, *args)  # fmt: skip
            assert code == 0, err
            for name in ("disparity", "defocus", "fusion_mask"):
                assert load_image(tmp_path / "maps" / f"o_{name}.png").shape[:2] == (150, 200)

    def test_quality_sets_the_error_budget(self, tmp_path, capsys, checkpoint):
        img, _ = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        depth = tmp_path / "d.npy"
        # a slope: CoCs of every size (a two-plane map has two, and every budget draws both)
        np.save(depth, np.tile(np.linspace(1, 0, img.shape[1], dtype=np.float32), (48, 1)))
        picked = {}
        for quality in ("high", "fast"):
            code, err = _run(
                capsys, "render", src, "-o", tmp_path / f"{quality}.png", "--blur", 400,
                "--focus", 1.0, "--depth", depth, "--weights", checkpoint, "--quality", quality,
                "-v",
            )  # fmt: skip
            assert code == 0, err
            layers, preset = err.split(" preset")[0].rsplit(" ", 3)[-3::2]
            picked[quality] = (int(layers), preset)
        # CoCs over 128 px at the low-res pass: only the 30 dB budget affords the coarse grids
        assert picked["high"] == (15, "balanced") and picked["fast"] == (15, "fast")
        # every CoC under a pixel: the picker returns the input
        out = tmp_path / "same.png"
        code, err = _run(capsys, "render", src, "-o", out, "--blur", 0.5, "--focus", 0.5,
                         "--depth", depth, "--weights", checkpoint, "-v")  # fmt: skip
        assert code == 0 and "input shown" in err
        np.testing.assert_array_equal(load_image(out), load_image(src))
        code, err = _run(capsys, "render", src, "-o", out, "--blur", 5, "--quality", "best")
        assert code == 2 and "--quality" in err

    def test_bad_weights(self, tmp_path, capsys):
        img, disp = _scene()
        src = _write_photo(tmp_path / "photo.png", img)
        (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
        code, err = _run(
            capsys, "render", src, "-o", tmp_path / "o.png", "--blur", 5,
            "--weights", tmp_path / "bad.pt",
        )  # fmt: skip
        assert code == 1 and "--weights" in err
        code, err = _run(
            capsys, "render", src, "-o", tmp_path / "o.png", "--blur", 5,
            "--weights", tmp_path / "missing.pt",
        )  # fmt: skip
        assert code == 1 and "missing.pt" in err

    def test_embedded_lens_blur_depth_and_focus(self, tmp_path, capsys):
        img, disp = _scene()
        z = np.where(disp > 0.5, 1.0, 4.0)
        blurred = np.full_like(img, 90)
        data = lensblur_jpeg(img, blurred, z, near=1.0, far=4.0, focal_distance=1.0)
        src = tmp_path / "lensblur.jpg"
        src.write_bytes(data)
        out = tmp_path / "o.png"
        code, err = _run(capsys, "render", src, "-o", out, "--blur", 12, "-v",
                         "--save-maps", tmp_path / "m")  # fmt: skip
        assert code == 0, err
        assert "embedded" in err and "focus 1.000" in err
        res = load_image(out)
        photo = load_image(io.BytesIO(data).getvalue())
        assert np.abs(photo - 90 / 255).max() < 0.02  # the file's main image is flat grey...
        # ...but the render starts from the embedded original: near half is the photo
        assert _grad(res[:, :28]) > 0.8 * _grad(img[:, :28] / 255.0)
        assert _grad(res[:, 36:]) < 0.3 * _grad(img[:, 36:] / 255.0)
        d = load_image(tmp_path / "m" / "o_disparity.png")[..., 0]
        assert d[:, :28].min() > 0.99 and d[:, 36:].max() < 0.01

    def test_icc_and_exif_carried_over(self, tmp_path, capsys):
        img, disp = _scene()
        srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
        exif = Image.Exif()
        exif[0x010F] = "CliTest"
        exif[0x0112] = 3
        src = _write_photo(
            tmp_path / "p.jpg", img, quality=95, icc_profile=srgb, exif=exif.tobytes()
        )
        save_depth(tmp_path / "d.png", disp[::-1, ::-1])  # depth of the upright photo
        out = tmp_path / "o.jpg"
        code, err = _run(
            capsys, "render", src, "-o", out, "--blur", 4, "--depth", tmp_path / "d.png"
        )
        assert code == 0, err
        with Image.open(out) as im:
            assert im.info.get("icc_profile") == srgb
            assert im.getexif().get(0x010F) == "CliTest"
            assert im.getexif().get(0x0112, 1) == 1

    def test_output_folder_and_max_pixels(self, tmp_path, capsys):
        img, disp = _scene(96, 128)
        src = _write_photo(tmp_path / "p.png", img)
        save_depth(tmp_path / "d.png", disp)
        (tmp_path / "out").mkdir()
        code, err = _run(
            capsys, "render", src, "-o", tmp_path / "out", "--blur", 4, "--depth",
            tmp_path / "d.png", "--max-pixels", 3072,
        )  # fmt: skip
        assert code == 0, err
        assert load_image(tmp_path / "out" / "p_bokeh.png").shape == (48, 64, 3)

    def test_focus_at_outside_photo(self, tmp_path, capsys):
        img, disp = _scene()
        src = _write_photo(tmp_path / "p.png", img)
        save_depth(tmp_path / "d.png", disp)
        code, err = _run(
            capsys, "render", src, "-o", tmp_path / "o.png", "--blur", 4,
            "--depth", tmp_path / "d.png", "--focus-at", "500,3",
        )  # fmt: skip
        assert code == 1 and "outside" in err

    @pytest.mark.parametrize("with_model", [False, True])
    def test_no_focus_given_focuses_on_the_subject(self, tmp_path, capsys, checkpoint,
                                                    with_model):  # fmt: skip
        """A near box off the centre, over a floor sloping away: with no focus given the box
        stays sharp and the floor blurs (the centre, where the floor is, was the old focus)."""
        h, w = 96, 128
        rng = np.random.default_rng(3)
        img = (rng.random((h, w, 3)) * 255).astype(np.uint8)
        disp = np.broadcast_to(np.linspace(0.0, 0.3, h, dtype=np.float32)[:, None], (h, w)).copy()
        disp[20:60, 10:50] = 0.9
        src = _write_photo(tmp_path / "p.png", img)
        save_depth(tmp_path / "d.png", disp)
        # K = 60 px puts the floor beyond the fusion gate, so the tiny model's random fusion
        # network cannot keep it sharp
        extra = ["--weights", checkpoint] if with_model else []
        argv = ["render", src, "-o", tmp_path / "o.png", "--blur", 60, "--depth",
                tmp_path / "d.png", *extra]  # fmt: skip
        code = main([str(a) for a in argv])
        said = capsys.readouterr()
        assert code == 0, said.err
        # where it focused is said without -v: a point on the box, at the box's disparity
        m = re.search(r"focused on the subject at \((\d+), (\d+)\), focal disparity ([\d.]+)",
                      said.out)  # fmt: skip
        assert m, said.out
        x, y, focus = int(m[1]), int(m[2]), float(m[3])
        assert 10 <= x < 50 and 20 <= y < 60 and focus > 0.85  # the box is the nearest
        assert main([str(a) for a in argv] + ["-q"]) == 0
        assert capsys.readouterr().out == ""
        out = np.asarray(Image.open(tmp_path / "o.png"))
        box = (slice(24, 56), slice(14, 46))
        floor = (slice(70, 96), slice(60, 128))
        assert _grad(out[box]) > 0.9 * _grad(img[box])
        assert _grad(out[floor]) < 0.5 * _grad(img[floor])

    def test_unreadable_input(self, tmp_path, capsys):
        bad = tmp_path / "broken.jpg"
        bad.write_bytes(b"\xff\xd8\xff\xe0garbage")
        code, err = _run(capsys, "render", bad, "-o", tmp_path / "o.png", "--blur", 4)
        assert code == 1 and "broken.jpg" in err and err.startswith("d2f: error:")
        code, err = _run(capsys, "render", tmp_path / "nope.jpg", "-o", tmp_path / "o.png",
                         "--blur", 4)  # fmt: skip
        assert code == 1 and "nope.jpg" in err


class TestBatch:
    def _folder(self, tmp_path: Path) -> tuple[Path, Path]:
        photos = tmp_path / "photos"
        depths = tmp_path / "depths"
        photos.mkdir()
        depths.mkdir()
        for i in range(2):
            img, disp = _scene(seed=i)
            _write_photo(photos / f"img{i}.png", img)
            save_depth(depths / f"img{i}_depth.png", disp)
        return photos, depths

    def test_all_good(self, tmp_path, capsys):
        photos, depths = self._folder(tmp_path)
        (photos / "notes.txt").write_text("not a photo")
        out = tmp_path / "out"
        code, err = _batch(capsys, photos, "-o", out, "--blur", 6, "--depth", depths,
                         "--focus", 1, "--format", "jpg")  # fmt: skip
        assert code == 0, err
        assert sorted(p.name for p in out.iterdir()) == [
            "img0_bokeh.jpg",
            "img1_bokeh.jpg",
            "manifest.jsonl",
        ]

    @pytest.mark.parametrize("tqdm", [True, False])
    def test_unreadable_file_is_skipped_and_reported(self, tmp_path, capsys, monkeypatch, tqdm):
        if not tqdm:  # tqdm is an extra: without it there is no bar, the same report
            monkeypatch.setitem(sys.modules, "tqdm", None)  # import tqdm raises ImportError
        photos, depths = self._folder(tmp_path)
        (photos / "corrupt.jpg").write_bytes(b"\xff\xd8\xff\xe0 truncated")
        out = tmp_path / "out"
        code, err = _batch(capsys, photos, "-o", out, "--blur", 6, "--depth", depths)
        assert code == 1
        assert "corrupt.jpg" in err and "1 of 3 photos failed" in err
        assert sorted(p.name for p in out.iterdir()) == [
            "img0_bokeh.png",
            "img1_bokeh.png",
            "manifest.jsonl",
        ]

    def test_an_unexpected_error_skips_one_file_only(self, tmp_path, capsys, monkeypatch):
        """A defect raising something other than ValueError (an IndexError from a reader)
        on one photo is reported for that photo, and the batch renders the others."""
        import d2f_core.photo_render as photo_render

        photos, depths = self._folder(tmp_path)
        real = photo_render.render_file

        def flaky(src, *args, **kwargs):
            if src.name == "img0.png":
                raise IndexError("list index out of range")
            return real(src, *args, **kwargs)

        monkeypatch.setattr(photo_render, "render_file", flaky)
        out = tmp_path / "out"
        # one worker renders in this process, where the patch is
        code, err = _batch(capsys, photos, "-o", out, "--blur", 6, "--depth", depths)
        assert code == 1
        assert "img0.png: unexpected IndexError: list index out of range" in err
        assert "1 of 2 photos failed" in err
        assert sorted(p.name for p in out.iterdir()) == ["img1_bokeh.png", "manifest.jsonl"]
        # the same defect in 'd2f render' is one line, without a traceback
        code, err = _run(capsys, "render", photos / "img0.png", "-o", out / "x.png", "--blur", 6,
                         "--depth", depths / "img0_depth.png")  # fmt: skip
        assert code == 1 and err.strip().count("\n") == 0
        assert err.startswith("d2f: error: unexpected IndexError")

    def test_output_folder_equal_to_input_refused(self, tmp_path, capsys):
        photos, depths = self._folder(tmp_path)
        before = sorted(p.name for p in photos.iterdir())
        code, err = _batch(capsys, photos, "-o", photos / ".", "--blur", 6)
        assert code == 2 and "differ" in err
        assert sorted(p.name for p in photos.iterdir()) == before

    def test_name_collisions_get_distinct_outputs(self, tmp_path, capsys):
        photos, depths = self._folder(tmp_path)
        img, _ = _scene(seed=5)
        _write_photo(photos / "img0.jpg", img, quality=95)
        out = tmp_path / "out"
        code, err = _batch(capsys, photos, "-o", out, "--blur", 6, "--depth", depths,
                         "--format", "png")  # fmt: skip
        assert code == 0, err
        assert len(list(out.glob("*.png"))) == 3

    def test_empty_folder_and_missing_weights(self, tmp_path, capsys):
        empty = tmp_path / "empty"
        empty.mkdir()
        code, err = _batch(capsys, empty, "-o", tmp_path / "o", "--blur", 6)
        assert code == 1 and "no photos" in err
        photos, _ = self._folder(tmp_path)
        code, err = _batch(capsys, photos, "-o", tmp_path / "o2", "--blur", 6)
        assert code == 1 and "2 of 2 photos failed" in err


class TestFallbackRenderer:
    def test_zero_blur_is_identity(self):
        img, disp = _scene()
        out = render_with_depth_only(img / 255.0, disp, 0.3, 0.0)
        np.testing.assert_allclose(out.bokeh, img / 255.0, atol=1e-6)

    def test_large_image_pass_is_capped(self):
        rng = np.random.default_rng(0)
        img = rng.random((600, 2100, 3)).astype(np.float32)
        disp = np.tile(np.linspace(0, 1, 2100, dtype=np.float32), (600, 1))
        out = render_with_depth_only(img, disp, 1.0, 20.0)
        assert out.bokeh.shape == img.shape
        assert out.maps["defocus"].shape == (293, 1024)
        # in-focus column (d = 1) is the input exactly, far side is smoothed
        np.testing.assert_allclose(out.bokeh[:, -1], img[:, -1], atol=1e-6)
        assert out.bokeh[:, :200].std() < 0.5 * img[:, :200].std()


@pytest.mark.shared_data
def test_real_lens_blur_file(tmp_path, capsys):
    src = SHARED / "google_lensblur_depthy" / "lensblur_sample.jpg"
    if not src.exists():
        pytest.skip(f"shared data not available: {src}")
    out = tmp_path / "o.jpg"
    code, err = _run(capsys, "render", src, "-o", out, "--blur", 30, "--max-pixels", 150_000)
    assert code == 0, err
    assert load_image(out).shape[0] * load_image(out).shape[1] <= 150_000


def test_default_pixel_cap(tmp_path, capsys, checkpoint, monkeypatch):
    """Photos above the default cap are downscaled with a one-line notice (a 144 MP PNG
    rendered for minutes at its size); ``--max-pixels 0`` lifts the cap, ``--max-pixels N``
    sets it without a notice."""
    from d2f_core import photo_render

    img, disp = _scene()  # 48x64 = 3072 px
    src = _write_photo(tmp_path / "big.png", img)
    monkeypatch.setattr(photo_render, "DEFAULT_MAX_PIXELS", 1200)
    common = ["--blur", 8, "--focus", 0.5, "--weights", checkpoint]
    code, err = _run(capsys, "render", src, "-o", tmp_path / "a.png", *common)
    assert code == 0, err
    with Image.open(tmp_path / "a.png") as im:
        assert im.width * im.height <= 1200 and im.width / im.height == pytest.approx(4 / 3, 0.1)
    assert "is 64x48 (0.0 MP): rendered at" in err and "--max-pixels 0" in err
    code, err = _run(capsys, "render", src, "-o", tmp_path / "b.png", "--max-pixels", 0, *common)
    assert code == 0 and "rendered at" not in err
    with Image.open(tmp_path / "b.png") as im:
        assert im.size == (64, 48)
    code, err = _run(capsys, "render", src, "-o", tmp_path / "c.png", "--max-pixels", 800, *common)
    assert code == 0 and "rendered at" not in err
    with Image.open(tmp_path / "c.png") as im:
        assert im.width * im.height <= 800
    code, err = _run(capsys, "render", src, "-o", tmp_path / "d.png", "--max-pixels", -5, *common)
    assert code == 2 and "0 (no limit)" in err


def test_save_maps_checked_before_anything_is_written(tmp_path, capsys, checkpoint):
    """A maps folder that cannot be made stops the render before the main output is
    written (it used to exit 1 after writing it)."""
    img, disp = _scene()
    src = _write_photo(tmp_path / "p.png", img)
    blocker = tmp_path / "maps"
    blocker.write_text("a file, not a folder")
    out = tmp_path / "out.png"
    code, err = _run(capsys, "render", src, "-o", out, "--blur", 8, "--focus", 0.5,
                     "--weights", checkpoint, "--save-maps", blocker / "sub")  # fmt: skip
    assert code == 1 and "--save-maps" in err and "cannot write there" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists() and blocker.read_text() == "a file, not a folder"
