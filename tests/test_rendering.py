import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from d2f_core import LayeredRenderer, render, render_bokeh, rendering
from d2f_core.metrics import psnr
from d2f_core.rendering import hdr_boost, hidden_surface, layer_plan
from d2f_core.rendering.blur import support_boxes as _support_boxes
from d2f_core.rendering.kernels import aperture_kernel, coarse_kernel
from d2f_core.rendering.plan import _MASK_EPS, blend_mask
from d2f_core.rendering.plan import TILE as _TILE
from d2f_core.rendering.plan import layer_mask as _layer_mask


def _soft_mask(coord, centre, grad=True):
    """The soft masks of the "nearest" and "paper" placements (``LayerPlan.mask``)."""
    return _layer_mask(coord, centre, 100.0 / 14, grad)


def _ramp(h=48, w=64, lo=0.0, hi=1.0):
    x = torch.linspace(lo, hi, w).expand(h, w)
    return x[None, None].clone()


def _row_band(monkeypatch, pixels: int) -> None:
    """Row bands of ``pixels`` in every stage that reads them."""
    for stage in (rendering.inputs, rendering.radiance, rendering.plan, rendering.tiled):
        monkeypatch.setattr(stage, "ROW_BAND", pixels)


def _texture(h=48, w=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(1, 3, h, w, generator=g) * 0.9


def _boxed_scene():
    """A textured 50x70 scene with a near box whose layers' support stays inside the frame."""
    disp = torch.full((1, 1, 50, 70), 0.2)
    disp[..., 12:31, 20:47] = 0.9
    return _texture(50, 70, seed=10), disp + 0.05 * _ramp(50, 70)


class TestKnownAnswers:
    def test_zero_blur_returns_input_exactly(self):
        img = _texture()
        for order in ("depth", "paper"):
            out = render(img, _ramp(), 0.3, 0.0, order=order)
            assert torch.equal(out, img)

    def test_disparity_at_focus_returns_input_exactly(self):
        img = _texture()
        disp = torch.full((1, 1, 48, 64), 0.42)
        out = render(img, disp, 0.42, 80.0)
        assert torch.equal(out, img)

    @pytest.mark.parametrize("order", ["depth", "paper"])
    @pytest.mark.parametrize("quality", ["exact", "fast"])
    @pytest.mark.parametrize(
        "aperture", [{}, {"blades": 6, "rotation": 10.0}, {"kernel": "hard"}], ids=str
    )
    def test_constant_image_stays_constant(self, order, quality, aperture):
        # fitted coarse kernels have negative taps: colour and alpha carry the same weights,
        # so the normalised colour still cannot move
        colour = torch.tensor([0.2, 0.5, 0.8]).view(1, 3, 1, 1)
        img = colour.expand(1, 3, 40, 56).clone()
        g = torch.Generator().manual_seed(1)
        disp = torch.rand(1, 1, 40, 56, generator=g)
        out = render(img, disp, 0.5, 60.0, order=order, quality=quality, **aperture)
        assert torch.allclose(out, img, atol=1e-5)

    def test_radiance_normalisation_keeps_flat_colour(self):
        # a random radiance map would tint a flat region without the f_l(R I) / f_l(R) division
        colour = torch.tensor([0.3, 0.6, 0.1]).view(1, 3, 1, 1)
        img = colour.expand(1, 3, 40, 40).clone()
        g = torch.Generator().manual_seed(2)
        radiance = torch.rand(1, 1, 40, 40, generator=g) * 0.99 + 0.01
        disp = torch.rand(1, 1, 40, 40, generator=g)
        out = render(img, disp, 0.0, 40.0, radiance=radiance)
        assert torch.allclose(out.mean(dim=(2, 3)), colour.view(1, 3), atol=1e-5)
        assert torch.allclose(out, img, atol=1e-5)

    @pytest.mark.parametrize("kernel,expected", [("hard", 23), ("soft", 23)])
    def test_point_light_gives_disc_of_right_diameter(self, kernel, expected):
        img = torch.zeros(1, 3, 61, 61)
        img[..., 30, 30] = 0.9
        disp = torch.ones(1, 1, 61, 61)
        out = render(img, disp, 0.0, 23.0, kernel=kernel, quality="exact")[0, 0]
        row = out[30]
        lit = (row > 0.5 * row.max()).nonzero().flatten()
        assert int(lit[-1] - lit[0] + 1) == expected
        # round: the same extent vertically, and energy is conserved by the normalisation
        col = out[:, 30]
        lit_v = (col > 0.5 * col.max()).nonzero().flatten()
        assert int(lit_v[-1] - lit_v[0] + 1) == expected
        assert out.sum().item() == pytest.approx(0.9, rel=1e-4)

    def test_polygon_aperture_gives_polygon(self):
        img = torch.zeros(1, 3, 61, 61)
        img[..., 30, 30] = 1.0
        disp = torch.ones(1, 1, 61, 61)
        disc = render(img, disp, 0.0, 33.0, kernel="hard", quality="exact")[0, 0] > 1e-5
        hexa = render(img, disp, 0.0, 33.0, kernel="hard", blades=6, quality="exact")[0, 0] > 1e-5
        assert hexa.sum() < disc.sum()
        assert (hexa & ~disc).sum() == 0


class TestOcclusion:
    def _bar_scene(self):
        h, w = 64, 96
        g = torch.Generator().manual_seed(3)
        img = 0.2 + 0.3 * torch.rand(1, 3, h, w, generator=g)  # textured far background
        disp = torch.full((1, 1, h, w), 0.1)
        img[..., :, 44:52] = 1.0  # near, bright vertical bar
        disp[..., :, 44:52] = 1.0
        return img, disp

    def test_foreground_spills_over_sharp_background_in_depth_order(self):
        img, disp = self._bar_scene()
        depth = render(img, disp, 0.1, 30.0, order="depth", quality="exact")
        paper = render(img, disp, 0.1, 30.0, order="paper", quality="exact")
        beside = (slice(None), slice(None), slice(8, 56), slice(38, 44))  # 1-6 px left of the bar
        spill_depth = (depth[beside] - img[beside]).mean().item()
        spill_paper = (paper[beside] - img[beside]).mean().item()
        # measured: depth order brightens the background beside the bar by ~0.3, the paper's
        # order keeps the in-focus background on top (~0.0)
        assert spill_depth > 0.15
        assert abs(spill_paper) < 0.02
        # the far background away from the bar stays sharp in both
        far = (slice(None), slice(None), slice(8, 56), slice(0, 20))
        assert psnr(depth[far], img[far]) > 40

    def test_background_does_not_spill_over_sharp_foreground(self):
        img, disp = self._bar_scene()
        out = render(img, disp, 1.0, 30.0, order="depth", quality="exact")
        bar = (slice(None), slice(None), slice(8, 56), slice(45, 51))
        assert psnr(out[bar], img[bar]) > 40

    def test_front_and_back_never_share_a_layer(self):
        disp = _ramp(8, 200)
        plan = layer_plan(disp, torch.tensor(0.5).view(1, 1, 1, 1), 60.0)
        signed = disp - 0.5
        for centre, _ in plan.order:
            mask = plan.mask(plan.side_coord(centre), centre)
            if centre > 0:
                assert (mask[signed <= 0] == 0).all()
            elif centre < 0:
                assert (mask[signed >= 0] == 0).all()

    def test_layers_composite_far_to_near(self):
        plan = layer_plan(_ramp(), torch.tensor(0.5).view(1, 1, 1, 1), 60.0)
        centres = [c for c, _ in plan.order]
        assert centres == sorted(centres)
        paper = layer_plan(_ramp(), torch.tensor(0.0).view(1, 1, 1, 1), 69.0, order="paper")
        assert [c for c, _ in paper.order] == list(range(14, -1, -1))
        assert [s for _, s in paper.order][::-1] == [
            1,
            3,
            5,
            7,
            11,
            15,
            19,
            23,
            27,
            33,
            39,
            45,
            53,
            61,
            69,
        ]

    def test_small_blur_needs_few_layers(self):
        focus = torch.tensor(0.5).view(1, 1, 1, 1)
        few = layer_plan(_ramp(), focus, 10.0)
        many = layer_plan(_ramp(), focus, 120.0)
        assert len(few.order) < len(many.order)
        assert max(s for _, s in few.order) <= 7

    def test_layer_coordinates_round_to_the_nearest_kernel(self):
        # kernels 1, 3, 5, 7, 11 px draw discs 0, 2, 4, 6, 10 px across (layers 0-4); a pixel
        # sits half a layer toward the side its overlapping layers hide: further out behind
        # focus (the nearer, sharper layer is on top), further in in front of it
        focus = torch.tensor(0.5).view(1, 1, 1, 1)
        coc = torch.tensor([10.0, 8.0, 5.0, 3.0, 0.8, 0.0])  # px at K = 20: |d - f| = coc / 20
        behind = (0.5 - coc / 20).view(1, 1, 1, -1)
        front = (0.5 + coc / 20).view(1, 1, 1, -1)
        plan_b = layer_plan(torch.cat([behind, front], dim=-1), focus, 20.0, placement="nearest")
        assert [s for c, s in plan_b.order if c >= 0] == [1, 3, 5, 7, 11]
        got = plan_b.coord.view(-1)
        u = torch.tensor([4.0, 3.5, 2.5, 1.5, 0.4, 0.0])
        torch.testing.assert_close(got[:6], -(u + 0.5) * (coc > 0) + 0.0, atol=1e-5, rtol=0)
        torch.testing.assert_close(got[6:], (u - 0.5).clamp(min=0), atol=1e-5, rtol=0)
        # the schedule stops at the first kernel whose disc covers the largest CoC
        nearest = {"placement": "nearest"}
        assert max(s for _, s in layer_plan(front, focus, 12.0, **nearest).order) == 7  # 6 px
        assert max(s for _, s in layer_plan(front, focus, 12.2, **nearest).order) == 11
        # a largest CoC of at most 1 px needs no blurred layer at all
        assert layer_plan(front, focus, 2.0, **nearest).order == [(0, 1)]
        assert layer_plan(front, focus, 2.0).order == [(0, 1)]

    def test_paper_placement_reads_kernel_sizes_as_cocs(self):
        # knots at the sizes 1, 3, 5, 7, 11 and no shift: the nearer of two overlapping layers
        # wins, which is the smaller kernel behind focus
        focus = torch.tensor(0.5).view(1, 1, 1, 1)
        coc = torch.tensor([10.0, 8.0, 5.0, 3.0, 0.8])
        disp = torch.cat([0.5 - coc / 20, 0.5 + coc / 20]).view(1, 1, 1, -1)
        plan = layer_plan(disp, focus, 20.0, placement="paper")
        u = torch.tensor([3.75, 3.25, 2.0, 1.0, 0.0])
        torch.testing.assert_close(plan.coord.view(-1), torch.cat([-u, u]), atol=1e-5, rtol=0)
        assert max(s for _, s in plan.order) == 11
        with pytest.raises(ValueError, match="placement"):
            layer_plan(disp, focus, 20.0, placement="middle")
        with pytest.raises(ValueError, match="placement"):
            render(torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8), 0.5, 5.0, placement="x")


