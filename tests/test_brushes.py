"""Focus and blur brushes: masks painted over the photo that edit the depth for every render
(:mod:`d2f_core.depth.brushes`, ``D2F.paint``, ``d2f render --sharp-mask/--blur-mask``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core.depth.brushes import Brushes, apply_brushes, follow_edges, mask_tensor
from d2f_core.io import load_mask
from d2f_core.pipeline import D2F

pytestmark = pytest.mark.usefixtures("one_thread")

SHARED = Path(__file__).resolve().parents[2] / "shared"
PORTRAIT = SHARED / "data" / "apple_portrait_jpeg_depth" / "image-with-matte.jpg"


def _detail(image: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """Mean absolute gradient of the grey image over ``box = (y0, y1, x0, x1)``."""
    y0, y1, x0, x1 = box
    g = np.asarray(image, np.float32)[y0:y1, x0:x1].mean(axis=2)
    return float(np.abs(np.diff(g, axis=0)).mean() + np.abs(np.diff(g, axis=1)).mean())


def _photo(h: int = 96, w: int = 128, seed: int = 0) -> np.ndarray:
    """2x2-pixel random texture: sharp by construction, every blur shows."""
    rng = np.random.default_rng(seed)
    cells = rng.uniform(0.1, 0.9, size=(h // 2, w // 2, 3)).astype(np.float32)
    return cells.repeat(2, 0).repeat(2, 1)


def _depth(h: int = 96, w: int = 128) -> np.ndarray:
    """A subject at 0.75 (rows 24-72, columns 44-84) before a background at 0.15."""
    d = np.full((h, w), 0.15, np.float32)
    d[24:72, 44:84] = 0.75
    return d


@pytest.fixture(scope="module")
def model() -> D2F:
    torch.manual_seed(0)
    return D2F.from_config({})


class TestApply:
    def test_sharp_pulls_to_the_focal_plane(self):
        d = torch.tensor([0.1, 0.3, 0.9, 0.6]).view(1, 1, 1, 4)
        sharp = torch.tensor([1.0, 0.5, 1.0, 0.0]).view(1, 1, 1, 4)
        out = apply_brushes(d, 0.6, sharp, None)
        assert torch.allclose(out, torch.tensor([0.6, 0.45, 0.6, 0.6]).view(1, 1, 1, 4))

    def test_blur_pushes_away_on_each_side(self):
        """Behind the plane toward 0, in front toward 1, at the plane to the far end of the
        range from it; the distance from the plane never shrinks."""
        d = torch.tensor([0.2, 0.8, 0.6, 0.6, 0.3]).view(1, 1, 1, 5)
        blur = torch.tensor([1.0, 1.0, 1.0, 0.5, 0.0]).view(1, 1, 1, 5)
        out = apply_brushes(d, 0.6, None, blur)
        assert torch.allclose(out, torch.tensor([0.0, 1.0, 0.0, 0.3, 0.3]).view(1, 1, 1, 5))
        out = apply_brushes(torch.full((1, 1, 1, 1), 0.2), 0.2, None, torch.ones(1, 1, 1, 1))
        assert float(out) == 1.0  # a focus behind the middle: the near end is farther
        rng = torch.Generator().manual_seed(0)
        d = torch.rand(1, 1, 32, 32, generator=rng)
        paint = torch.rand(1, 1, 32, 32, generator=rng)
        for f in (0.0, 0.3, 0.5, 0.9, 1.0):
            pushed = apply_brushes(d, f, None, paint)
            assert bool(((pushed - f).abs() >= (d - f).abs() - 1e-6).all())
            assert bool(((pushed >= 0) & (pushed <= 1)).all())

    def test_unpainted_is_untouched(self):
        d = torch.rand(1, 1, 8, 8)
        zero = torch.zeros(1, 1, 8, 8)
        assert torch.equal(apply_brushes(d, 0.4, zero, zero), d)
        assert apply_brushes(d, 0.4, None, None) is d


class TestMasks:
    @pytest.mark.parametrize(
        "mask",
        [
            np.array([[0, 255], [255, 0]], np.uint8),
            np.array([[False, True], [True, False]]),
            np.array([[0.0, 1.0], [1.0, 0.0]], np.float32),
            # RGBA: a white stroke on a transparent layer; the transparent white is unpainted
            np.array(
                [
                    [[255, 255, 255, 0], [255, 255, 255, 255]],
                    [[255, 255, 255, 255], [0, 0, 0, 255]],
                ],
                np.uint8,
            ),  # fmt: skip
        ],
    )
    def test_kinds_of_mask(self, mask):
        t = mask_tensor(mask, (2, 2), "m")
        assert t.shape == (1, 1, 2, 2) and t.dtype == torch.float32
        assert torch.allclose(t[0, 0], torch.tensor([[0.0, 1.0], [1.0, 0.0]]))

    @pytest.mark.parametrize(
        ("mask", "message"),
        [
            (np.array([[0.0, np.nan]]), "NaN"),
            (np.array([[0.0, 2.0]]), r"\[0, 1\]"),
            (np.array([[0, 300]]), "0-255"),
            (np.zeros((2, 2, 5)), "channels"),
            (np.zeros(4), "H x W"),
            (np.array([["a"]]), "numeric"),
            (np.zeros((4, 2)), "mask is 2x4 but the image is 4x2: aspect ratios differ"),
        ],
    )
    def test_bad_masks_name_the_problem(self, mask, message):
        with pytest.raises(ValueError, match=message):
            mask_tensor(mask, (2, 4), "sharp_mask")

    def test_a_small_mask_is_resized_to_the_photo(self):
        t = mask_tensor(np.ones((3, 4), np.uint8) * 255, (30, 40), "m")
        assert t.shape == (1, 1, 30, 40) and float(t.min()) == pytest.approx(1.0)

    def test_both_painted_the_larger_paint_wins(self):
        image = torch.rand(1, 3, 4, 4)
        sharp = np.zeros((4, 4), np.float32)
        blur = np.zeros((4, 4), np.float32)
        sharp[:, :2], blur[:, 1:] = 1.0, 0.6
        b = Brushes.painted(image, sharp, blur, edges=False)
        assert b.sharp[0, 0, 0].tolist() == [255, 255, 0, 0]
        assert b.blur[0, 0, 0].tolist() == [0, 0, 153, 153]
        assert Brushes.painted(image, np.zeros((4, 4)), None) is None
        assert b.coverage() == pytest.approx((0.5, 0.5 * 0.6), abs=1e-3)


class TestFollowEdges:
    def test_a_stroke_spilling_over_a_colour_edge_is_cut_back(self):
        """A stroke painted over the dark half that spills 6 px into the light half keeps
        the dark half and loses the spill; a stroke in one colour is unchanged."""
        h, w = 256, 512  # the window: 0.02 of the long side, 10 px
        image = torch.full((1, 3, h, w), 0.2)
        image[..., 256:] = 0.8
        stroke = torch.zeros(1, 1, h, w)
        stroke[..., 64:192, 32:262] = 1.0
        out = follow_edges(image, stroke)
        assert float(out[..., 80:176, 40:256].min()) > 0.99  # the dark part kept
        assert float(out[..., 80:176, 256:262].max()) < 0.05  # the spill cut back
        flat = torch.full((1, 3, h, w), 0.5)
        assert torch.allclose(follow_edges(flat, stroke), stroke, atol=1e-4)


class TestPaintedRender:
    def test_painted_sharp_stays_sharp_wherever_the_focus_goes(self, model):
        """The background painted sharp, focused on the subject: the painted part is the
        photo's own; focused elsewhere it still is; the rest renders as without paint."""
        photo, depth = _photo(), _depth()
        scene = model.prepare(photo, depth=depth, refine=False)
        sharp = np.zeros(depth.shape, np.float32)
        sharp[4:20, 4:40] = 1.0  # a patch of background
        painted = model.paint(scene, sharp=sharp, edges=False)
        assert scene.brushes is None and painted.brushes is not None  # a new scene
        patch = (slice(6, 18), slice(6, 38))
        for focus in (0.75, 0.5, 0.95):
            plain = model.render(scene, focus, 40.0, budget=None)
            res = model.render(painted, focus, 40.0, budget=None)
            assert np.abs(res.bokeh[patch] - photo[patch]).max() < 1e-5
            assert np.abs(plain.bokeh[patch] - photo[patch]).mean() > 0.02
            # the subject, far from the patch, is as without the paint
            subject = (slice(40, 72), slice(60, 84))
            assert np.abs(res.bokeh[subject] - plain.bokeh[subject]).max() < 1e-5
            # the pass (half size) sees the patch on the focal plane
            assert res.disparity[4:8, 4:18] == pytest.approx(focus, abs=1e-5)
        # painting nothing clears the paint
        assert model.paint(painted).brushes is None

    def test_painted_blur_blurs_what_the_map_puts_in_focus(self, model):
        photo, depth = _photo(), _depth()
        scene = model.prepare(photo, depth=depth, refine=False)
        blur = np.zeros(depth.shape, np.float32)
        blur[24:72, 44:64] = 1.0  # the left half of the subject
        painted = model.paint(scene, blur=blur, edges=False)
        plain = model.render(scene, 0.75, 40.0, budget=None)
        res = model.render(painted, 0.75, 40.0, budget=None)
        left, right = (26, 70, 48, 60), (26, 70, 68, 82)
        assert _detail(plain.bokeh, left) == pytest.approx(_detail(photo, left), rel=1e-4)
        assert _detail(res.bokeh, left) < 0.5 * _detail(photo, left)
        assert _detail(res.bokeh, right) == pytest.approx(_detail(photo, right), rel=0.02)

    def test_preview_sees_the_paint(self, model):
        photo, depth = _photo(), _depth()
        sharp = np.zeros(depth.shape, np.float32)
        sharp[:, :32] = 1.0
        painted = model.paint(model.prepare(photo, depth=depth, refine=False), sharp=sharp)
        preview = model.render(painted, 0.75, 40.0, max_side=64, budget=None)
        assert preview.disparity[:, :12].min() == pytest.approx(0.75, abs=1e-4)

    def test_paint_needs_a_scene(self, model):
        with pytest.raises(ValueError, match="scene"):
            model.paint("scene", sharp=np.ones((2, 2)))


