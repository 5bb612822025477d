"""The focal range: a band of disparity around the focus that stays sharp, the blur growing
from its edges (``CoC = K max(0, |d - f| - r/2)``), in the renderer, the pipeline and the
subject's range that a click measures; and the f-number and focus position of the app's
language in the library."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from d2f_core.depth.subject import MAX_FOCAL_RANGE, subject_range
from d2f_core.lens import blur_px, focus_of_position, position_of_focus
from d2f_core.pipeline import D2F
from d2f_core.pipeline.focus import FocusStage
from d2f_core.rendering import render
from d2f_core.rendering.schedule import check_focal_range, fold_focal_range, outside_range

pytestmark = pytest.mark.usefixtures("one_thread")


def _scene(h: int = 64, w: int = 96, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    image = torch.rand(1, 3, h, w, generator=g)
    ramp = torch.linspace(0.0, 1.0, w).view(1, 1, 1, w).expand(1, 1, h, w).contiguous()
    return image, ramp


class TestFold:
    def test_coc_grows_from_the_band_edges(self):
        d = torch.tensor([0.0, 0.3, 0.45, 0.5, 0.55, 0.7, 1.0]).view(1, 1, 1, -1)
        folded = fold_focal_range(d, 0.5, 0.2)
        expected = torch.clamp((d - 0.5).abs() - 0.1, min=0)
        assert torch.allclose((folded - 0.5).abs(), expected, atol=1e-6)
        # the depth order is kept
        assert bool((folded.diff(dim=-1) >= 0).all())

    def test_zero_is_identity(self):
        d = torch.rand(1, 1, 4, 5)
        assert fold_focal_range(d, 0.3, 0.0) is d
        assert outside_range(d, 0.0) is d
        assert outside_range(0.4, 0.2) == pytest.approx(0.3)
        assert outside_range(0.05, 0.2) == 0.0

    @pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan"), "wide", None, True])
    def test_bad_range_names_the_argument(self, bad):
        with pytest.raises(ValueError, match="focal_range"):
            check_focal_range(bad)


class TestRender:
    def test_zero_range_is_todays_render(self):
        image, d = _scene()
        a = render(image, d, 0.4, 20.0)
        b = render(image, d, 0.4, 20.0, focal_range=0.0)
        assert torch.equal(a, b)

    def test_range_renders_the_folded_map(self):
        image, d = _scene()
        a = render(image, d, 0.4, 20.0, focal_range=0.3)
        b = render(image, fold_focal_range(d, 0.4, 0.3), 0.4, 20.0)
        assert torch.equal(a, b)

    def test_inside_the_band_is_sharp(self):
        image, d = _scene()
        thin = render(image, d, 0.5, 30.0)
        wide = render(image, d, 0.5, 30.0, focal_range=0.4)
        # columns well inside the band (|d - 0.5| < 0.2, away from the blur spilling in)
        inner = slice(int(0.4 * 96), int(0.6 * 96) + 1)
        err_wide = (wide - image)[..., inner].abs().mean()
        err_thin = (thin - image)[..., inner].abs().mean()
        assert err_wide < 0.25 * err_thin
        # far outside it the blur stays
        assert (wide - image)[..., :5].abs().mean() > 0.02

    def test_bad_range_raises(self):
        image, d = _scene(8, 8)
        with pytest.raises(ValueError, match="focal_range"):
            render(image, d, 0.4, 5.0, focal_range=-1)


class TestSubjectRange:
    @staticmethod
    def _map(seed: int = 0) -> np.ndarray:
        rng = np.random.default_rng(seed)
        h, w = 120, 160
        yy, xx = np.mgrid[0:h, 0:w]
        d = 0.2 + 0.01 * rng.standard_normal((h, w))  # background with noise
        subject = (yy - 60) ** 2 / 40**2 + (xx - 80) ** 2 / 30**2 < 1
        # a subject 0.06 deep (a face turned a little), with a few wild pixels
        d[subject] = (
            0.78
            + 0.06 * ((xx[subject] - 50) / 60)
            + 0.002 * rng.standard_normal(int(subject.sum()))
        )
        return d.astype(np.float32)

    def test_covers_the_subject_not_the_background(self):
        d = self._map()
        focus = float(d[60, 80])
        r = subject_range(d, (80.5 / 160, 60.5 / 120), focus)
        inside = d[60, 55:105]
        # the band covers the subject's own depth (but for its last percentile)...
        assert focus - r / 2 <= np.percentile(inside, 2) + 1e-3
        assert focus + r / 2 >= np.percentile(inside, 98) - 1e-3
        # ...and is nowhere near the background
        assert r < 0.12
        assert abs(focus - 0.2) > r / 2 + 0.4

    def test_capped_and_zero_without_a_region(self):
        ramp = np.tile(np.linspace(0, 1, 200, dtype=np.float32), (50, 1))
        r = subject_range(ramp, (0.5, 0.5), 0.5)
        assert r <= MAX_FOCAL_RANGE
        steps = np.tile((np.arange(100) % 2).astype(np.float32), (20, 1))  # all edges
        assert subject_range(steps, (0.5, 0.5), 0.5) == 0.0


@pytest.fixture(scope="module")
def model() -> D2F:
    torch.manual_seed(0)
    return D2F.from_config({})


def _photo(h: int = 96, w: int = 128) -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.random((h, w, 3)).astype(np.float32)


def _depth(h: int = 96, w: int = 128) -> np.ndarray:
    d = np.full((h, w), 0.15, np.float32)
    d[20:76, 40:88] = np.linspace(0.7, 0.8, 48, dtype=np.float32)  # a subject 0.1 deep
    return d


class TestPipeline:
    def test_click_range_keeps_the_subject_pixels(self, model):
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        focus, r = model.focus_at(scene, 64, 48, with_range=True)
        assert 0.09 <= r <= 0.13
        res = model.render(scene, focus, 40.0, budget=None, focal_range=r)
        inner = (slice(24, 72), slice(44, 84))
        # every pixel inside the range is the photo's own, at full resolution
        assert np.array_equal(res.bokeh[inner], _photo()[inner])
        assert np.all(res.fusion_mask[inner] == 1.0)
        thin = model.render(scene, focus, 40.0, budget=None)
        assert not np.array_equal(thin.bokeh[inner], _photo()[inner])
        # the background is still blurred
        assert np.abs(res.bokeh[:, :20] - _photo()[:, :20]).mean() > 0.05

    def test_subject_focus_takes_the_subjects_range_on_request(self, model):
        """The subject found with no focus given gets, on request, the range a click on it
        gets: the subject's 0.1 of depth, far from the background; without the request the
        call is as before."""
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        focus, (x, y) = model.subject_focus(scene)
        assert 40 <= x < 88 and 20 <= y < 76 and 0.7 <= focus <= 0.8
        again, point, r = model.subject_focus(scene, with_range=True)
        assert (again, point) == (focus, (x, y))
        click = FocusStage._range_at(scene, x, y, focus)
        assert r == click
        assert 0.09 <= r <= 0.2
        assert focus - r / 2 <= 0.7 + 0.01 and focus + r / 2 >= 0.8 - 0.01  # the whole subject
        assert focus - r / 2 > 0.15 + 0.3  # not the background
        flat = model.prepare(_photo(), depth=np.full((96, 128), 0.4, np.float32), refine=False)
        f, (cx, cy), r = model.subject_focus(flat, with_range=True)
        assert (cx, cy) == (63.5, 47.5) and f == pytest.approx(0.4)  # the centre
        assert r == pytest.approx(0.0, abs=1e-3)  # a flat map: no depth to cover

    def test_no_focus_given_renders_at_the_subject(self, model):
        """The library with no focus focuses as the app and the CLI do (``default_focus``): on
        the subject, found once per scene, with the focal range a click on it gets, so the
        whole subject is the photo's own; ``result.focus`` and ``result.focal_range`` say
        where (and repeat a focus given, whose range is 0 unless given)."""
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        focus, (x, y), r = model.subject_focus(scene, with_range=True)
        assert model.default_focus(scene) == (focus, r, (x, y), "subject")
        auto = model.render(scene, blur=30.0)
        assert auto.focus == focus and 0.7 <= focus <= 0.8
        assert auto.focal_range == r and 0.09 <= r <= 0.2
        assert np.array_equal(auto.bokeh, model.render(scene, focus, 30.0, focal_range=r).bokeh)
        inner = (slice(24, 72), slice(44, 84))  # the subject, 0.7-0.8 of depth
        assert np.array_equal(auto.bokeh[inner], _photo()[inner])
        thin = model.render(scene, focus, 30.0)
        assert thin.focal_range == 0.0 and not np.array_equal(thin.bokeh[inner], _photo()[inner])
        # a range given with no focus is kept
        assert model.render(scene, blur=30.0, focal_range=0.0).focal_range == 0.0
        middle = model.render(scene, 0.5, 30.0)
        assert middle.focus == 0.5 and not np.array_equal(middle.bokeh, auto.bokeh)
        assert scene.cache["subject"] == (focus, model.subject_focus(scene)[1])  # found once
        with pytest.raises(ValueError, match="focus"):
            model.render(scene, float("nan"), 30.0)

    def test_no_focus_given_renders_at_the_phones_focal_plane(self, model):
        """A map that came with a focal plane (a phone's) is rendered there by default, as
        the CLI does; a focus that is not a finite number counts as none recorded."""
        from d2f_core.depth.sources import DepthMap

        recorded = DepthMap(_depth(), "embedded", "phone depth", focus=0.2)
        scene = model.prepare(_photo(), depth=recorded, refine=False)
        assert scene.focus == 0.2
        result = model.render(scene, blur=30.0)
        assert result.focus == 0.2 and result.focal_range == 0.0  # a phone's focal plane
        assert model.default_focus(scene) == (0.2, 0.0, None, "photo")
        assert np.array_equal(result.bokeh, model.render(scene, 0.2, 30.0).bokeh)
        for bad in (float("nan"), None):
            odd = DepthMap(_depth(), "embedded", "phone depth", focus=bad)
            scene = model.prepare(_photo(), depth=odd, refine=False)
            assert scene.focus is None
            assert model.render(scene, blur=30.0).focus == model.subject_focus(scene)[0]

    def test_zero_range_is_todays_render(self, model):
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        a = model.render(scene, 0.75, 30.0)
        b = model.render(scene, 0.75, 30.0, focal_range=0.0)
        assert np.array_equal(a.bokeh, b.bokeh)

    def test_focus_at_default_is_a_number(self, model):
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        assert isinstance(model.focus_at(scene, 64, 48), float)

    def test_f_number_is_the_apps_lens(self, model):
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        a = model.render(scene, 0.75, f_number=1.8)
        b = model.render(scene, 0.75, blur_px(1.8, 128))
        assert np.array_equal(a.bokeh, b.bokeh)

    @pytest.mark.parametrize(
        "kwargs, name",
        [
            ({"blur": 10.0, "f_number": 2.0}, "f_number"),
            ({"f_number": 0.1}, "f_number"),
            ({"f_number": "wide"}, "f_number"),
            ({"focal_range": 2.0}, "focal_range"),
        ],
    )
    def test_bad_arguments_name_themselves(self, model, kwargs, name):
        scene = model.prepare(_photo(), depth=_depth(), refine=False)
        with pytest.raises(ValueError, match=name):
            model.render(scene, 0.5, **kwargs)


def test_focus_position_is_the_apps_slider():
    assert focus_of_position(0.0) == 1.0 and focus_of_position(1.0) == 0.0
    assert focus_of_position(0.25) == 0.75
    assert position_of_focus(focus_of_position(0.313)) == 0.313
    with pytest.raises(ValueError, match="focus position"):
        focus_of_position(1.5)