class TestHighlights:
    def test_boost_makes_brighter_disc(self):
        img = torch.full((1, 3, 61, 61), 0.1)
        img[..., 29:32, 29:32] = 1.0
        disp = torch.ones(1, 1, 61, 61)
        ones = torch.ones_like(disp)  # a radiance map: the paper's boost
        on = render(img, disp, 0.0, 23.0, highlight_boost=True, quality="exact", radiance=ones)
        off = render(img, disp, 0.0, 23.0, highlight_boost=False, quality="exact")
        own = render(img, disp, 0.0, 23.0, quality="exact")
        disc = (slice(None), slice(None), slice(24, 37), slice(24, 37))
        twice = render(img, disp, 0.0, 23.0, highlight_boost=2.0, quality="exact")
        # a 3x3 highlight in a 23-px disc (~415 px): without the boost the disc mean is
        # (0.1 * 406 + 9) / 415 = 0.120; a lone spot, with or without a radiance map: 9 of the
        # 400 px around it are saturated, weight 3 + 9 (1 - 9 / 400)^4 = 11.22,
        # (0.1 * 406 + 11.22 * 9) / (406 + 101) = 0.279; at strength 2, weight 22.44:
        # (0.1 * 406 + 22.44 * 9) / (406 + 202) = 0.399
        assert on[disc].mean().item() == pytest.approx(0.279, abs=0.006)
        assert own[disc].mean().item() == pytest.approx(0.279, abs=0.006)
        assert off[disc].mean().item() == pytest.approx(0.120, abs=0.006)
        assert twice[disc].mean().item() == pytest.approx(0.399, abs=0.008)
        none = render(img, disp, 0.0, 23.0, highlight_boost=0.0, quality="exact")
        torch.testing.assert_close(none, off)
        for bad in (-1.0, 11.0, float("nan"), "lots"):
            with pytest.raises(ValueError, match="highlight_boost"):
                render(img, disp, 0.0, 23.0, highlight_boost=bad)
        # still a disc: the boost changes brightness, not the extent
        assert on[..., 30, :5].max() < 0.11 and on[..., 30, -5:].max() < 0.11

    def test_boost_keeps_hue_of_white_highlight(self):
        img = torch.full((1, 3, 41, 41), 0.1)
        img[..., 20, 20] = 1.0
        disp = torch.ones(1, 1, 41, 41)
        out = render(img, disp, 0.0, 15.0, quality="exact")[0, :, 20, 20]
        assert torch.allclose(out, out.mean().expand(3), atol=1e-6)

    def test_hdr_boost_formula(self):
        img = torch.tensor([1.0, 0.5, 0.2]).view(1, 3, 1, 1)
        r0 = torch.full((1, 1, 1, 1), 0.4)
        assert hdr_boost(img, r0).item() == pytest.approx(3.0)
        per = hdr_boost(img, r0, per_channel=True).flatten()
        assert torch.allclose(per, 3 * torch.tensor([1.0, 0.5, 0.2]) ** 5)
        dim = torch.full((1, 3, 1, 1), 0.5)
        assert hdr_boost(dim, r0).item() == pytest.approx(0.4)
        near = torch.tensor([0.2, 0.995, 0.4]).view(1, 3, 1, 1)
        assert hdr_boost(near, r0).item() == pytest.approx(3.0 * 0.995**5, rel=1e-6)
        assert hdr_boost(near, r0, beta=2.5).item() == pytest.approx(3.0 * 0.995**2.5, rel=1e-6)

    def test_a_lone_saturated_spot_weighs_more(self):
        # one saturated pixel: 1/16 of its 4-px cell, 1/400 of the 5 x 5 cells around it; a
        # saturated 24 x 24 block fills every such square around its middle
        from d2f_core.rendering.radiance import SPOT_ALPHA

        img = torch.full((2, 3, 40, 48), 0.3)
        img[0, :, 17, 21] = 1.0
        img[1, :, 8:32, 12:36] = 1.0
        img[1, 1, 8:32, 12:36] = 0.995  # the brightest channel decides
        plain = hdr_boost(img, None)
        spot = hdr_boost(img, None, spot=SPOT_ALPHA)
        lone = 3.0 + (SPOT_ALPHA - 3.0) * (1 - 1 / 400) ** 4
        assert float(spot[0, 0, 17, 21]) == pytest.approx(lone, rel=1e-5)
        assert float(plain[0, 0, 17, 21]) == pytest.approx(3.0)
        assert float(spot[1, 0, 20, 24]) == pytest.approx(3.0, rel=1e-6)  # a wide highlight
        edge = float(spot[1, 0, 8, 12])  # its corner: a quarter of the square around it
        assert 3.0 < edge < lone
        # unsaturated pixels keep their weight; the boost never falls under the paper's
        unsaturated = img.amax(dim=1, keepdim=True) < 0.99
        assert bool((spot[unsaturated] == 1).all()) and bool((spot >= plain - 1e-6).all())
        # with gradients (dense) the same numbers; per channel, the same share
        src = img.clone().requires_grad_()
        with torch.enable_grad():
            dense = hdr_boost(src, None, spot=SPOT_ALPHA)
        assert dense.requires_grad
        torch.testing.assert_close(dense.detach(), spot)
        per = hdr_boost(img, None, spot=SPOT_ALPHA, per_channel=True)
        assert float(per[0, 0, 17, 21]) == pytest.approx(lone, rel=1e-5)
        with pytest.raises(ValueError, match="spot"):
            hdr_boost(img, None, spot=-1.0)

    def test_render_boosts_lone_spots_with_or_without_a_radiance_map(self):
        # a small lamp on a far dark wall, focus near: the render weighs it as hdr_boost's
        # spot weight does, with no radiance map and with one, and its disc is brighter than
        # with the paper's boost alone
        from d2f_core.rendering.radiance import SPOT_ALPHA

        img = torch.full((1, 3, 64, 64), 0.05)
        img[..., 31:33, 31:33] = 1.0
        disp = torch.zeros(1, 1, 64, 64)
        own = render(img, disp, 1.0, 16.0, quality="exact")
        spot = hdr_boost(img, None, spot=SPOT_ALPHA)
        weighed = render(
            img, disp, 1.0, 16.0, quality="exact", radiance=spot, highlight_boost=False
        )
        torch.testing.assert_close(own, weighed)
        ones = torch.ones_like(disp)
        mapped = render(img, disp, 1.0, 16.0, quality="exact", radiance=ones)
        spotted = render(
            img, disp, 1.0, 16.0, quality="exact", radiance=hdr_boost(img, ones, spot=SPOT_ALPHA),
            highlight_boost=False,
        )  # fmt: skip
        torch.testing.assert_close(mapped, spotted)
        paper = render(
            img, disp, 1.0, 16.0, quality="exact", radiance=hdr_boost(img, None),
            highlight_boost=False,
        )  # fmt: skip
        assert float(own[0, 0, 32, 36]) > 1.5 * float(paper[0, 0, 32, 36])


class TestBands:
    """Without gradients the plan and the highlight weights are computed by bands of rows:
    the same numbers as over the whole frame, bit for bit."""

    @staticmethod
    def whole_and_banded(monkeypatch, fn):
        whole = fn()
        _row_band(monkeypatch, 97)  # bands of 1-2 rows, a short last one
        with torch.inference_mode():
            banded = fn()
        return whole, banded

    @pytest.mark.parametrize("placement", ["nearest", "paper"])
    def test_layer_plan(self, monkeypatch, placement):
        gen = torch.Generator().manual_seed(8)
        disp = torch.rand(2, 1, 37, 53, generator=gen)
        disp[1, 0, 5, 7] = 1.0  # the largest CoC on one pixel of the second image
        focus = torch.tensor([0.45, 0.2]).view(2, 1, 1, 1)
        whole, banded = self.whole_and_banded(
            monkeypatch,
            lambda: rendering.layer_plan(disp, focus, 83.0, placement=placement),
        )
        assert whole.order == banded.order and len(whole.order) > 5
        assert torch.equal(whole.coord, banded.coord)
        # the largest CoC from the extremes picked the same cut of the schedule
        assert max(abs(c) for c, _ in whole.order) == max(abs(c) for c, _ in banded.order)

    def test_layer_plan_from_given_extremes(self, monkeypatch):
        # the caller's extremes (render has them from its input checks) give the same plan
        disp = 0.4 + torch.rand(1, 1, 37, 53, generator=torch.Generator().manual_seed(5)) * 0.3
        focus = torch.full((1, 1, 1, 1), 0.9)
        _row_band(monkeypatch, 97)
        with torch.inference_mode():
            plain = rendering.layer_plan(disp, focus, 83.0)
            given = rendering.layer_plan(
                disp, focus, 83.0, extremes=rendering.inputs.tensor_extremes(disp)
            )
            wrong = rendering.layer_plan(disp, focus, 83.0, extremes=(0.0, 0.7))
        assert plain.order == given.order and torch.equal(plain.coord, given.coord)
        # (they are used: a farther lowest value asks for larger kernels)
        assert max(k for _, k in wrong.order) > max(k for _, k in plain.order)

    def test_mixed_dtypes_and_broadcast_radiance_as_whole_frame(self, monkeypatch):
        """A float64 focus on a float32 map promotes the plan to float64, and a radiance of
        one value per image broadcasts: both as over the whole frame."""
        gen = torch.Generator().manual_seed(10)
        disp = torch.rand(1, 1, 30, 40, generator=gen)
        focus = torch.full((1, 1, 1, 1), 0.3, dtype=torch.float64)
        whole, banded = self.whole_and_banded(
            monkeypatch, lambda: rendering.layer_plan(disp, focus, 50.0)
        )
        assert banded.coord.dtype == torch.float64 and torch.equal(whole.coord, banded.coord)
        img = torch.rand(1, 3, 30, 40, generator=gen)
        r0 = torch.full((1, 1, 1, 1), 0.5)
        whole, banded = self.whole_and_banded(monkeypatch, lambda: hdr_boost(img, r0))
        assert banded.shape == (1, 1, 30, 40) and torch.equal(whole, banded)

    def test_layer_plan_keeps_gradients_whole(self, monkeypatch):
        _row_band(monkeypatch, 97)
        disp = torch.rand(1, 1, 20, 30, requires_grad=True)
        plan = rendering.layer_plan(disp, torch.full((1, 1, 1, 1), 0.5), 40.0)
        plan.coord.sum().backward()
        assert disp.grad is not None and disp.grad.abs().sum() > 0

    @pytest.mark.parametrize("with_radiance", [False, True])
    def test_hdr_boost(self, monkeypatch, with_radiance):
        gen = torch.Generator().manual_seed(9)
        img = torch.rand(2, 3, 31, 45, generator=gen)
        img[:, :, ::4] = 0.995  # highlights in every fourth row
        r0 = torch.rand(2, 1, 31, 45, generator=gen) if with_radiance else None
        whole, banded = self.whole_and_banded(monkeypatch, lambda: hdr_boost(img, r0))
        assert torch.equal(whole, banded) and (whole > 2.9).any()


