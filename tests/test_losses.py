"""Training losses: known answers, invariants and float64 gradchecks."""

from __future__ import annotations

import logging

import pytest
import torch

from d2f_core.train.losses import (
    D2FLoss,
    PerceptualLoss,
    VGG19Features,
    binary_focus_mask,
    edge_aware_smoothness,
    gaussian_window,
    l1_loss,
    laplacian,
    poisson_loss,
    ssim,
    ssim_loss,
)

pytestmark = pytest.mark.usefixtures("one_thread")


def _rand(*shape, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=dtype)


class TestL1SSIM:
    def test_l1_known(self):
        assert float(l1_loss(torch.zeros(1, 3, 2, 2), torch.full((1, 3, 2, 2), 0.25))) == 0.25

    def test_identical_is_zero(self):
        x = _rand(2, 3, 20, 20)
        assert float(ssim_loss(x, x)) == pytest.approx(0.0, abs=1e-6)
        assert float(l1_loss(x, x)) == 0.0

    def test_constant_images_known_value(self):
        # no variance: SSIM = (2ab + C1) / (a^2 + b^2 + C1)
        a, b, c1 = 0.2, 0.6, 0.01**2
        x = torch.full((1, 1, 16, 16), a, dtype=torch.float64)
        got = ssim(x, torch.full_like(x, b))
        assert float(got) == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-5)

    def test_matches_skimage_gaussian_ssim(self):
        skm = pytest.importorskip("skimage.metrics")
        x, y = _rand(1, 1, 40, 40, seed=1), _rand(1, 1, 40, 40, seed=2)
        y = 0.5 * x + 0.5 * y
        ref = skm.structural_similarity(
            x[0, 0].numpy(),
            y[0, 0].numpy(),
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
            full=True,
        )[1][5:-5, 5:-5].mean()  # skimage pads; compare on the valid region
        assert float(ssim(x, y)) == pytest.approx(float(ref), abs=1e-4)

    def test_small_images(self):
        x = _rand(1, 3, 4, 6)
        assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)

    def test_window(self):
        w = gaussian_window(11, 1.5)
        assert w.shape == (11, 11) and float(w.sum()) == pytest.approx(1.0)
        assert torch.equal(w, w.T)
        with pytest.raises(ValueError):
            gaussian_window(4)

    def test_shape_errors(self):
        with pytest.raises(ValueError, match="same shape"):
            l1_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
        with pytest.raises(ValueError, match="pred"):
            ssim(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4))

    def test_gradcheck(self):
        x = _rand(1, 2, 7, 7, seed=3, dtype=torch.float64).requires_grad_()
        y = _rand(1, 2, 7, 7, seed=4, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda a: ssim_loss(a, y, window=5), (x,))
        assert torch.autograd.gradcheck(lambda a: l1_loss(a, y), (x,))


class TestSmoothness:
    def test_constant_is_zero(self):
        assert float(edge_aware_smoothness(torch.ones(1, 1, 16, 16), _rand(1, 3, 16, 16))) == 0

    def test_ramp_known_value(self):
        # D = a * x on a flat image: |dx D| = a * 2^s at scale s, so the mean over 4 scales
        # is a * (1 + 2 + 4 + 8) / 4
        a = 0.01
        d = (a * torch.arange(32.0)).expand(1, 1, 32, 32).contiguous()
        got = edge_aware_smoothness(d, torch.full((1, 3, 32, 32), 0.5))
        assert float(got) == pytest.approx(a * 15 / 4, rel=1e-5)

    def test_edges_in_image_reduce_penalty(self):
        d = (torch.arange(16.0) > 7).float().expand(1, 1, 16, 16).contiguous()
        flat = torch.zeros(1, 3, 16, 16)
        edge = d.expand(1, 3, 16, 16).contiguous()
        assert float(edge_aware_smoothness(d, edge)) < float(edge_aware_smoothness(d, flat))

    def test_gradcheck(self):
        d = _rand(1, 1, 8, 8, seed=5, dtype=torch.float64).requires_grad_()
        im = _rand(1, 3, 8, 8, seed=6, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: edge_aware_smoothness(x, im), (d,))

    def test_bad_input(self):
        with pytest.raises(ValueError, match="disparity"):
            edge_aware_smoothness(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))


