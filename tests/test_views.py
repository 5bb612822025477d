"""Views smaller than the whole photo at full resolution: the whole render at a screen's size
(``D2F.render(..., screen=S)``) is the full render downscaled, and a region's render
(``D2F.render_region``) is the full render's crop, each for a fraction of the cost."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from d2f_core.metrics import psnr
from d2f_core.pipeline import D2F
from d2f_core.sizing import resize

pytestmark = pytest.mark.usefixtures("one_thread")

PORTRAIT = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data"
    / "apple_portrait_jpeg_depth"
    / "image-with-matte.jpg"
)


def _down(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]
    return resize(t, size)[0].permute(1, 2, 0).numpy()


def _scene_arrays(h: int = 900, w: int = 1200, seed: int = 0):
    """Smooth colour blobs with fine texture, a near box before a slanted far wall."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    base = np.stack([0.5 + 0.3 * np.sin(xx / 37 + c) * np.cos(yy / 53 - c) for c in range(3)], 2)
    image = np.clip(base + rng.normal(0, 0.08, (h, w, 3)), 0, 1).astype(np.float32)
    depth = (0.1 + 0.3 * xx / w).astype(np.float32)
    depth[h // 4 : 3 * h // 4, w // 5 : w // 2] = 0.8
    return image, depth


@pytest.fixture(scope="module")
def model() -> D2F:
    torch.manual_seed(0)
    return D2F.from_config({})


@pytest.fixture(scope="module")
def shipped() -> D2F:
    """The shipped weights: their radiance and fusion networks, as the app renders."""
    return D2F.from_pretrained()


class TestScreen:
    def test_screen_render_is_the_full_render_downscaled(self, shipped):
        model = shipped
        image, depth = _scene_arrays()
        scene = model.prepare(image, depth=depth)
        for focus, blur, span in ((0.8, 30.0, 0.0), (0.25, 50.0, 0.1), (0.5, 8.0, 0.0)):
            full = model.render(scene, focus, blur, focal_range=span)
            for screen in (600, 800):
                small = model.render(scene, focus, blur, focal_range=span, screen=screen)
                assert max(small.bokeh.shape[:2]) == screen
                assert psnr(small.bokeh, _down(full.bokeh, small.bokeh.shape[:2])) >= 40.0
        # the photo's own size or larger: the full render itself
        same = model.render(scene, 0.8, 30.0, screen=1200)
        assert np.array_equal(same.bokeh, model.render(scene, 0.8, 30.0).bokeh)

    def test_screen_scene_is_made_once_and_keeps_the_paint(self, model):
        image, depth = _scene_arrays(300, 400)
        scene = model.prepare(image, depth=depth)
        a = model.screen_scene(scene, 200)
        assert a.size == (150, 200) and model.screen_scene(scene, 200).image is a.image
        assert model.screen_scene(scene, 400) is scene
        sharp = np.zeros((300, 400), np.float32)
        sharp[:, 300:] = 1.0
        painted = model.paint(scene, sharp=sharp, edges=False)
        assert model.screen_scene(painted, 200).brushes is painted.brushes
        assert model.screen_scene(scene, 200).brushes is None
        # the paint reaches the screen's picture: the painted far wall is the photo's
        shown = model.render(painted, 0.8, 40.0, screen=200)
        photo = _down(image, (150, 200))
        assert np.abs(shown.bokeh[20:130, 160:195] - photo[20:130, 160:195]).max() < 0.02
        assert (
            np.abs(model.render(scene, 0.8, 40.0, screen=200).bokeh - photo)[20:130, 160:195].mean()
            > 0.01
        )

    @pytest.mark.skipif(
        not PORTRAIT.exists(), reason="../shared/data (the 12 MP portrait) is absent"
    )
    def test_twelve_megapixels_on_screen(self, shipped):
        """The 12 MP portrait as the app shows it (1600 px), focused on the face: within 40 dB
        of the download downscaled (measured 60.6)."""
        from d2f_core.io import load_photo

        photo = load_photo(PORTRAIT, max_pixels=20_000_000)
        scene = shipped.prepare(photo)
        focus, span = shipped.focus_at(scene, 1720, 480, with_range=True)
        full = shipped.render(scene, focus, f_number=1.4, focal_range=span)
        small = shipped.render(scene, focus, f_number=1.4, focal_range=span, screen=1600)
        assert small.bokeh.shape == (1600, 1200, 3)
        assert psnr(small.bokeh, _down(full.bokeh, (1600, 1200))) >= 40.0


class TestRegion:
    @pytest.mark.parametrize(
        "box",
        [(500, 300, 780, 520), (0, 0, 300, 200), (1000, 700, 1200, 900), (240, 230, 241, 231)],
    )
    def test_region_is_the_full_renders_crop(self, model, box):
        image, depth = _scene_arrays()
        scene = model.prepare(image, depth=depth)
        for focus, blur, span in ((0.8, 30.0, 0.0), (0.25, 60.0, 0.1)):
            full = model.render(scene, focus, blur, focal_range=span)
            part = model.render_region(scene, box, focus, blur, focal_range=span)
            x0, y0, x1, y1 = box
            assert part.bokeh.shape == (y1 - y0, x1 - x0, 3)
            assert psnr(part.bokeh, full.bokeh[y0:y1, x0:x1]) >= 40.0

    def test_region_reads_focus_and_aperture_from_the_whole_photo(self, model):
        image, depth = _scene_arrays()
        scene = model.prepare(image, depth=depth)
        full = model.render(scene, f_number=2.0)  # the default focus, the subject's range
        part = model.render_region(scene, (100, 100, 400, 300), f_number=2.0)
        assert part.focus == full.focus and part.focal_range == full.focal_range
        assert psnr(part.bokeh, full.bokeh[100:300, 100:400]) >= 40.0

    def test_region_keeps_the_paint(self, model):
        image, depth = _scene_arrays()
        scene = model.prepare(image, depth=depth)
        sharp = np.zeros(depth.shape, np.float32)
        sharp[100:400, 800:1100] = 1.0
        painted = model.paint(scene, sharp=sharp, edges=False)
        part = model.render_region(painted, (850, 150, 1050, 350), 0.8, 40.0)
        assert np.abs(part.bokeh - image[150:350, 850:1050]).max() < 1e-5

    @pytest.mark.parametrize(
        "box",
        [(0, 0, 0, 10), (-1, 0, 10, 10), (0, 0, 1201, 10), (0, 0, 10.5, 10), "box", (1, 2, 3)],
    )
    def test_bad_boxes_are_named(self, model, box):
        image, depth = _scene_arrays(90, 120)
        scene = model.prepare(image, depth=depth)
        with pytest.raises(ValueError, match="box"):
            model.render_region(scene, box, 0.5, 20.0)


class TestFusionGate:
    """The fusion gate is a CoC in the photo's pixels, whatever the pass's size."""

    def test_gate_in_the_photos_pixels(self, model):
        from d2f_core.rendering.schedule import defocus_to_coc

        image, depth = _scene_arrays(300, 400)
        scene = model.prepare(image, depth=depth)
        expected = defocus_to_coc(model.config.fusion_gate) / model.config.render_scale
        assert expected == pytest.approx(23.6)
        assert model.gate_coc(scene.pixel_scale) == pytest.approx(expected)
        screen = model.screen_scene(scene, 200)
        assert screen.pixel_scale == pytest.approx(0.5)
        assert model.gate_coc(screen.pixel_scale) == pytest.approx(expected / 2)

    def test_small_pass_does_not_sharpen_a_blurred_background(self):
        """A 1200 px photo through a 200 px pass (a sixth, as a 12 MP photo's pass is a
        fifth): the wall, 40-70 px out of focus, is the pass's blur alone (mask 0), on the
        full render and on a 600 px screen. A gate at the pass's own scale (71 px here) let
        the fusion network put some of the sharp photo back there."""
        torch.manual_seed(0)
        small_pass = D2F.from_config({"max_render_side": 200})
        image, depth = _scene_arrays(800, 1200)
        scene = small_pass.prepare(image, depth=depth)
        assert tuple(scene.image_lr.shape[-2:]) == (133, 200)
        near = depth >= 0.8
        assert not near[:, 620:].any()  # the wall: disparity 0.1-0.4, focus on the box
        for screen in (None, 600):
            result = small_pass.render(scene, 0.8, 100.0, screen=screen)
            wall = result.fusion_mask[:, result.fusion_mask.shape[1] * 620 // 1200 :]
            assert float(wall.max()) == 0.0
            box = result.fusion_mask[
                result.fusion_mask.shape[0] * 3 // 8 : result.fusion_mask.shape[0] * 5 // 8,
                result.fusion_mask.shape[1] * 3 // 10 : result.fusion_mask.shape[1] * 4 // 10,
            ]
            assert float(box.min()) == pytest.approx(1.0)  # the box in focus: the photo

    def test_no_line_where_a_floor_crosses_the_gate(self, shipped):
        """A textured floor receding from the focal plane: the sharp photo fusion puts back
        fades out towards the gate's CoC, with no step between two rows (a hard gate took
        the mask from 0.34 to 0 between two rows here)."""
        h, w = 600, 800
        rng = np.random.default_rng(0)
        cells = rng.standard_normal((h // 2, w // 2, 3)).repeat(2, 0).repeat(2, 1)
        image = np.clip(0.5 + 0.25 * cells, 0, 1).astype(np.float32)
        disparity = np.tile(np.linspace(1.0, 0.0, h, dtype=np.float32)[:, None], (1, w))
        scene = shipped.prepare(image, depth=disparity)
        result = shipped.render(scene, 1.0, 60.0)
        mask = result.fusion_mask[:, 20:-20].mean(axis=1)
        coc = 60.0 * (1.0 - disparity[:, 0])
        gate = shipped.gate_coc(scene.pixel_scale)
        assert mask[coc < 0.4 * gate].min() > 0.1  # fusion is at work near the focus
        assert mask[coc >= gate].max() == 0.0
        across = (coc > 0.5 * gate) & (coc < 1.2 * gate)  # into the gate and past it
        assert np.abs(np.diff(mask[across])).max() < 0.02  # a ramp, not a step
