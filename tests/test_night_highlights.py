"""Highlights at night: clipped far lights behind a near subject become discs as bright as a
real lens makes them. Generated night scenes carry the lights' true radiance (3-30 times the
clip level), so the thin lens's ground truth knows how bright each disc is; the photo given to
d2f is clipped, as a camera clips it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from d2f_core.pipeline import D2F
from d2f_core.train.synth.dataset import _encode
from d2f_core.train.synth.lens import Scene, render_pinhole, render_thin_lens
from d2f_core.train.synth.standing import make_standing_scene, subject_mask

pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.slow]

K = 40.0
SEEDS = range(9000, 9008)


def _luma(a: np.ndarray) -> np.ndarray:
    return a @ np.array([0.2126, 0.7152, 0.0722], np.float32)


@pytest.fixture(scope="module")
def discs():
    """Per night scene: the d2f scene (true depth), the focus, the ground truth (sRGB) and
    the discs of the far lights (where they alone reach 0.2 in the thin lens, the subject and
    4 px around it left out)."""
    model = D2F.from_pretrained()
    out = []
    for seed in SEEDS:
        scene = make_standing_scene((256, 384), seed=seed, kind="night")
        pinhole, disparity = render_pinhole(scene)
        focus = scene.subject
        truth = _encode(render_thin_lens(scene, focus, K, samples=96), "srgb")
        lights = [lay for lay in scene.layers if lay.kind == "light"]
        alone = render_thin_lens(
            Scene(lights, scene.size, scene.margin, focus, seed), focus, K, samples=96
        )
        subject = ndimage.binary_dilation(subject_mask(scene) > 0.01, iterations=4)
        mask = (alone.max(axis=2) > 0.2) & ~subject
        prepared = model.prepare(_encode(pinhole, "srgb"), depth=disparity, refine=False)
        out.append((prepared, focus, truth, mask))
    return model, out


def _brightness(model, cases, **options) -> float:
    """The discs' mean brightness over the ground truth's, pooled over the scenes."""
    ours = truth = 0.0
    for prepared, focus, gt, mask in cases:
        bokeh = model.render(prepared, focus, K, **options).bokeh
        ours += float(_luma(bokeh)[mask].sum())
        truth += float(_luma(gt)[mask].sum())
    return ours / truth


def test_far_lights_are_as_bright_as_a_real_lens_makes_them(discs):
    """Measured on these 8 scenes: 0.98 of the ground truth's brightness by default, 0.44 with
    no boost, 1.17 at Boost 2. (The paper's boost alone, before a lone saturated spot weighed
    more with a radiance map too: 0.65 on seeds 9000-9011.)"""
    model, cases = discs
    assert all(mask.sum() > 100 for *_, mask in cases)
    default = _brightness(model, cases)
    assert 0.9 <= default <= 1.1, default
    none = _brightness(model, cases, highlight_boost=False)
    assert none < 0.8 * default
    assert _brightness(model, cases, highlight_boost=2.0) > 1.15 * default


def test_boost_changes_nothing_without_clipped_pixels(discs):
    model, cases = discs
    prepared, focus, *_ = cases[0]
    dim = model.prepare(
        np.clip(prepared.image[0].permute(1, 2, 0).numpy(), 0, 0.9),
        depth=prepared.disparity_lr[0, 0].numpy(),
        refine=False,
    )
    a = model.render(dim, focus, K, highlight_boost=1.0).bokeh
    b = model.render(dim, focus, K, highlight_boost=2.5).bokeh
    np.testing.assert_array_equal(a, b)
    torch.testing.assert_close(torch.from_numpy(a), torch.from_numpy(b))