class TestPoisson:
    def test_laplacian_known(self):
        x = torch.zeros(1, 1, 5, 5)
        x[0, 0, 2, 2] = 1.0
        lap = laplacian(x)[0, 0]
        assert float(lap[2, 2]) == -4.0 and float(lap[1, 2]) == 1.0 and float(lap.sum()) == 0.0
        ramp = torch.arange(6.0).expand(1, 1, 6, 6).contiguous()
        assert torch.all(laplacian(ramp)[..., 1:-1, 1:-1] == 0)

    def test_target_gives_zero(self):
        image, up = _rand(1, 3, 12, 12, seed=1), _rand(1, 3, 12, 12, seed=2)
        mask = (torch.arange(12.0) < 6).float().expand(1, 1, 12, 12).contiguous()
        target = image * mask + up * (1 - mask)
        assert float(poisson_loss(target, image, up, mask)) == 0.0
        # the Laplacian ignores constant offsets
        assert float(poisson_loss(target + 0.1, image, up, mask)) == pytest.approx(0, abs=1e-10)

    def test_known_value(self):
        # B_t = 0 everywhere (image = up = 0); B_hr has a single unit spike
        fused = torch.zeros(1, 1, 5, 5)
        fused[0, 0, 2, 2] = 1.0
        zero = torch.zeros(1, 1, 5, 5)
        # lap(spike) = -4 at the centre and 1 at 4 neighbours: (16 + 4) / 25 / 2
        got = poisson_loss(fused, zero, zero, torch.ones(1, 1, 5, 5))
        assert float(got) == pytest.approx(20 / 25 / 2)

    def test_gradcheck(self):
        f = _rand(1, 3, 6, 6, seed=7, dtype=torch.float64).requires_grad_()
        im = _rand(1, 3, 6, 6, seed=8, dtype=torch.float64)
        up = _rand(1, 3, 6, 6, seed=9, dtype=torch.float64)
        mask = (_rand(1, 1, 6, 6, seed=10, dtype=torch.float64) > 0.5).double()
        assert torch.autograd.gradcheck(lambda x: poisson_loss(x, im, up, mask), (f,))

    def test_binary_mask(self):
        d = torch.tensor([0.0, 0.24, 0.25, 0.9])
        assert binary_focus_mask(d).tolist() == [1.0, 1.0, 0.0, 0.0]


class TestPerceptual:
    def test_off_without_weights(self, caplog):
        with caplog.at_level(logging.WARNING, logger="d2f_core.train.losses"):
            loss = PerceptualLoss(None)
        assert "switched off" in caplog.text
        assert not loss.enabled
        assert float(loss(_rand(1, 3, 8, 8), _rand(1, 3, 8, 8, seed=1))) == 0.0

    def test_local_weights(self, tmp_path):
        torch.manual_seed(0)
        ref = VGG19Features(("relu1_2", "relu2_2"))
        # a torchvision-style file: full features plus a classifier to be ignored
        state = {k: v for k, v in ref.state_dict().items()}
        state["classifier.0.weight"] = torch.zeros(2, 2)
        path = tmp_path / "vgg19.pth"
        torch.save(state, path)
        loss = PerceptualLoss(path, layers=("relu1_2", "relu2_2"))
        assert loss.enabled
        x, y = _rand(1, 3, 16, 16), _rand(1, 3, 16, 16, seed=1)
        assert float(loss(x, x)) == 0.0
        value = loss(x.requires_grad_(), y)
        assert float(value.detach()) > 0
        value.backward()
        assert x.grad is not None
        assert all(not p.requires_grad for p in loss.parameters())

    def test_feature_shapes(self):
        feats = VGG19Features(("relu1_2", "relu3_4"))(torch.rand(1, 3, 32, 32))
        assert [tuple(f.shape) for f in feats] == [(1, 64, 32, 32), (1, 256, 8, 8)]

    def test_bad_files(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="none.pth"):
            PerceptualLoss(tmp_path / "none.pth")
        bad = tmp_path / "bad.pth"
        bad.write_bytes(b"junk")
        with pytest.raises(ValueError, match="cannot read"):
            PerceptualLoss(bad)
        torch.save({"features.0.weight": torch.zeros(3)}, bad)
        with pytest.raises(ValueError, match="not a VGG19"):
            PerceptualLoss(bad, layers=("relu1_2",))


class TestTotals:
    def test_stage1_identical_prediction(self):
        loss = D2FLoss()
        x = _rand(2, 3, 16, 16)
        terms = loss.stage1(x, x, torch.ones(2, 1, 8, 8), x)
        assert float(terms["total"]) == pytest.approx(0.0, abs=1e-6)

    def test_stage1_weights(self):
        loss = D2FLoss()
        p, t, im = _rand(1, 3, 16, 16), _rand(1, 3, 16, 16, seed=1), _rand(1, 3, 16, 16, seed=2)
        d = _rand(1, 1, 16, 16, seed=3)
        terms = loss.stage1(p, t, d, im)
        expected = terms["l1"] + 0.1 * terms["vgg"] + terms["ssim"] + 0.1 * terms["grad"]
        assert float(terms["total"]) == pytest.approx(float(expected))

    def test_stage2_adds_poisson(self):
        loss = D2FLoss()
        f, t, im = _rand(1, 3, 16, 16), _rand(1, 3, 16, 16, seed=1), _rand(1, 3, 16, 16, seed=2)
        up, d = _rand(1, 3, 16, 16, seed=4), _rand(1, 1, 16, 16, seed=3)
        s1 = loss.stage1(f, t, d, im)
        s2 = loss.stage2(f, t, d, im, up, d)
        assert float(s2["total"]) == pytest.approx(float(s1["total"] + 10 * s2["poisson"]))
