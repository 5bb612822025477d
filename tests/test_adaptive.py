"""Adaptive render settings (d2f_core.rendering.adaptive): budget, identity path, fusion."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import d2f_core.rendering as rendering
import d2f_core.rendering.adaptive as adaptive
from d2f_core.metrics import psnr
from d2f_core.rendering.adaptive import BUDGETS, choose_settings, render_adaptive
from d2f_core.train.synth import linear_to_srgb, make_scene, render_pinhole

pytestmark = pytest.mark.usefixtures("two_threads")


def _scene(seed: int, size=(96, 144)):
    """A generated scene (held out from the calibration seeds): sRGB image and disparity."""
    scene = make_scene(size, seed=seed)
    radiance, disp = render_pinhole(scene)
    image = torch.from_numpy(linear_to_srgb(radiance)).permute(2, 0, 1)[None].contiguous()
    orders = [float(lay.order) for lay in scene.layers]
    return image, torch.from_numpy(disp)[None, None].contiguous(), scene.subject, min(orders)


class TestIdentityPath:
    def test_zero_blur_returns_input_without_layer_work(self, monkeypatch):
        image, disp, subject, _ = _scene(301, (40, 56))

        def no_render(*args, **kwargs):
            raise AssertionError("the identity path must not render layers")

        monkeypatch.setattr(adaptive, "render", no_render)
        out, settings = render_adaptive(image, disp, subject, 0.0)
        assert settings.identity and not settings.fusion
        assert settings.layers == []  # no layer was even planned
        assert torch.equal(out, image)

    def test_sub_pixel_coc_is_identity(self, monkeypatch):
        image, disp, subject, _ = _scene(302, (40, 56))
        blur = 0.99 / float((disp - subject).abs().max())
        monkeypatch.setattr(adaptive, "render", None)  # calling it would raise TypeError
        out, settings = render_adaptive(image, disp, subject, blur)
        assert settings.identity and settings.max_coc < 1
        assert torch.equal(out, image)

    def test_renderer_zero_blur_composites_nothing(self, monkeypatch):
        calls = []
        real = rendering.composite.composite_layers
        monkeypatch.setattr(
            rendering.api, "composite_layers", lambda *a, **k: calls.append(1) or real(*a, **k)
        )
        image, disp, subject, _ = _scene(303, (40, 56))
        assert torch.equal(rendering.render(image, disp, subject, 0.0), image)
        assert calls == []
        rendering.render(image, disp, subject, 20.0)
        assert calls == [1]  # the counter does see real layer work


class TestBudget:
    @pytest.mark.parametrize("quality", sorted(BUDGETS))
    def test_stays_within_budget_of_exact_reference(self, quality):
        # held-out seeds (the calibration used 201-208); subject and far focus, two K
        for seed in (311, 312, 313):
            image, disp, subject, far = _scene(seed)
            for focus in (subject, far):
                for blur in (6.0, 20.0):
                    out, settings = render_adaptive(image, disp, focus, blur, quality=quality)
                    ref = rendering.render(image, disp, focus, blur, quality="exact")
                    got = psnr(out, ref)
                    assert got >= BUDGETS[quality], (seed, focus, blur, settings, got)

    def test_tighter_budget_never_predicts_worse(self):
        _, disp, subject, _ = _scene(314)
        fast = choose_settings(disp, subject, 30.0, quality="fast")
        high = choose_settings(disp, subject, 30.0, quality="high")
        assert high.predicted_psnr >= fast.predicted_psnr
        assert fast.cost <= high.cost

    def test_infinite_budget_is_the_reference(self):
        _, disp, subject, _ = _scene(315, (40, 56))
        s = choose_settings(disp, subject, 30.0, budget_db=math.inf)
        assert s.render_options() == {"num_layers": 15, "quality": "exact"}


class TestPlan:
    def test_small_blur_occupies_few_layers(self):
        _, disp, subject, _ = _scene(316)
        small = choose_settings(disp, subject, 4.0)
        large = choose_settings(disp, subject, 60.0)
        assert 0 < len(small.layers) < len(large.layers)
        assert max(size for _, size, _ in small.layers) <= 5
        assert sum(share for *_, share in small.layers) >= 1.0  # every pixel is in a layer

    def test_fusion_needed_only_near_focus(self):
        disp = torch.linspace(0.6, 1.0, 64).expand(1, 1, 48, 64).contiguous()
        # all pixels far behind the focal plane of a half-resolution pass: nothing is sharp
        assert not choose_settings(disp, 0.0, 100.0, full_scale=2.0).fusion
        assert choose_settings(disp, 0.8, 100.0, full_scale=2.0).fusion
        # a full-resolution render needs no fusion at all
        assert not choose_settings(disp, 0.8, 100.0, full_scale=1.0).fusion

    def test_paper_order_keeps_the_models_layers(self):
        image, disp, subject, _ = _scene(317, (40, 56))
        _, settings = render_adaptive(image, disp, subject, 10.0, order="paper", quality="fast")
        assert settings.num_layers == 15

    @pytest.mark.parametrize(
        "kwargs,match",
        [
            ({"focus": 1.5}, "focus"),
            ({"blur": -1.0}, "blur"),
            ({"quality": "ultra"}, "quality"),
            ({"disparity": np.zeros((4, 4))}, "disparity"),
        ],
    )
    def test_bad_inputs_raise(self, kwargs, match):
        args = {"disparity": torch.zeros(1, 1, 8, 8), "focus": 0.5, "blur": 4.0} | kwargs
        with pytest.raises(ValueError, match=match):
            choose_settings(args.pop("disparity"), args.pop("focus"), args.pop("blur"), **args)

    def test_render_adaptive_refuses_fixed_layers(self):
        image, disp, subject, _ = _scene(318, (40, 56))
        with pytest.raises(ValueError, match="num_layers"):
            render_adaptive(image, disp, subject, 10.0, num_layers=15)