@pytest.mark.parametrize("size", [1, 3, 5, 9])
def test_max_and_min_filters_are_max_pool(size):
    # the window-doubling filters against max_pool2d (edges held: padding a maximum with
    # the edge value is padding it with -inf), and the minimum as the negated maximum
    t = torch.randn(2, 3, 17, 23, generator=torch.Generator().manual_seed(size))
    pool = F.max_pool2d(t, size, stride=1, padding=size // 2)
    assert torch.equal(rendering.hidden._max_filter(t, size), pool)
    low = rendering.hidden._max_filter(t, size, torch.minimum)
    assert torch.equal(low, -F.max_pool2d(-t, size, stride=1, padding=size // 2))


@pytest.mark.parametrize("shape", [(1, 1, 8, 12), (1, 1, 9, 13), (1, 5, 31, 7), (2, 1, 1, 1)])
@pytest.mark.parametrize("g", [1, 2, 3, 4, 8])
def test_cell_max_is_max_pool(shape, g):
    """Cell maxima by strided maxima: max_pool2d's numbers, partial cells included."""
    t = torch.randn(*shape, generator=torch.Generator().manual_seed(g))
    want = F.max_pool2d(t, g, g, ceil_mode=True)
    got = rendering.hidden._cell_max(t, g)
    assert got.shape == want.shape and torch.equal(got, want)


@pytest.mark.parametrize("rows", [1, 6, 7, 8, 23])
def test_transposed_in_blocks(monkeypatch, rows):
    """A tall matrix transposed block by block: the same as one transpose, whatever the
    last block holds."""
    monkeypatch.setattr(rendering.blur, "_TRANSPOSE_ROWS", 7)
    m = torch.randn(rows, 15, generator=torch.Generator().manual_seed(rows))
    got = rendering.blur._transposed(m)
    assert got.is_contiguous() and torch.equal(got, m.t().contiguous())


class TestImplementations:
    @pytest.mark.parametrize("order", ["depth", "paper"])
    def test_fft_crop_skip_equals_direct_full_frame(self, order):
        img = _texture(40, 52, seed=4).double()
        disp = torch.rand(1, 1, 40, 52, generator=torch.Generator().manual_seed(5)).double()
        fast = render(img, disp, 0.6, 45.0, order=order, quality="exact")
        ref = render(
            img, disp, 0.6, 45.0, order=order, quality="exact", method="direct", full_frame=True
        )
        assert torch.allclose(fast, ref, atol=1e-9)

    @pytest.mark.parametrize("quality", ["high", "balanced", "fast"])
    def test_reduced_resolution_stays_close_to_exact(self, quality):
        img = _texture(96, 128, seed=6)
        yy = torch.linspace(0, 1, 96).view(1, 1, 96, 1).expand(1, 1, 96, 128)
        disp = yy + 0.1 * torch.rand(1, 1, 96, 128, generator=torch.Generator().manual_seed(7))
        disp = disp.clamp(0, 1)
        ref = render(img.double(), disp.double(), 0.3, 90.0, quality="exact")
        out = render(img, disp, 0.3, 90.0, quality=quality)
        assert psnr(out, ref) >= 45.0

    @pytest.mark.usefixtures("one_thread")
    def test_module_equals_function(self):
        # one thread: with two, a render differs from the same render by one float32 ulp on
        # about 1 call in 1,500 (the threads' order of summation), more often under load
        img, disp = _texture(), _ramp()
        mod = LayeredRenderer(order="depth", blades=5, rotation=12.0)
        assert torch.equal(
            mod(img, disp, 0.4, 33.0), render(img, disp, 0.4, 33.0, blades=5, rotation=12.0)
        )

    def test_batch_matches_single(self):
        img = torch.cat([_texture(seed=1), _texture(seed=2)])
        disp = torch.cat([_ramp(), 1 - _ramp()])
        out = render(img, disp, torch.tensor([0.2, 0.7]), 30.0)
        assert torch.allclose(out[:1], render(img[:1], disp[:1], 0.2, 30.0), atol=1e-6)
        assert torch.allclose(out[1:], render(img[1:], disp[1:], 0.7, 30.0), atol=1e-6)

    @pytest.mark.slow
    def test_gradcheck(self):
        g = torch.Generator().manual_seed(8)
        img = (torch.rand(1, 3, 9, 9, generator=g, dtype=torch.float64) * 0.8).requires_grad_()
        disp = torch.rand(1, 1, 9, 9, generator=g, dtype=torch.float64).requires_grad_()
        r0 = (torch.rand(1, 1, 9, 9, generator=g, dtype=torch.float64) + 0.1).requires_grad_()

        def fn(i, d, r):
            return render(i, d, 0.5, 8.0, radiance=r, quality="exact")

        assert torch.autograd.gradcheck(fn, (img, disp, r0), eps=1e-6, atol=1e-5)

    @pytest.mark.parametrize("quality", ["exact", "fast"])
    def test_gradients_flow_through_reduced_resolution_layers(self, quality):
        g = torch.Generator().manual_seed(9)
        img = torch.rand(2, 3, 48, 48, generator=g).requires_grad_()
        disp = torch.rand(2, 1, 48, 48, generator=g).requires_grad_()
        r0 = torch.rand(2, 1, 48, 48, generator=g).requires_grad_()
        out = render(img, disp, torch.tensor([0.2, 0.9]), 60.0, radiance=r0, quality=quality)
        out.square().mean().backward()
        for t in (img, disp, r0):
            assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0
        with torch.no_grad():
            same = render(img, disp, torch.tensor([0.2, 0.9]), 60.0, radiance=r0, quality=quality)
        assert torch.allclose(out, same, atol=1e-6)

    @staticmethod
    def _true_support(plan, centre, height, width):
        """Tiles where the layer's exact mask reaches _MASK_EPS: [tile rows], [tile columns]."""
        mask = plan.mask(plan.side_coord(centre), centre)[0, 0]
        hit = F.max_pool2d(mask[None, None], _TILE, ceil_mode=True)[0, 0] >= _MASK_EPS
        return hit.any(dim=1), hit.any(dim=0)

    @pytest.mark.parametrize("order", ["depth", "paper"])
    @pytest.mark.parametrize("placement", ["nearest", "paper"])
    @pytest.mark.parametrize("scene", ["edge", "noise", "ramp"])
    def test_support_boxes_hold_every_reached_pixel(self, order, placement, scene):
        # a layer's box must hold every pixel its mask reaches, and a layer that reaches a
        # pixel must have a box
        g = torch.Generator().manual_seed(12)
        height, width = 61, 83  # not whole tiles
        if scene == "edge":
            disp = torch.full((1, 1, height, width), 0.05)
            disp[..., 9:40, 17:51] = 0.93
        elif scene == "noise":
            disp = torch.rand(1, 1, height, width, generator=g) ** 3
        else:
            disp = _ramp(height, width)
        for focus in (0.0, 0.31, 0.93, 1.0):
            plan = layer_plan(
                disp, torch.full((1, 1, 1, 1), focus), 70.0, order=order, placement=placement
            )
            boxes = _support_boxes(plan, height, width)
            for centre, _ in plan.order:
                rows, cols = self._true_support(plan, centre, height, width)
                if not rows.any():
                    continue
                assert centre in boxes, (focus, centre)
                y0, y1, x0, x1 = boxes[centre]
                r = torch.nonzero(rows).flatten()
                c = torch.nonzero(cols).flatten()
                assert y0 <= r[0] * _TILE and min(height, (r[-1] + 1) * _TILE) <= y1
                assert x0 <= c[0] * _TILE and min(width, (c[-1] + 1) * _TILE) <= x1

    def test_depth_edge_skips_the_layers_between_its_sides(self):
        # a sharp subject over a far background: every 8-px tile on the silhouette holds both
        # depths, but no pixel lies between them, so the layers in between get no box, and a
        # layer on one side gets a box around that side's pixels only
        height, width = 96, 128
        disp = torch.full((1, 1, height, width), 0.1)
        disp[..., 28:70, 37:91] = 0.85
        plan = layer_plan(disp, torch.full((1, 1, 1, 1), 0.85), 60.0)
        boxes = _support_boxes(plan, height, width)
        reached = {
            centre
            for centre, _ in plan.order
            if self._true_support(plan, centre, height, width)[0].any()
        }
        assert len(plan.order) > 2 * len(reached)  # most layers hold no pixel
        assert set(boxes) == reached
        assert boxes[0] == (24, 72, 32, 96)  # the subject, grown to whole tiles

    @pytest.mark.parametrize("method", ["fft", "direct"])
    def test_cropped_layers_match_plain_layered_model(self, method):
        # the model written out plainly: every layer masked over the whole frame, convolved
        # with a zero-padded 'same' convolution, composited back to front
        img, disp = _boxed_scene()
        plan = layer_plan(disp.double(), torch.full((1, 1, 1, 1), 0.5).double(), 40.0)
        x = img.double()
        acc = torch.zeros(1, 4, 50, 70, dtype=torch.float64)
        for centre, size in plan.order:
            mask = plan.mask(plan.side_coord(centre), centre)
            z = torch.cat([mask, mask * x], dim=1)
            r = size // 2
            k = aperture_kernel(2 * r + 1, radius=r, dtype=torch.float64)
            blurred = F.conv2d(F.pad(z, (r,) * 4), k.flip(-1, -2).expand(4, 1, -1, -1), groups=4)
            acc = acc * (1 - blurred[:, :1].clamp(0, 1)) + blurred
        # and under every layer, what lies behind the rims of blurred near objects
        ones_x = torch.cat([torch.ones_like(x[:, :1]), x], dim=1)
        hidden = hidden_surface(lambda ys, xs: ones_x[0][:, ys, xs], plan)
        assert hidden is not None
        y0, y1, x0, x1 = hidden.box
        under = torch.zeros_like(acc)
        under[..., y0:y1, x0:x1] = hidden.window(y0, y1, x0, x1)
        assert under[:, :1].max() > 0.5
        acc = acc + (1 - acc[:, :1].clamp(0, 1)) * under
        expected = (acc[:, 1:] / acc[:, :1]).clamp(0, 1)
        with torch.no_grad():
            out = render(img, disp, 0.5, 40.0, quality="exact", method=method)
        assert torch.allclose(out.double(), expected, atol=1e-5)

    @pytest.mark.parametrize("method", ["fft", "direct"])
    @pytest.mark.parametrize("quality", ["high", "balanced", "fast"])
    def test_inference_layout_matches_autograd_path(self, quality, method):
        # without gradients, directly convolved layers are stacked in strips along channels
        # and coarse layers pooled straight from the product; with gradients all are planar
        img, disp = _boxed_scene()
        src = img.clone().requires_grad_()
        with torch.enable_grad():
            ref = render(src, disp, 0.5, 40.0, quality=quality, method=method)
        with torch.no_grad():
            out = render(img, disp, 0.5, 40.0, quality=quality, method=method)
        assert ref.requires_grad and not out.requires_grad
        assert torch.allclose(out, ref.detach(), atol=1e-5)

    def test_inference_mode_inside_leaves_ordinary_tensors(self):
        # without gradients the layers run in inference mode; the result and the cached
        # kernels must still be ordinary tensors that autograd and in-place ops accept
        from d2f_core.rendering import KernelSpec
        from d2f_core.rendering.blur import _spectrum
        from d2f_core.rendering.blur import kernel_tensor as _kernel
        from d2f_core.rendering.plan import _integer_table

        for cache in (_kernel, _spectrum, _integer_table):
            cache.cache_clear()
        with torch.inference_mode():  # first built in inference mode, as a render does
            built = [
                _kernel(KernelSpec(), 15, 2, "cpu", torch.float32),
                _spectrum(KernelSpec(), 15, 2, 32, 32, "cpu", torch.float32, 0.25),
                *_integer_table((0, 2, 4), torch.float32, "cpu"),
            ]
        assert not any(t.is_inference() for t in built)
        img, disp = _texture(), _ramp()
        with torch.no_grad():
            out = render(img, disp, 0.4, 60.0)
        assert not out.is_inference()
        out.mul_(0.5)  # in place, outside inference mode
        src = img.clone().requires_grad_()
        again = render(src, disp, 0.4, 60.0)  # the same cached kernels, now with autograd
        again.mean().backward()
        assert src.grad is not None and src.grad.abs().sum() > 0
        assert torch.allclose(again.detach(), 2 * out, atol=1e-5)

    def test_coarse_layers_use_fitted_kernels_up_to_the_cap(self):
        from d2f_core.rendering import KernelSpec
        from d2f_core.rendering.blur import _FIT_MAX_SIZE
        from d2f_core.rendering.blur import kernel_tensor as _kernel

        spec = KernelSpec("soft", 6, 10.0)
        fitted = _kernel(spec, 33, 2, "cpu", torch.float32)
        assert torch.equal(fitted, coarse_kernel(33, 2, blades=6, rotation=10.0))
        quarter = _kernel(spec, 33, 2, "cpu", torch.float32, 0.25)
        assert torch.allclose(quarter, 0.25 * fitted, rtol=1e-6, atol=0)
        assert torch.equal(
            _kernel(spec, 7, 1, "cpu", torch.float32), aperture_kernel(7, blades=6, rotation=10.0)
        )
        # above the cap the aperture is sampled on the coarse grid
        size = _FIT_MAX_SIZE + 88
        r = size // 2
        half = math.ceil(r / 4 + 0.5)
        sampled = aperture_kernel(2 * half + 1, blades=6, rotation=10.0, radius=r, scale=4.0)
        assert torch.equal(_kernel(spec, size, 4, "cpu", torch.float32), sampled)

    def test_reduced_resolution_keeps_polygon_corners(self):
        # a 6-blade aperture at half resolution is as wide across its corners as at full
        # resolution (the sampled coarse kernel rounded them: 1.057 against 1.121)
        img = torch.full((1, 3, 96, 96), 0.05)
        img[..., 47:50, 47:50] = 1.0
        disp = torch.zeros(1, 1, 96, 96)

        def aspect(out):
            lum = out[0].mean(0) - 0.05
            inside = (lum > 0.5 * lum[48, 48]).nonzero()
            ys, xs = inside[:, 0], inside[:, 1]
            return float(xs.max() - xs.min() + 1) / float(ys.max() - ys.min() + 1)

        exact = aspect(render(img, disp, 1.0, 40.0, blades=6, quality="exact"))
        assert exact > 1.1
        for quality in ("high", "balanced", "fast"):
            assert aspect(render(img, disp, 1.0, 40.0, blades=6, quality=quality)) == pytest.approx(
                exact, abs=0.02
            )

    @pytest.mark.parametrize("channels", [4, 5, 7])
    @pytest.mark.parametrize("size", [3, 7, 11, 23])
    @pytest.mark.parametrize(
        "frame,box",
        [
            ((50, 70), (0, 50, 0, 70)),  # whole frame
            ((50, 70), (16, 24, 8, 40)),  # interior: output rows grown to whole strips
            ((61, 33), (0, 9, 25, 33)),  # at a corner, odd frame height
            ((6, 90), (2, 5, 0, 90)),  # too few rows for more than one strip
        ],
    )
    def test_strip_stacked_convolution(self, channels, size, frame, box):
        # strips of the layer stacked along channels, against one plain convolution of the
        # whole zero-padded layer
        from d2f_core.rendering import KernelSpec
        from d2f_core.rendering.blur import (
            direct_stacked as _direct_stacked,
        )
        from d2f_core.rendering.blur import (
            kernel_tensor as _kernel,
        )

        height, width = frame
        y0, y1, x0, x1 = box
        g = torch.Generator().manual_seed(size + channels)
        layer = torch.rand(2, channels, y1 - y0, x1 - x0, generator=g, dtype=torch.float64)
        k = _kernel(KernelSpec(), size, 1, "cpu", torch.float64)
        r = k.shape[-1] // 2
        full = torch.zeros(2, channels, height + 2 * r, width + 2 * r, dtype=torch.float64)
        full[..., y0 + r : y1 + r, x0 + r : x1 + r] = layer
        expected = F.conv2d(full, k.flip(-1, -2).expand(channels, 1, -1, -1), groups=channels)

        def rows(r0, r1, out):
            return out.copy_(layer[..., r0:r1, :])

        out, oy0, ox0 = _direct_stacked(rows, layer, channels, box, k, frame)
        s, hs, wo = out.shape[-3:]
        assert out.shape[:2] == (2, channels) and 0 <= oy0 and oy0 + s * hs <= height
        got = torch.zeros_like(expected)
        got[..., oy0 : oy0 + s * hs, ox0 : ox0 + wo] = out.flatten(2, 3)
        # inside the output window: the convolution; outside it: nothing reaches
        assert oy0 <= max(0, y0 - r) and oy0 + s * hs >= min(height, y1 + r)
        assert ox0 == max(0, x0 - r) and ox0 + wo == min(width, x1 + r)
        torch.testing.assert_close(got, expected, atol=1e-12, rtol=0)
        if box == (0, 50, 0, 70):
            assert s > 1  # the strips are in use, not just the single-strip fallback

    @pytest.mark.skipif(
        not hasattr(__import__("os"), "confstr")
        or not (__import__("os").confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"),
        reason="glibc's malloc only",
    )
    @pytest.mark.slow
    def test_frame_sized_blocks_come_from_the_heap(self):
        # after the first render's setting, a 16 MB block (a 5-channel 1 MP frame) is carved
        # from the heap, whose freed memory glibc keeps, instead of being mapped (and later
        # unmapped and zero-filled again) on its own; mallinfo2 counts the mapped bytes
        import subprocess
        import sys

        script = """
import ctypes, sys, torch
from d2f_core import rendering
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split())]
libc = ctypes.CDLL(None)
if not hasattr(libc, "mallinfo2"):
    print("skip")
    sys.exit()
libc.mallinfo2.restype = Info
if sys.argv[1] == "on":
    assert rendering.api._keep_freed_heap()
    img = torch.rand(1, 3, 64, 96)
    rendering.render(img, img[:, :1], 0.5, 10.0)  # the setting holds across a render
before = libc.mallinfo2().hblkhd
block = torch.empty(16 << 20, dtype=torch.uint8)
print(libc.mallinfo2().hblkhd - before)
"""
        mapped = {}
        for mode in ("on", "off"):
            run = subprocess.run(
                [sys.executable, "-c", script, mode], capture_output=True, text=True, timeout=300
            )
            assert run.returncode == 0, run.stderr
            if run.stdout.split()[-1] == "skip":
                pytest.skip("this glibc has no mallinfo2")
            mapped[mode] = int(run.stdout.split()[-1])
        assert mapped["off"] >= 16 << 20, mapped  # mapped on its own without the setting
        assert mapped["on"] == 0, mapped

    @pytest.mark.parametrize(
        "knots",
        [[1.0, 3.0, 5.0, 7.0, 11.0, 15.0, 19.0, 23.0, 27.0, 33.0, 39.0, 45.0, 53.0, 61.0, 69.0],
         [1.0, 4.0, 90.0, 91.0], [0.5, 2.25, 7.0]],
    )  # fmt: skip
    def test_interp_matches_numpy(self, knots):
        # integer knots use a table over the integers, others a binary search: both are
        # np.interp onto the knot index, with its slope as the gradient
        from d2f_core.rendering.plan import _interp

        g = torch.Generator().manual_seed(1)
        x = torch.rand(1, 1, 30, 40, generator=g, dtype=torch.float64) * 100 - 5
        x[0, 0, 0, : len(knots)] = torch.tensor(knots, dtype=torch.float64)  # knots exactly
        x.requires_grad_()
        got = _interp(x, knots)
        index = np.arange(len(knots), dtype=np.float64)
        expected = np.interp(x.detach().numpy(), knots, index)
        np.testing.assert_allclose(got.detach().numpy(), expected, rtol=0, atol=1e-12)
        assert got[0, 0, 0, : len(knots)].tolist() == index.tolist()
        got.sum().backward()
        xs = x.detach().numpy()
        inside = (xs > knots[0]) & (xs < knots[-1])
        seg = np.clip(np.searchsorted(knots, xs, side="right"), 1, len(knots) - 1)
        slope = 1 / (np.asarray(knots)[seg] - np.asarray(knots)[seg - 1])
        np.testing.assert_allclose(x.grad.numpy()[inside], slope[inside], rtol=1e-12)
        assert (x.grad.numpy()[(xs < knots[0]) | (xs > knots[-1])] == 0).all()

    @pytest.mark.parametrize("factor", [2, 4])
    @pytest.mark.parametrize("shape", [(1, 6, 12, 18), (2, 3, 5, 7), (1, 1, 1, 1), (1, 2, 1, 9)])
    def test_upsample_matches_interpolate(self, factor, shape):
        from d2f_core.rendering.blur import upsample_grid as _upsample

        z = torch.rand(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
        height, width = shape[2] * factor - 1, shape[3] * factor - 2
        up = F.interpolate(z, scale_factor=factor, mode="bilinear", align_corners=False)
        expected = up[..., :height, :width]
        torch.testing.assert_close(_upsample(z, factor, height, width), expected)
        zg = z.clone().requires_grad_()
        torch.testing.assert_close(_upsample(zg, factor, height, width), expected)

    @pytest.mark.parametrize("factor", [2, 4, 8])
    def test_pooling_matches_avg_pool(self, factor):
        from d2f_core.rendering.blur import pool_grid as _pool
        from d2f_core.rendering.blur import pool_product as _pool_product

        g = torch.Generator().manual_seed(factor)
        x = torch.rand(2, 5, 24, 40, generator=g, dtype=torch.float64)
        mask = torch.rand(2, 1, 24, 40, generator=g, dtype=torch.float64)
        expected = F.avg_pool2d(mask * x, factor)
        torch.testing.assert_close(_pool(mask * x, factor), expected)
        torch.testing.assert_close(_pool_product(x, mask, factor), expected)
        out, out_product = torch.empty_like(expected), torch.empty_like(expected)
        assert _pool(mask * x, factor, out) is out
        assert _pool_product(x, mask, factor, out_product) is out_product
        torch.testing.assert_close(out, expected)
        torch.testing.assert_close(out_product, expected)
        # sums (the no-gradient path: the kernel carries the 1 / factor**2)
        sums = expected * factor**2
        torch.testing.assert_close(_pool(mask * x, factor, mean=False), sums)
        torch.testing.assert_close(_pool_product(x, mask, factor, out, mean=False), sums)

    def test_coarse_kernel_gain(self):
        # the no-gradient path blurs cell sums with the kernel times 1 / factor**2: the same
        # composite as cell means with the plain kernel, in direct and FFT convolution
        from d2f_core.rendering import KernelSpec
        from d2f_core.rendering.blur import fft_conv as _fft
        from d2f_core.rendering.blur import kernel_tensor as _kernel

        spec = KernelSpec()
        k = _kernel(spec, 23, 2, "cpu", torch.float64)
        k4 = _kernel(spec, 23, 2, "cpu", torch.float64, 0.25)
        torch.testing.assert_close(k4, k / 4, atol=0, rtol=0)
        z = torch.rand(
            1, 5, 20, 30, dtype=torch.float64, generator=torch.Generator().manual_seed(3)
        )
        torch.testing.assert_close(_fft(4 * z, spec, 23, 2, 0.25), _fft(z, spec, 23, 2))


class TestFocusBlurChecks:
    """``check_focus_blur`` owns the focus and blur rule; each public entry checks them once
    and passes the floats down (``checked=True``), and ``render`` called directly still checks
    its own input."""

    @staticmethod
    def _count(monkeypatch) -> list[float]:
        seen: list[float] = []
        check = rendering.inputs._check_focus
        monkeypatch.setattr(rendering.inputs, "_check_focus", lambda v: seen.append(v) or check(v))
        return seen

    @pytest.mark.parametrize(
        "focus,blur,match",
        [
            (1.5, 10.0, r"focus must be in \[0, 1\], got 1\.5"),
            (float("nan"), 10.0, "focus must be in"),
            ("near", 10.0, "focus must be a number, got 'near'"),
            (torch.tensor([0.2, 1.5]), 10.0, r"focus must be in \[0, 1\], got 1\.5"),
            (torch.tensor([0.2, float("nan")]), 10.0, "focus must be in"),
            (torch.tensor([0.2, 0.3, 0.4]), 10.0, "focus must be a scalar or have 2 values"),
            (0.5, -1.0, r"blur must be a number in \[0, 10000\] px, got -1\.0"),
            (0.5, float("inf"), "blur must be a number in"),
            (0.5, None, "blur must be a number, got None"),
        ],
    )
    def test_render_called_directly_checks_its_input(self, focus, blur, match):
        img, disp = _texture().repeat(2, 1, 1, 1), _ramp().repeat(2, 1, 1, 1)
        with pytest.raises(ValueError, match=match):
            render(img, disp, focus, blur)

    def test_each_public_entry_checks_focus_once(self, monkeypatch):
        from d2f_core.rendering import adaptive

        img, disp = _texture(24, 32), _ramp(24, 32)
        calls = {
            "render": lambda: render(img, disp, 0.4, 12.0),
            "render_bokeh": lambda: render_bokeh(
                img[0].permute(1, 2, 0).numpy(), disp[0, 0].numpy(), 0.4, 12.0
            ),
            "LayeredRenderer": lambda: LayeredRenderer()(img, disp, 0.4, 12.0),
            "choose_settings": lambda: adaptive.choose_settings(disp, 0.4, 12.0),
            "render_adaptive": lambda: adaptive.render_adaptive(img, disp, 0.4, 12.0),
            # a batch is checked once, then its images render one by one unchecked
            "render, a batch": lambda: render(
                img.repeat(3, 1, 1, 1), disp.repeat(3, 1, 1, 1), torch.tensor([0.1, 0.4, 0.9]), 12.0
            ),
        }
        counts = {}
        for name, call in calls.items():
            seen = self._count(monkeypatch)
            call()
            counts[name] = len(seen)
        # LayeredRenderer() also checks its options once, by a render of one pixel; the batch
        # checks the least and the largest focus of its tensor
        expected = {name: 1 for name in calls} | {"LayeredRenderer": 2, "render, a batch": 2}
        assert counts == expected

    @pytest.mark.usefixtures("one_thread")  # two threads differ by an ulp now and then
    def test_checked_values_render_the_same(self):
        img = torch.cat([_texture(seed=1), _texture(seed=2)])
        disp = torch.cat([_ramp(), 1 - _ramp()])
        for focus in (0.3, torch.tensor([0.2, 0.7])):
            torch.testing.assert_close(
                render(img, disp, focus, 30.0, checked=True),
                render(img, disp, focus, 30.0),
                atol=0,
                rtol=0,
            )


class TestNumpyAPI:
    def test_uint8_and_float_agree(self):
        rng = np.random.default_rng(0)
        img8 = rng.integers(0, 256, (30, 40, 3), dtype=np.uint8)
        disp = rng.random((30, 40)).astype(np.float32)
        a = render_bokeh(img8, disp, 0.5, 20.0)
        b = render_bokeh(img8.astype(np.float32) / 255, disp, 0.5, 20.0)
        assert a.dtype == np.float32 and a.shape == (30, 40, 3)
        np.testing.assert_allclose(a, b, atol=1e-6)

    def test_disparity_rounding_slack_is_clamped_beyond_it_refused(self):
        """Maps converted from 8/16-bit depth overshoot [0, 1] by rounding: up to 1e-3 is
        clamped (the render equals the clamped map's), more is refused, the same way as
        D2F.prepare (one checker)."""
        rng = np.random.default_rng(1)
        img = rng.random((20, 24, 3)).astype(np.float32)
        disp = rng.random((20, 24)).astype(np.float32)
        over = disp.copy()
        over[0, :12], over[1, :12] = 1.0008, -0.0008
        clamped = np.clip(over, 0, 1)
        np.testing.assert_array_equal(
            render_bokeh(img, over, 0.5, 12.0), render_bokeh(img, clamped, 0.5, 12.0)
        )
        assert not np.array_equal(
            render_bokeh(img, clamped, 0.5, 12.0), render_bokeh(img, disp, 0.5, 12.0)
        )
        for bad in (1.002, -0.002):
            wrong = disp.copy()
            wrong[3, 3] = bad
            with pytest.raises(ValueError, match=r"disparity must be in \[0, 1\]"):
                render_bokeh(img, wrong, 0.5, 12.0)
        # tensors, H x W x 1 and nested lists are read as the same map
        ref = render_bokeh(img, disp, 0.5, 12.0)
        for form in (torch.from_numpy(disp), disp[..., None], disp.tolist()):
            np.testing.assert_array_equal(render_bokeh(img, form, 0.5, 12.0), ref)
        # the image too: an H x W x 3 tensor or nested lists read as the array
        for form in (torch.from_numpy(img), img.tolist()):
            np.testing.assert_array_equal(render_bokeh(form, disp, 0.5, 12.0), ref)

    @pytest.mark.parametrize(
        "kwargs,match",
        [
            ({"focus": -0.1}, "focus"),
            ({"focus": 1.5}, "focus"),
            ({"focus": float("nan")}, "focus"),
            ({"focus": float("inf")}, "focus"),
            ({"blur": -1.0}, "blur"),
            ({"blur": float("nan")}, "blur"),
            ({"disparity": np.zeros((10, 12), np.float32)}, "shape"),
            ({"disparity": np.full((12, 16), np.nan, np.float32)}, "NaN"),
            ({"disparity": np.full((12, 16), np.inf, np.float32)}, "NaN or inf"),
            ({"disparity": np.full((12, 16), 2.0, np.float32)}, r"\[0, 1\]"),
            ({"image": np.zeros((12, 16), np.float32)}, "image"),
            ({"image": np.full((12, 16, 3), np.nan, np.float32)}, "NaN"),
            ({"image": np.full((12, 16, 3), 1.5, np.float32)}, r"\[0, 1\]"),
            ({"order": "random"}, "order"),
            ({"quality": "ultra"}, "quality"),
            # wrong types and dtypes: InputTypeError, a ValueError and a TypeError
            ({"image": np.zeros((12, 16, 3), np.int16)}, "uint8 or float"),
            ({"image": "photo.jpg"}, "image"),
            ({"disparity": np.zeros((12, 16), np.complex64)}, "disparity"),
            ({"disparity": np.zeros((12, 16), dtype=object)}, "disparity"),
            ({"focus": "near"}, "focus"),
            ({"blur": None}, "blur"),
        ],
    )
    def test_bad_inputs_raise_value_error(self, kwargs, match):
        args = {
            "image": np.zeros((12, 16, 3), np.float32),
            "disparity": np.zeros((12, 16), np.float32),
            "focus": 0.5,
            "blur": 10.0,
        }
        args.update(kwargs)
        with pytest.raises(ValueError, match=match):
            render_bokeh(**args)


@pytest.mark.parametrize("grad", [False, True])
def test_layer_mask_has_no_denormal_floats(grad):
    # the sigmoid's tail passes through denormal floats (under 1.2e-38) before it reaches 0;
    # convolving a layer holding them ran 2x slower at 512x768 (x86 arithmetic on denormals)
    coord = torch.linspace(-30.0, 30.0, 600_001)
    gamma = rendering.GAMMA / 14.0
    mask = _layer_mask(coord.clone(), 0, gamma, grad)
    plain = torch.sigmoid(2 * gamma * (1.0 - coord.abs()))
    assert bool(((plain > 0) & (plain < torch.finfo(torch.float32).tiny)).any())  # it would
    assert not bool(((mask > 0) & (mask < torch.finfo(torch.float32).tiny)).any())
    kept = plain > 1e-20
    torch.testing.assert_close(mask[kept], plain[kept], rtol=1e-5, atol=0)
    assert bool((mask[~kept] == 0).all())


@pytest.mark.parametrize("grad", [False, True])
def test_blend_mask_known_values(grad):
    # layer 2's mask: 0 up to coordinate 1, rising to 1 at 2, 1 up to (not at) 3, then 0
    coord = torch.tensor([-9.0, 0.5, 1.0, 1.25, 1.75, 2.0, 2.5, 2.999, 3.0, 3.5, 9.0])
    want = torch.tensor([0.0, 0.0, 0.0, 0.25, 0.75, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    torch.testing.assert_close(blend_mask(coord.clone(), 2, grad), want)
    # a pixel between two layers: in the first in full, in the second by where it lies
    for u in (2.0, 2.3, 2.9):
        shares = [float(blend_mask(torch.tensor([u]), c, grad)) for c in range(6)]
        assert shares == pytest.approx([0, 0, 1, u - 2, 0, 0], abs=1e-6)
    # no denormal floats next to the ramp's foot
    tiny = torch.tensor([1.0 + 1e-7, 1.0 + 2e-38]) - 0.0
    mask = blend_mask(tiny, 2, grad)
    assert not bool(((mask > 0) & (mask < torch.finfo(torch.float32).tiny)).any())
    if grad:
        c = torch.tensor([1.25, 2.5], requires_grad=True)
        blend_mask(c, 2).sum().backward()
        assert c.grad.tolist() == [1.0, 0.0]  # the ramp carries the gradient


class TestBlendPlacement:
    def test_coordinates_sit_on_the_cocs_the_kernels_draw(self):
        from d2f_core.rendering.kernels import effective_diameter

        focus = torch.tensor(0.5).view(1, 1, 1, 1)
        drawn = [effective_diameter(s) for s in (1, 3, 5, 7, 11)]
        # CoCs on each kernel's drawn CoC, and half-way between two of them
        coc = torch.tensor(drawn + [(drawn[1] + drawn[2]) / 2, (drawn[3] + drawn[4]) / 2])
        disp = torch.cat([0.5 - coc / 20, 0.5 + coc / 20]).view(1, 1, 1, -1)
        plan = layer_plan(disp, focus, 20.0)
        # (float32 rounding may put the largest CoC a hair past kernel 11's: then 15 follows)
        assert plan.blend and [s for c, s in plan.order if c >= 0][:5] == [1, 3, 5, 7, 11]
        u = torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0, 1.5, 3.5])
        torch.testing.assert_close(plan.coord.view(-1), torch.cat([-u, u]), atol=1e-4, rtol=0)
        # the schedule stops at the first kernel that draws the largest CoC
        at = 20.0 * drawn[3] / 10.0  # a largest CoC of 10 px x drawn[3] / 10: kernel 7
        front = (0.5 + torch.tensor([0.0, 0.5])).view(1, 1, 1, -1)
        assert max(s for _, s in layer_plan(front, focus, at).order) == 7
        assert max(s for _, s in layer_plan(front, focus, at * 1.01).order) == 11
        # the hard disk's kernels draw smaller CoCs than the soft ones
        hard = layer_plan(disp, focus, 20.0, kernel="hard")
        assert float(hard.coord.max()) > float(plan.coord.max()) - 1e-6
        assert float(hard.coord[0, 0, 0, 8]) > 1.0

    def test_a_plane_mixes_the_two_kernels_around_its_coc(self):
        # a plane at one CoC between kernels 7 and 11: away from the frame's edges, every
        # pixel shows (1 - t) K_7 + t K_11 of the photo, t where the CoC lies between the
        # CoCs those kernels draw
        from d2f_core.rendering.kernels import effective_diameter

        gen = torch.Generator().manual_seed(5)
        img = torch.rand(1, 3, 48, 64, generator=gen) * 0.9
        c7, c11 = effective_diameter(7), effective_diameter(11)
        coc, t = c7 + 0.3 * (c11 - c7), 0.3
        for sign in (1, -1):
            disp = torch.full((1, 1, 48, 64), 0.5 + sign * coc / 20.0)
            out = render(img, disp, 0.5, 20.0, quality="exact", highlight_boost=False)

            def blurred(size):
                k = aperture_kernel(size)
                r = size // 2
                weight = k.flip(-1, -2).expand(3, 1, -1, -1)
                return F.conv2d(F.pad(img, (r,) * 4), weight, groups=3)

            want = (1 - t) * blurred(7) + t * blurred(11)
            inside = (..., slice(6, -6), slice(6, -6))
            torch.testing.assert_close(out[inside], want[inside], atol=2e-5, rtol=0)

    @staticmethod
    def _plane_psnr(disparity: float, focus: float, blur: float, placement: str) -> float:
        from d2f_core.train.synth import Layer, Scene, render_pinhole, render_thin_lens

        g = np.random.default_rng(3)
        h, w, m = 64, 96, 24
        noise = torch.from_numpy(g.random((1, 3, h + 2 * m, w + 2 * m)).astype(np.float32))
        rgb = (0.15 + 0.35 * (noise + F.avg_pool2d(noise, 3, 1, 1)))[0].numpy()
        layer = Layer(rgb, np.ones(rgb.shape[1:], np.float32), -m, -m, disparity)
        scene = Scene([layer], (h, w), m, focus)
        pinhole, disp = render_pinhole(scene)
        target = np.clip(render_thin_lens(scene, focus, blur, samples=200), 0, 1)
        image = torch.from_numpy(np.clip(pinhole, 0, 1)).permute(2, 0, 1)[None].contiguous()
        out = render(
            image,
            torch.from_numpy(disp)[None, None],
            focus,
            blur,
            quality="exact",
            highlight_boost=False,
            placement=placement,
        )
        crop = int(blur * abs(disparity - focus) / 2) + 2
        pred = out[0].permute(1, 2, 0).numpy()[crop:-crop, crop:-crop]
        return psnr(pred, target[crop:-crop, crop:-crop])

    def test_closer_to_the_thin_lens_truth_than_the_nearest_kernel(self):
        # a textured plane against the accumulation-buffer truth at CoCs between and on
        # kernels, on both sides of focus; measured: blend 35.4-54.8 dB, "nearest" 29.8-52.2
        # dB, blend ahead by 5.6 dB on average and behind at 8 px only (47.01 against 47.27)
        gains = []
        for coc in (1.5, 3.0, 4.0, 5.5, 8.0, 12.5, 17.0):
            for disparity, focus in ((0.9, 0.4), (0.1, 0.6)):
                blur = coc / 0.5
                blend = self._plane_psnr(disparity, focus, blur, "blend")
                nearest = self._plane_psnr(disparity, focus, blur, "nearest")
                assert blend > 35.0 and blend > nearest - 0.5, (coc, disparity, blend, nearest)
                gains.append(blend - nearest)
        assert float(np.mean(gains)) > 4.0


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    h=st.integers(1, 24),
    w=st.integers(1, 24),
    focus=st.floats(0, 1),
    blur=st.floats(0, 200),
    order=st.sampled_from(["depth", "paper"]),
    quality=st.sampled_from(["exact", "balanced", "fast"]),
    blades=st.sampled_from([0, 0, 5, 6]),
    kernel=st.sampled_from(["soft", "hard"]),
    seed=st.integers(0, 2**16),
    saturate=st.booleans(),
)
def test_output_finite_and_in_range(
    h, w, focus, blur, order, quality, blades, kernel, seed, saturate
):
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, 3)).astype(np.float32)
    if saturate:
        img[rng.random((h, w)) < 0.2] = 1.0
    disp = rng.random((h, w)).astype(np.float32)
    out = render_bokeh(
        img, disp, focus, blur, order=order, quality=quality, blades=blades, kernel=kernel
    )
    assert out.shape == (h, w, 3)
    assert np.isfinite(out).all()
    assert out.min() >= 0.0 and out.max() <= 1.0


class TestBehindFocus:
    """``render(..., behind=True)``: the share and colour of the layers at and behind the
    focal plane, which the full-resolution sharpening replaces."""

    @staticmethod
    def _scene(seed: int):
        rng = np.random.default_rng(seed)
        image = torch.from_numpy(rng.random((1, 3, 96, 128), dtype=np.float32))
        disparity = torch.full((1, 1, 96, 128), 0.3)
        disparity[..., 30:60, 40:80] = 1.0  # a near box, blurred over the background
        image[..., 30:60, 40:80] = 0.9
        return image, disparity

    @pytest.mark.parametrize("quality", ["exact", "balanced"])
    def test_splits_the_result_into_behind_and_front(self, quality):
        image, disparity = self._scene(0)
        plain = rendering.render(
            image, disparity, 0.3, 40.0, quality=quality, highlight_boost=False
        )
        out, share, colour = rendering.render(
            image, disparity, 0.3, 40.0, quality=quality, behind=True, highlight_boost=False
        )
        if quality == "exact":  # the same composite (coarse grids merge in another order)
            torch.testing.assert_close(out, plain, atol=1e-5, rtol=0)
        assert float(share[..., 45, 60]) < 0.01  # the middle of the box: all front
        assert float(share[..., 90, 5]) > 0.999  # far from it: all background
        # what is not behind comes from the front layers alone: the same for another
        # background photo under the same box
        other, _ = self._scene(1)
        out2, share2, colour2 = rendering.render(
            other, disparity, 0.3, 40.0, quality=quality, behind=True, highlight_boost=False
        )
        torch.testing.assert_close(share2, share, atol=1e-5, rtol=0)
        torch.testing.assert_close(out2 - share2 * colour2, out - share * colour, atol=1e-3, rtol=0)

    def test_nothing_in_front(self):
        image, disparity = self._scene(0)
        out, share, colour = rendering.render(image, disparity, 1.0, 40.0, behind=True)
        assert torch.equal(share, torch.ones_like(share)) and torch.equal(colour, out)
        out, share, colour = rendering.render(image, disparity, 0.3, 0.0, behind=True)
        assert torch.equal(out, image) and torch.equal(share, torch.ones_like(share))
        batch = rendering.render(image.repeat(2, 1, 1, 1), disparity.repeat(2, 1, 1, 1), 0.3,
                                 40.0, behind=True)  # fmt: skip
        assert [tuple(t.shape) for t in batch] == [
            (2, 3, 96, 128),
            (2, 1, 96, 128),
            (2, 3, 96, 128),
        ]


class TestLargeFrames:
    """The tiled, banded path large frames take (forced here on small ones)."""

    @staticmethod
    def _scene(h=150, w=218, seed=3):
        # sides that are not multiples of the 32-px tile; a far wall, a slanted floor, a near
        # box and a few highlights
        g = torch.Generator().manual_seed(seed)
        image = torch.rand(1, 3, h, w, generator=g) * 0.9
        image[..., 20:24, 30:34] = 1.0
        yy = torch.linspace(0, 1, h).view(1, 1, h, 1).expand(1, 1, h, w)
        disp = (0.15 + 0.7 * yy).clone()
        disp[..., : h // 3, :] = 0.1
        disp[..., 40:90, 120:180] = 0.95
        return image, disp

    @pytest.mark.parametrize("quality", ["balanced", "fast", "high"])
    @pytest.mark.parametrize("order", ["depth", "paper"])
    @pytest.mark.parametrize("boost", [True, False])
    def test_tiled_path_matches_the_layer_by_layer_path(self, monkeypatch, quality, order, boost):
        image, disp = self._scene()
        options = dict(quality=quality, order=order, highlight_boost=boost)
        plain = render(image, disp, 0.55, 260.0, **options)
        exact = render(
            image.double(), disp.double(), 0.55, 260.0, **(options | {"quality": "exact"})
        )
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        monkeypatch.setattr(rendering.tiled, "_BAND_PIXELS", 40 * 218)  # several bands
        calls = []
        tiled_render = rendering.tiled.render_tiled
        monkeypatch.setattr(
            rendering.api, "render_tiled", lambda *a: calls.append(1) or tiled_render(*a)
        )
        tiled = render(image, disp, 0.55, 260.0, **options)
        assert calls and tiled.shape == image.shape and not tiled.is_inference()
        # the same layers, masks and grids: what differs is where the coarse grids end past
        # the frame and the order the grids are merged in
        assert psnr(tiled, plain) >= 50.0
        assert psnr(tiled, exact) >= 40.0

    def test_constant_image_stays_constant(self, monkeypatch):
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        _, disp = self._scene()
        image = torch.tensor([0.2, 0.5, 0.8]).view(1, 3, 1, 1).expand(1, 3, 150, 218).clone()
        out = render(image, disp, 0.5, 200.0)
        assert torch.allclose(out, image, atol=1e-5)

    def test_gradients_and_exact_keep_the_layer_by_layer_path(self, monkeypatch):
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        monkeypatch.setattr(rendering.api, "render_tiled", None)  # would raise if called
        image, disp = self._scene(40, 56)
        render(image, disp, 0.5, 60.0, quality="exact")
        render(image.requires_grad_(), disp, 0.5, 60.0)
        render(image.detach(), disp, 0.5, 60.0, behind=True)

    def test_grid_factors_follow_the_quarter_threshold(self):
        # on every grid a kernel spans at least quarter / 4 cells
        f = rendering.grid_factor
        assert [f(s, "balanced") for s in (13, 15, 38, 39, 77, 78, 155, 156, 900)] == [
            1, 2, 2, 4, 4, 8, 8, 16, 16,
        ]  # fmt: skip
        assert f(89, "high") == 4 and f(90, "high") == 8 and f(180, "high") == 16
        assert f(900, "exact") == 1

    def test_spans(self):
        assert rendering.blur.column_spans([1, 2, 5, 9], gap=3) == [(1, 5), (9, 9)]
        assert rendering.blur.column_spans([1, 2, 5, 9], gap=1) == [(1, 2), (5, 5), (9, 9)]
        assert rendering.blur.column_spans([]) == []

    def test_hit_boxes_cover_the_hit_tiles_once(self):
        # every hit tile in exactly one box, boxes whole tiles, within the rows and columns
        # asked for, and a box's extra tiles only in the gaps of under two tiles it bridges
        g = torch.Generator().manual_seed(3)
        hit = torch.rand(23, 31, generator=g) > 0.8
        hit[:, 12:20] = False  # a gap of 8 tile columns splits the spans
        boxes = rendering.tiles.hit_boxes(hit, 2, 21, 1, 30, 32)
        covered = torch.zeros(23, 31, dtype=torch.int64)
        for y0, y1, x0, x1 in boxes:
            assert y0 % 32 == y1 % 32 == x0 % 32 == x1 % 32 == 0
            assert y1 - y0 <= rendering.tiles.HIT_BAND * 32
            covered[y0 // 32 : y1 // 32, x0 // 32 : x1 // 32] += 1
        assert int(covered.max()) == 1
        inside = torch.zeros_like(hit)
        inside[2:21, 1:30] = True
        assert torch.equal(covered.bool() & hit, hit & inside)
        assert not covered[:, 12:20].any() and not covered[:2].any() and not covered[21:].any()
        assert rendering.tiles.hit_boxes(torch.zeros(4, 4, dtype=torch.bool), 0, 4, 0, 4, 32) == []
        # the boxes of bands of 4 rows lie inside those of bands of 16 (the FFT's pieces
        # cover every tile the masking wrote)
        big = rendering.tiles.hit_boxes(hit, 2, 21, 1, 30, 32, 16)
        for y0, y1, x0, x1 in boxes:
            assert any(a <= y0 and y1 <= b and c <= x0 and x1 <= d for a, b, c, d in big)

    def test_fft_by_pieces_is_the_fft_of_the_whole(self):
        # a layer that is 0 outside two boxes, blurred box by box and summed, is its blur
        g = torch.Generator().manual_seed(11)
        z = torch.zeros(1, 1, 90, 130)
        pieces = [(0, 32, 8, 40), (48, 90, 64, 128)]
        for a, b, c, d in pieces:
            z[..., a:b, c:d] = torch.rand(b - a, d - c, generator=g)
        spec = rendering.KernelSpec()
        whole = rendering.blur.fft_conv(z, spec, 45, 2, 0.25)
        parts = rendering.tiled._PieceBlur(pieces, spec, 45, 2, 0.25)(z)
        assert parts.shape == whole.shape
        torch.testing.assert_close(parts, whole, rtol=0, atol=1e-5)
        assert float(whole.abs().max()) > 0.1

    @pytest.mark.parametrize("h,w", [(64, 96), (70, 96), (64, 101), (75, 101), (20, 25)])
    def test_tile_source_matches_a_padded_copy(self, h, w):
        # tiles read from the frame and its two padded edge copies are those of a padded copy
        x = torch.rand(2, h, w, generator=torch.Generator().manual_seed(h * w))
        src = rendering.tiles.TileSource(x, 32, 7.0)
        ny, nx = -(-h // 32), -(-w // 32)
        padded = torch.full((2, ny * 32, nx * 32), 7.0)
        padded[:, :h, :w] = x
        # (ny, nx, C, 32, 32), a view of the padded copy
        tiles = padded.view(2, ny, 32, nx, 32).permute(1, 3, 0, 2, 4)
        torch.testing.assert_close(src.extreme(torch.amax), tiles.amax(dim=(2, 3, 4)))
        src.refill(-7.0)
        padded[:, h:] = -7.0
        padded[:, :, w:] = -7.0
        torch.testing.assert_close(src.extreme(torch.amin), tiles.amin(dim=(2, 3, 4)))
        assert torch.equal(x, padded[:, :h, :w])  # the frame itself is only read

    def test_tiled_path_leaves_a_callers_radiance_alone(self, monkeypatch):
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        image, disp = self._scene()
        radiance = torch.rand(1, 1, 150, 218, generator=torch.Generator().manual_seed(2))
        kept = radiance.clone()
        options = dict(radiance=radiance, highlight_boost=False)
        tiled = render(image, disp, 0.55, 260.0, **options)
        assert torch.equal(radiance, kept)
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 10**9)
        assert psnr(tiled, render(image, disp, 0.55, 260.0, **options)) >= 50.0

    @staticmethod
    def _cell_sums(image, weights, coord, centre, mask_of, gate):
        """Brute force: the layer ``[m, m w I, m w]`` at full resolution, summed over 2x2
        cells (zero past the frame) and divided by 4."""
        h, w = coord.shape
        m = rendering.tiled._tile_mask(coord.clone(), centre, mask_of, gate)
        layer = torch.cat([m[None], image[0] * weights[0] * m, weights[0] * m])
        layer = F.pad(layer, (0, w % 2, 0, h % 2))
        return F.avg_pool2d(layer[None], 2)[0]

    @pytest.mark.parametrize("mask_of", [_soft_mask, blend_mask], ids=["soft", "blend"])
    @pytest.mark.parametrize("h,w,band", [(64, 64, 0), (67, 77, 0), (69, 77, 14 * 77)])
    def test_half_source_is_the_masked_frame_in_cells(self, monkeypatch, h, w, band, mask_of):
        """Where a 2x2 cell holds one layer coordinate, masking the cell's mean is masking
        its pixels; the cells across a depth edge are kept pixel by pixel. Either way the
        coarse layers get the cell sums of the full-resolution layer."""
        if band:
            # bands of 14 rows, the last of 13: its buffer is the one of the bands before,
            # and the row past the frame must not keep what an earlier band left there
            _row_band(monkeypatch, band)
        gen = torch.Generator().manual_seed(h + w)
        image = torch.rand(1, 3, h, w, generator=gen)
        weights = 1 + 3 * torch.rand(1, 1, h, w, generator=gen)
        # one coordinate per 2x2 cell (a slanted floor), a near box whose edges cut cells,
        # and a one-pixel stripe far behind
        cells = torch.linspace(-3.0, 4.0, (h + 1) // 2)[:, None].expand(-1, (w + 1) // 2)
        coord = cells.repeat_interleave(2, 0).repeat_interleave(2, 1)[:h, :w].clone()
        coord[13:40, 21:52] = 6.3
        coord[:, 9] = -5.0
        hp, wp = -(-h // 32) * 32, -(-w // 32) * 32
        half = rendering.tiled._HalfSource(image, weights, coord[None], hp, wp, 5)
        assert half.n > 0 and half.x.shape == (5, hp // 2, wp // 2)
        # past the frame: no input, and a coordinate no mask reaches
        assert not half.x[:, -(-h // 2) :].any() and not half.x[:, :, -(-w // 2) :].any()
        assert (half.c[-(-h // 2) :] == rendering.plan.FAR).all()
        hit = torch.ones(hp // 32, wp // 32, dtype=torch.bool)
        for centre, gate in ((-3, -1), (-1, -1), (1, 1), (4, 0), (6, 0), (-5, 0)):
            grid = half.x * rendering.tiled._tile_mask(half.c.clone(), centre, mask_of, gate)
            half.add_mixed(grid, centre, mask_of, gate, hit, (0, 0), 2)
            want = self._cell_sums(image, weights, coord, centre, mask_of, gate)
            gh, gw = want.shape[-2:]
            torch.testing.assert_close(grid[:, :gh, :gw], want, rtol=1e-5, atol=1e-6)
            assert float(want[0].max()) > 0.4  # the layer is there
        # a layer whose tiles are not hit gets none of its mixed cells
        grid = torch.zeros(5, hp // 2, wp // 2)
        half.add_mixed(grid, 6, mask_of, 0, torch.zeros_like(hit), (0, 0), 2)
        assert not grid.any()

    @pytest.mark.parametrize("mask_of", [_soft_mask, blend_mask], ids=["soft", "blend"])
    def test_half_source_cells_summed_into_coarser_grids(self, mask_of):
        # a grid of 8 px from the source's cells of 2 px, mixed cells included
        gen = torch.Generator().manual_seed(4)
        image, weights = torch.rand(1, 3, 64, 96, generator=gen), torch.ones(1, 1, 64, 96)
        coord = torch.zeros(64, 96)
        coord[:, 37:] = 5.0  # an edge through cells of 2 px
        half = rendering.tiled._HalfSource(image, weights, coord[None], 64, 96, 5)
        hit = torch.ones(2, 3, dtype=torch.bool)
        grid = torch.zeros(5, 8, 12)
        m = rendering.tiled._tile_mask(half.c.clone(), 5, mask_of, 0)
        rendering.blur.pool_product(half.x, m, 4, out=grid, mean=False)
        half.add_mixed(grid, 5, mask_of, 0, hit, (0, 0), 8)
        want = self._cell_sums(image, weights, coord, 5, mask_of, 0)
        want = F.avg_pool2d(want[None], 4, divisor_override=1)[0]
        torch.testing.assert_close(grid, want, rtol=1e-5, atol=1e-5)

    def test_tile_bins_are_the_coordinates_the_tiles_hold(self):
        gen = torch.Generator().manual_seed(6)
        coord = (torch.rand(70, 100, generator=gen) * 12 - 6).round(decimals=2)
        coord[:32, :32] = 0.0
        coord[5, 5] = -0.1
        present, lower, upper = rendering.tiles.tile_bins(coord, 32, 3, 4)
        q = rendering.tiles.TILE_BINS
        for ty in range(3):
            for tx in range(4):
                tile = coord[ty * 32 : ty * 32 + 32, tx * 32 : tx * 32 + 32].flatten()
                got = present[ty * 4 + tx] > 0
                # each pixel's bin holds it, on its own side of 0
                for v in tile.tolist():
                    inside = (lower <= v) & (v <= upper)
                    inside &= (upper > 0) if v > 0 else (lower < 0) if v < 0 else (upper == 0)
                    assert bool((inside & got).any())
                assert int(got.sum()) <= tile.numel()
        assert torch.all(upper - lower <= 1.0 / q + 1e-6)
        first = present[0] > 0
        # the first tile: 0 and one pixel in (-0.25, 0]: two bins
        assert int(first.sum()) == 2 and bool(first[(lower == 0) & (upper == 0)].all())

    def test_a_tile_across_a_depth_edge_is_not_in_the_layers_between(self, monkeypatch):
        """A depth edge through tiles: the layers between its sides take none of them (each
        tile is convolved for the layers near the coordinates its pixels have), and the
        picture is what the tiles' coordinate ranges gave."""
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        gen = torch.Generator().manual_seed(12)
        image = torch.rand(1, 3, 160, 224, generator=gen)
        disp = torch.full((1, 1, 160, 224), 0.95)
        disp[..., :, 100:] = 0.15  # a far wall beside a subject at the focus
        areas = {}
        boxes = rendering.blur.direct_stacked

        def count(rows_of, like, chans, box, k, frame):
            key = k.shape[-1]
            areas[key] = areas.get(key, 0) + (box[1] - box[0]) * (box[3] - box[2])
            return boxes(rows_of, like, chans, box, k, frame)

        monkeypatch.setattr(rendering.composite, "direct_stacked", count)
        monkeypatch.setattr(rendering.tiled, "direct_stacked", count)
        exact_hits = render(image, disp, 0.95, 240.0)
        with_bins, areas = areas, {}
        monkeypatch.setattr(rendering.tiled, "_EXACT_HITS", False)
        ranges = render(image, disp, 0.95, 240.0)
        assert psnr(exact_hits, ranges) >= 60.0
        # the sharp layers next to the focal plane: only the subject's side of the edge
        assert sum(with_bins.values()) < 0.6 * sum(areas.values())

    @pytest.mark.parametrize("coc", [-9.0, -2.6, 2.6, 3.0, 9.0])
    def test_flat_tiles_between_layers_keep_their_layers(self, monkeypatch, coc):
        """Tiles whose every pixel sits a fraction of a layer from the focal plane (a CoC
        of a few px, in front or behind; 2.6 px in front sits between 0 and a quarter of a
        layer): the layers either side still take them."""
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        gen = torch.Generator().manual_seed(13)
        image = torch.rand(1, 3, 128, 160, generator=gen)
        disp = torch.full((1, 1, 128, 128 + 32), 0.5)
        disp[..., :64, :96] = 0.5 + coc / 240.0
        disp[..., 96:, 128:] = 0.05
        exact_hits = render(image, disp, 0.5, 240.0)
        monkeypatch.setattr(rendering.tiled, "_EXACT_HITS", False)
        assert psnr(exact_hits, render(image, disp, 0.5, 240.0)) >= 60.0

    def test_cells_across_the_focal_planes_gate_are_split(self, monkeypatch):
        """In front of the focal plane small CoCs sit at coordinate 0, which the layers in
        front do not take, beside pixels at a fraction of a layer that they do: a 2x2 cell
        holding both is masked pixel by pixel, not at its mean (with few layers, layer 1 is
        on a coarse grid)."""
        gen = torch.Generator().manual_seed(0)
        image = torch.rand(1, 3, 128, 192, generator=gen)
        disp = 0.5 + (4.33 + torch.rand(1, 1, 128, 192, generator=gen) * 2.73) / 60
        disp[..., :, 150:] = 0.1
        options = dict(quality="fast", num_layers=4)
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        tiled = render(image, disp, 0.5, 60.0, **options)
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 10**9)
        assert psnr(tiled, render(image, disp, 0.5, 60.0, **options)) >= 50.0

    def test_float64_disparity_with_a_float32_image(self, monkeypatch):
        # the plan (and the cells across depth edges) in float64, the layers in float32
        image, disp = self._scene(97, 131)
        disp = disp.double()
        plain = render(image, disp, 0.5, 60.0)
        monkeypatch.setattr(rendering.api, "_TILED_MIN_PIXELS", 0)
        tiled = render(image, disp, 0.5, 60.0)
        assert tiled.dtype == torch.float32 and psnr(tiled, plain) >= 50.0

    def test_hidden_surface_reads_edge_pixels_alone(self):
        # the tiled path's pixels along the edges, made one by one from the image and the
        # weights, give the surface the renderer's whole-frame layer input gives
        image, disp = _boxed_scene()
        weights = 1 + torch.rand(1, 1, *disp.shape[-2:], generator=torch.Generator().manual_seed(1))
        plan = layer_plan(disp, torch.tensor(0.2), 60.0)
        x = torch.cat([torch.ones_like(disp), image * weights, weights], dim=1)
        whole = hidden_surface(rendering.hidden.input_pixels(x, False), plan)
        reads = []

        def pixels(ys, xs):
            reads.append(ys.numel())
            out = torch.empty(5, ys.numel())
            rendering.tiled._fill_layer(image, weights, ys, xs, torch.ones(()), out)
            return out

        alone = hidden_surface(pixels, plan)
        assert whole is not None and reads and sum(reads) < disp.numel() / 4
        assert torch.equal(whole.x, alone.x) and whole.box == alone.box

    def test_upsample_rows_matches_whole_upsampling(self):
        grid = torch.rand(5, 13, 9, generator=torch.Generator().manual_seed(8))
        whole = rendering.blur.upsample_grid(grid[None], 4, 52, 35)[0]
        for y0, y1 in ((0, 16), (16, 48), (48, 52), (8, 20)):
            part = rendering.tiled._upsample_rows(grid, 4, y0, y1, 35)
            torch.testing.assert_close(part, whole[:, y0:y1])


class TestThreadChoice:
    """Fewer torch threads while other processes keep the cores busy."""

    @pytest.fixture
    def two_threads(self):
        saved = torch.get_num_threads()
        torch.set_num_threads(2)
        yield
        torch.set_num_threads(saved)

    @pytest.mark.parametrize("others,cores,inside", [(0, 2, 2), (1, 2, 1), (5, 2, 1),
                                                     (1, 8, 2), (None, 2, 2)])  # fmt: skip
    def test_threads_inside_and_after(self, monkeypatch, two_threads, others, cores, inside):
        monkeypatch.setattr(rendering.threads, "_running_elsewhere", lambda: others)
        monkeypatch.setattr(rendering.threads, "_usable_cores", lambda: cores)
        with rendering.threads.ThreadChoice():
            assert torch.get_num_threads() == inside
        assert torch.get_num_threads() == 2

    def test_render_restores_threads_and_checks_again(self, monkeypatch, two_threads):
        busy = iter([0, 3, 3, 3] + [3] * 100)
        seen = []
        monkeypatch.setattr(rendering.threads, "_running_elsewhere", lambda: next(busy))
        monkeypatch.setattr(rendering.threads, "_RECHECK_S", 0.0)
        blend = rendering.composite.blend_part
        monkeypatch.setattr(
            rendering.composite,
            "blend_part",
            lambda *a: seen.append(torch.get_num_threads()) or blend(*a),
        )
        image, disp = TestLargeFrames._scene(48, 64)
        render(image, disp, 0.5, 40.0)
        assert seen and seen[-1] == 1  # the machine became busy during the render
        assert torch.get_num_threads() == 2

    def test_running_elsewhere_reads_proc(self):
        got = rendering.threads._running_elsewhere()
        assert got is None or got >= 0
