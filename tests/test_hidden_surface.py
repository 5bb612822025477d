"""What a lens sees past the rim of a blurred near object (``rendering.hidden_surface``).

The photo shows only the near object there; a thin lens sees past its rim, up to its CoC
radius inside it, to the background behind. Checked against the accumulation-buffer ground
truth of ``d2f_core.train.synth``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from d2f_core import rendering
from d2f_core.metrics import psnr
from d2f_core.train.synth import Layer, Scene, render_pinhole, render_thin_lens


def _occluder_scene(near: float = 0.9, far: float = 0.2, focus: float = 0.2):
    """A background plane of horizontal stripes (what lies behind the rectangle's left and
    right rims continues what is beside them) and a flat near rectangle in front of it."""
    h, w, m = 96, 128, 40
    yy, xx = np.mgrid[-m : h + m, -m : w + m]
    stripes = ((yy // 8) % 2).astype(np.float32) * 0.6 + 0.2 + 0 * xx
    rgb = np.stack([stripes, 1 - stripes, 0.4 + 0 * stripes]).astype(np.float32)
    back = Layer(rgb, np.ones(rgb.shape[1:], np.float32), -m, -m, far)
    box = np.zeros((3, 40, 56), np.float32)
    box[:] = np.array([0.85, 0.25, 0.15], np.float32)[:, None, None]
    front = Layer(box, np.ones(box.shape[1:], np.float32), 28, 36, near)
    return Scene([back, front], (h, w), m, focus)


def _render(scene: Scene, focus: float, blur: float, **options):
    pinhole, disp = render_pinhole(scene)
    image = torch.from_numpy(np.clip(pinhole, 0, 1)).permute(2, 0, 1)[None].contiguous()
    out = rendering.render(
        image,
        torch.from_numpy(disp)[None, None],
        focus,
        blur,
        quality="exact",
        kernel="hard",
        highlight_boost=False,
        **options,
    )
    return out[0].permute(1, 2, 0).numpy(), disp


def _rim(disp: np.ndarray, near: float, radius: int) -> np.ndarray:
    """The near object's pixels within ``radius`` px of its left or right edge, away from its
    corners."""
    inside = disp >= near - 1e-6
    rim = inside & ~ndimage.binary_erosion(inside, structure=np.ones((1, 3)), iterations=radius)
    return rim & ndimage.binary_erosion(inside, structure=np.ones((3, 1)), iterations=radius)


class TestBlurredOccluder:
    """Focus on the background, a blurred rectangle in front (CoC 28 px)."""

    focus, blur = 0.2, 40.0

    @pytest.fixture(scope="class")
    @classmethod
    def case(cls):
        scene = _occluder_scene(focus=cls.focus)
        truth = np.clip(render_thin_lens(scene, cls.focus, cls.blur, samples=256), 0, 1)
        with_hidden, disp = _render(scene, cls.focus, cls.blur)
        without, _ = _render(scene, cls.focus, cls.blur, hidden=False)
        return truth, with_hidden, without, disp

    def test_rim_shows_the_background(self, case):
        truth, with_hidden, without, disp = case
        rim = _rim(disp, 0.9, 14)
        got, old = psnr(with_hidden[rim], truth[rim]), psnr(without[rim], truth[rim])
        print(f"rim PSNR: {got:.2f} dB with the hidden surface, {old:.2f} dB without")
        # measured: 22.4 against 20.1 dB (what remains is the surface drawn twice at the rim,
        # by the two layers either side of its CoC)
        assert got > old + 1.5

    def test_edge_pixel_is_half_occluder(self, case):
        # at the rim a straight edge covers half the CoC disc: half box, half background
        truth, with_hidden, without, _ = case
        y, x = 50, 36  # the rectangle's left edge, mid-height, first column inside
        box_red = 0.85
        assert abs(truth[y, x, 0] - (box_red + 0.2) / 2) < 0.03  # stripe behind: red 0.2
        assert abs(without[y, x, 0] - box_red) < 0.02  # the near object alone
        # measured: 0.73 against the truth's 0.54 (the box drawn by two layers covers the
        # background as 1 - (1 - a)^2 of it), against 0.85 without the hidden surface
        err, old = abs(truth[y, x, 0] - with_hidden[y, x, 0]), abs(truth[y, x, 0] - box_red)
        assert err < old - 0.08

    def test_whole_frame_no_worse(self, case):
        truth, with_hidden, without, _ = case
        assert psnr(with_hidden, truth) > psnr(without, truth) + 1


def test_sharp_near_object_is_unchanged():
    # focus on the near rectangle: its rim is opaque, nothing is seen past it
    scene = _occluder_scene(focus=0.9)
    a, _ = _render(scene, 0.9, 40.0)
    b, _ = _render(scene, 0.9, 40.0, hidden=False)
    np.testing.assert_array_equal(a, b)


def test_no_depth_edge_no_hidden_surface():
    # a slanted plane: the disparity changes smoothly, there is no rim to see past
    h, w = 64, 96
    disp = torch.linspace(0.1, 0.9, h).view(1, 1, h, 1).expand(1, 1, h, w).contiguous()
    image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
    plan = rendering.layer_plan(disp, torch.tensor(0.5).view(1, 1, 1, 1), 40.0)
    x = torch.cat([torch.ones(1, 1, h, w), image], dim=1)
    assert rendering.hidden_surface(lambda ys, xs: x[0][:, ys, xs], plan) is None
    a = rendering.render(image, disp, 0.5, 40.0)
    b = rendering.render(image, disp, 0.5, 40.0, hidden=False)
    torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_push_pull_fills_from_known_pixels():
    values = torch.zeros(1, 1, 16, 16)
    values[..., :, :8] = 0.25
    values[..., :, 8:] = 0.75
    known = torch.zeros(1, 1, 16, 16)
    known[..., :, 0] = 1
    known[..., :, 15] = 1
    out = rendering.hidden._push_pull(values, known)
    # known pixels are kept; the gap between takes values between the two sides, ordered
    assert torch.allclose(out[..., :, 0], torch.tensor(0.25))
    assert torch.allclose(out[..., :, 15], torch.tensor(0.75))
    row = out[0, 0, 8]
    assert bool((row[1:] >= row[:-1] - 1e-6).all())
    assert 0.25 <= float(row.min()) and float(row.max()) <= 0.75


def test_near_side_on_a_kernel_size():
    # A near rectangle whose CoC is exactly the last kernel's, (0.95 - 0.1) * 80 = 68 px: its
    # layer coordinate is 13.5 in float32, 13.4999990 one float32 step nearer the focus and
    # 13.4999999 in float64. Layer 14, the more blurred of the two either side, draws it in
    # every case, so the hidden surface and the render must not depend on which ("nearest"
    # placement: the one that puts a pixel half a layer from its CoC's place).
    h, w = 96, 128
    image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
    near = torch.tensor(0.95)

    def disparity(value: torch.Tensor) -> torch.Tensor:
        d = torch.full((1, 1, h, w), 0.1)
        d[..., 24:72, 40:90] = value
        return d

    inputs = [
        (image, disparity(near)),
        (image, disparity(torch.nextafter(near, torch.tensor(0.0)))),
        (image.double(), disparity(near).double()),
    ]
    surfaces, renders = [], []
    for img, d in inputs:
        f = torch.tensor(0.1, dtype=d.dtype).view(1, 1, 1, 1)
        plan = rendering.layer_plan(d, f, 80.0, placement="nearest")
        assert abs(float(plan.coord.max()) - 13.5) < 1e-5
        x = torch.cat([torch.ones_like(img[:, :1]), img], dim=1)
        surfaces.append(rendering.hidden_surface(rendering.hidden.input_pixels(x, False), plan))
        renders.append(rendering.render(img, d, 0.1, 80.0, placement="nearest").double())
    # the near side's CoC radius is 34 px: cells of 8 px, the frame's edges within reach
    assert [(s.grid, s.box) for s in surfaces] == [(8, (0, 96, 0, 128))] * 3
    for other in renders[1:]:
        assert float((other - renders[0]).abs().max()) < 1e-3


def test_drawn_only_within_its_spans():
    # two small near boxes far apart on a wide frame: the surface is 0 outside the column
    # spans it reports for any rows, and compositing by spans equals compositing its whole box
    h, w = 96, 320
    disp = torch.full((1, 1, h, w), 0.2)
    disp[..., 10:40, 20:60] = 0.9
    disp[..., 10:40, 260:300] = 0.9
    image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(5))
    with torch.inference_mode():
        plan = rendering.layer_plan(disp, torch.tensor(0.2).view(1, 1, 1, 1), 28.0)
        x = torch.cat([torch.ones_like(image[:, :1]), image], dim=1)
        under = rendering.hidden_surface(rendering.hidden.input_pixels(x, False), plan)
        assert under is not None
        y0, y1, x0, x1 = under.box
        assert x0 < 20 and x1 > 300  # the box holds both: its middle is 0
        whole = under.window(y0, y1, x0, x1)[0]
        drawn_rows = 0
        for a, b in [(y0, y1), (y0, y0 + 4), (12, 20), (30, 41), (60, y1)]:
            spans = under.spans(a, b)
            assert all(x0 <= s < e <= x1 for s, e in spans)
            inside = torch.zeros(w, dtype=torch.bool)
            for s, e in spans:
                inside[s:e] = True
            assert not inside[110:210].any()  # far from both boxes
            rows = whole[:, a - y0 : b - y0]
            assert rows[..., ~inside[x0:x1]].abs().max() == 0
            drawn_rows += bool(spans)
            assert bool(spans) == bool(rows.abs().max() > 0)
        assert drawn_rows >= 3  # the whole box and the near boxes' rows
        acc = torch.rand(4, h, w, generator=torch.Generator().manual_seed(6))
        expect = acc.clone()
        region = expect[:, y0:y1, x0:x1]
        region.addcmul_(whole, 1 - region[:1].clamp(0, 1))
        under.composite(acc, y0, y1)
        torch.testing.assert_close(acc, expect, rtol=0, atol=1e-6)