class TestLoadMask:
    def test_formats(self, tmp_path):
        grey = np.zeros((6, 8), np.uint8)
        grey[:, 4:] = 255
        Image.fromarray(grey).save(tmp_path / "l.png")
        assert np.array_equal(load_mask(tmp_path / "l.png"), grey / 255.0)
        Image.fromarray(grey.astype(np.uint16) * 257).save(tmp_path / "i16.png")
        assert np.allclose(load_mask(tmp_path / "i16.png"), grey / 255.0)
        rgba = np.zeros((6, 8, 4), np.uint8)
        rgba[..., :3] = 255  # white everywhere, opaque only on the right
        rgba[:, 4:, 3] = 255
        Image.fromarray(rgba).save(tmp_path / "rgba.png")
        assert np.array_equal(load_mask(tmp_path / "rgba.png"), grey / 255.0)

    def test_orientation_is_applied(self, tmp_path):
        grey = np.zeros((6, 8), np.uint8)
        grey[0, 0] = 255
        im = Image.fromarray(grey)
        exif = im.getexif()
        exif[0x0112] = 6  # stored turned: shown a quarter turn clockwise
        im.save(tmp_path / "turned.jpg", exif=exif.tobytes(), quality=100)
        upright = load_mask(tmp_path / "turned.jpg", size=(80, 60))
        assert upright.shape == (8, 6)
        assert upright[0, -1] > 0.5 and upright[0, 0] < 0.2

    def test_bad_files(self, tmp_path):
        (tmp_path / "text.png").write_text("not an image")
        with pytest.raises(ValueError, match="not an image"):
            load_mask(tmp_path / "text.png")
        Image.fromarray(np.zeros((6, 8), np.uint8)).save(tmp_path / "m.png")
        data = (tmp_path / "m.png").read_bytes()
        (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match="cut.png"):
            load_mask(tmp_path / "cut.png")
        with pytest.raises(ValueError, match="mask is 8x6 but the image is 8x8"):
            load_mask(tmp_path / "m.png", size=(8, 8))
        with pytest.raises(FileNotFoundError):
            load_mask(tmp_path / "missing.png")


class TestCommandLine:
    def _run(self, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "d2f_core.cli", "render", *args],
            capture_output=True,
            text=True,
            timeout=300,
            env=env,
        )

    @pytest.mark.slow
    def test_masks_on_the_command_line(self, two_plane_scene, tmp_path, tiny_checkpoint):
        """``--sharp-mask`` keeps the painted background sharp with the subject in focus, with
        the network's weights and with a depth map alone; the mask is never overwritten."""
        s = two_plane_scene
        h, w = s.image.shape[:2]
        mask = np.zeros((h // 2, w // 2), np.uint8)  # half the photo's size: resized
        mask[5:40, 100:150] = 255  # background, right of the subject
        Image.fromarray(mask).save(tmp_path / "sharp.png")
        x, y = s.near_point
        patch = (slice(20, 70), slice(210, 290))  # 10 px inside the stroke
        photo = s.image.astype(np.float32)
        # the weights' path, and the map-only path (no weights where they are looked for)
        no_weights = {**os.environ, "D2F_WEIGHTS": str(tmp_path / "no-such-weights.pt")}
        for weights, env in ((["--weights", str(tiny_checkpoint)], None), ([], no_weights)):
            common = [str(s.photo), "--depth", str(s.disparity), "--focus-at", f"{x},{y}",
                      "--blur", "30", *weights]  # fmt: skip
            plain = self._run(*common, "-o", str(tmp_path / "plain.png"), env=env)
            assert plain.returncode == 0, plain.stderr
            out = tmp_path / "painted.png"
            done = self._run(
                *common, "--sharp-mask", str(tmp_path / "sharp.png"), "-o", str(out), env=env
            )
            assert done.returncode == 0, done.stderr
            before = np.asarray(Image.open(tmp_path / "plain.png"), np.float32)
            after = np.asarray(Image.open(out), np.float32)
            assert np.abs(before[patch] - photo[patch]).mean() > 10.0, weights
            assert np.abs(after[patch] - photo[patch]).mean() < 1.0, weights
            subject = (slice(70, 170), slice(50, 130))
            assert np.abs(after[subject] - before[subject]).mean() < 0.5, weights
        kept = (tmp_path / "sharp.png").read_bytes()
        bad = self._run(str(s.photo), "--blur", "30", "--sharp-mask", str(tmp_path / "sharp.png"),
                        "-o", str(tmp_path / "sharp.png"))  # fmt: skip
        assert bad.returncode == 2 and "is the --sharp-mask file" in bad.stderr
        assert (tmp_path / "sharp.png").read_bytes() == kept
        square = tmp_path / "square.png"
        Image.fromarray(np.zeros((50, 50), np.uint8)).save(square)
        bad = self._run(str(s.photo), "--blur", "30", "--blur-mask", str(square), "-o",
                        str(tmp_path / "x.png"))  # fmt: skip
        assert bad.returncode == 1
        assert bad.stderr.strip().splitlines() == [
            f"d2f: error: {square}: mask is 50x50 but the image is 320x240: aspect ratios differ"
        ]


@pytest.mark.slow
@pytest.mark.skipif(not PORTRAIT.exists(), reason="../shared/data (the 12 MP portrait) is absent")
def test_portrait_lamp_painted_sharp():
    """The 12 MP portrait focused on the face (a click there, with its range), the lamps
    behind painted sharp: the lamps keep at least 0.9 of their detail, the face at least
    0.95, and the background outside the paint is as blurred as without it."""
    from d2f_core.io import load_photo

    model = D2F.from_pretrained()
    photo = load_photo(PORTRAIT, max_pixels=20_000_000)
    h, w = photo.image.shape[:2]
    assert (w, h) == (3024, 4032)
    scene = model.prepare(photo)
    focus, focal_range = model.focus_at(scene, 1720, 480, with_range=True)
    lamp_mask = np.zeros((h, w), np.uint8)
    lamp_mask[:720, 2060:] = 255  # the copper pendants, right of the head
    painted = model.paint(scene, sharp=lamp_mask)
    src = photo.image
    lamps, face, background = (40, 650, 2200, 3000), (350, 650, 1550, 1900), (100, 1500, 400, 1000)
    plain = model.render(scene, focus, f_number=1.4, focal_range=focal_range)
    res = model.render(painted, focus, f_number=1.4, focal_range=focal_range)

    def kept(image, box):
        return _detail(image, box) / _detail(src, box)

    assert kept(plain.bokeh, lamps) < 0.5  # without the paint they are blurred
    assert kept(res.bokeh, lamps) >= 0.9
    assert kept(res.bokeh, face) >= 0.95
    assert kept(plain.bokeh, background) < 0.6
    assert kept(res.bokeh, background) == pytest.approx(kept(plain.bokeh, background), rel=0.01)
