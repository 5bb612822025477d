import math

import numpy as np
import pytest
import torch

from d2f_core.rendering.kernels import (
    PAPER_GROWING_SIZES,
    aperture_kernel,
    coarse_kernel,
    effective_diameter,
    hard_disk_kernel,
    kernel_sizes,
    polygon_kernel,
    soft_disk_kernel,
)


class TestKernels:
    @pytest.mark.parametrize("size", [1, 3, 7, 23, 69])
    @pytest.mark.parametrize(
        "build",
        [soft_disk_kernel, hard_disk_kernel, lambda s, **kw: polygon_kernel(s, 6, 15.0, **kw)],
    )
    def test_sums_to_one_and_shape(self, size, build):
        k = build(size)
        assert k.shape == (size, size)
        assert torch.isclose(k.sum(), torch.tensor(1.0), atol=1e-6)
        assert (k >= 0).all()

    def test_device_and_dtype(self):
        k = soft_disk_kernel(9, device="cpu", dtype=torch.float64)
        assert k.dtype == torch.float64 and k.device.type == "cpu"
        assert hard_disk_kernel(5, dtype=torch.float16).dtype == torch.float16

    def test_soft_disk_known_values(self):
        # r = 3: centre weight 0.5 + 0.5 tanh(0.25 * 9 + 0.5), corner outside the disk
        raw = 0.5 + 0.5 * math.tanh(0.25 * 9 + 0.5)
        corner = 0.5 + 0.5 * math.tanh(0.25 * (9 - 18) + 0.5)
        k = soft_disk_kernel(7, dtype=torch.float64)
        assert k[3, 3] / k[0, 0] == pytest.approx(raw / corner, rel=1e-9)

    def test_hard_disk_is_binary_disk(self):
        k = hard_disk_kernel(7)
        inside = k > 0
        yy, xx = torch.meshgrid(torch.arange(-3, 4), torch.arange(-3, 4), indexing="ij")
        assert torch.equal(inside, (xx**2 + yy**2) <= 9)
        assert torch.allclose(k[inside], torch.full_like(k[inside], 1 / inside.sum()))

    def test_size_one_is_identity(self):
        assert soft_disk_kernel(1).item() == pytest.approx(1.0)

    def test_polygon_has_blade_symmetry(self):
        k = polygon_kernel(31, 6, 0.0, dtype=torch.float64)
        # a hexagon is symmetric under 180 degree rotation; a pentagon is not
        assert torch.allclose(k, k.flip(0, 1), atol=1e-12)
        p = polygon_kernel(31, 5, 0.0, soft=False)
        assert not torch.allclose(p, p.flip(1))
        # a polygon covers less area than its circumscribed disk
        assert (polygon_kernel(31, 6, soft=False) > 0).sum() < (hard_disk_kernel(31) > 0).sum()

    def test_polygon_rotation_by_one_sector_is_identity(self):
        a = polygon_kernel(25, 5, 10.0, dtype=torch.float64)
        b = polygon_kernel(25, 5, 10.0 + 72.0, dtype=torch.float64)
        assert torch.allclose(a, b, atol=1e-9)

    def test_bad_arguments(self):
        with pytest.raises(ValueError, match="odd"):
            soft_disk_kernel(4)
        with pytest.raises(ValueError, match="size must be >= 1, got 0"):
            hard_disk_kernel(0)
        with pytest.raises(ValueError, match="blades"):
            polygon_kernel(9, 2)
        with pytest.raises(ValueError, match="shape"):
            aperture_kernel(9, shape="square")

    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), 2.5, "9", True, -1])
    def test_sizes_and_counts_are_whole_numbers(self, bad):
        """Kernel sizes, coarse factors, schedule counts and layer counts name themselves
        for NaN, infinity, fractions, text and bools (no OverflowError, no silent
        truncation), and take whole floats and NumPy integers."""
        from d2f_core.rendering import api, kernels

        calls = {
            "size": lambda v: soft_disk_kernel(v),
            "factor": lambda v: kernels.coarse_kernel(9, v),
            "count": lambda v: kernels.kernel_sizes(v),
            "num_layers": lambda v: api.render_bokeh(
                np.zeros((4, 4, 3), np.float32), np.zeros((4, 4), np.float32), 0.5, 4.0,
                num_layers=v,
            ),
        }  # fmt: skip
        for name, call in calls.items():
            with pytest.raises(ValueError, match=f"^{name} must be"):
                call(bad)
        assert soft_disk_kernel(9.0).shape == soft_disk_kernel(np.int64(9)).shape == (9, 9)
        assert len(kernels.kernel_sizes(np.int32(4))) == 4

    def test_whole_numbers_beyond_a_float(self):
        """Integers are taken exactly, however large: never rounded through a float, and
        never an unnamed OverflowError."""
        from d2f_core.errors import whole_number

        assert whole_number(2**53 + 1, "n", 1) == 2**53 + 1
        assert whole_number(10**400, "n", 1) == 10**400
        assert whole_number(np.uint64(2**63 + 1), "n", 1) == 2**63 + 1
        with pytest.raises(ValueError, match=r"n must be >= 1, got np.int8\(-5\)"):
            whole_number(np.int8(-5), "n", 1)
        with pytest.raises(ValueError, match="n must be a whole number, got inf"):
            whole_number(float("inf"), "n", 1)


class TestCoarseKernel:
    """Kernels for layers rendered at 1/2 or 1/4 resolution (cell mean, coarse convolution,
    bilinear upsampling), fitted to the full-resolution kernel by least squares."""

    @staticmethod
    def _reduced(x: torch.Tensor, k: torch.Tensor, factor: int) -> torch.Tensor:
        from d2f_core.rendering.blur import pool_grid as _pool
        from d2f_core.rendering.blur import upsample_grid as _upsample

        r = k.shape[-1] // 2
        coarse = torch.nn.functional.conv2d(_pool(x, factor), k.flip(-1, -2)[None, None], padding=r)
        return _upsample(coarse, factor, *x.shape[-2:])

    @pytest.mark.parametrize(
        "size,factor,between_db",
        [(7, 2, 50.0), (11, 2, 53.8), (15, 2, 55.0), (23, 4, 46.0), (39, 4, 54.0)],
    )
    def test_closer_to_full_resolution_than_sampled_aperture(self, size, factor, between_db):
        # piecewise-constant 8-px blocks, like the hard-edged layers a renderer blurs; the
        # full-resolution blur is the reference (measured, PSNR over the interior: sampled
        # 44.3 / 52.4 / 52.4 / 39.8 / 49.4 dB, fitted 56.6 / 55.2 / 58.0 / 52.1 / 58.2 dB)
        g = torch.Generator().manual_seed(1)
        cells = torch.rand(1, 1, 24, 24, generator=g, dtype=torch.float64)
        x = torch.nn.functional.interpolate(cells, scale_factor=8, mode="nearest")
        r = size // 2
        k_full = aperture_kernel(size, dtype=x.dtype)[None, None]
        ref = torch.nn.functional.conv2d(x, k_full, padding=r)
        half = math.ceil(r / factor + 0.5)
        sampled = aperture_kernel(2 * half + 1, radius=r, scale=factor, dtype=x.dtype)
        fitted = coarse_kernel(size, factor, dtype=x.dtype)
        assert fitted.shape == sampled.shape
        assert torch.equal(coarse_kernel(size, factor, fit=False, dtype=x.dtype), sampled)

        def db(k):
            err = (self._reduced(x, k, factor) - ref)[..., 48:-48, 48:-48]
            return float(-10 * torch.log10(err.square().mean()))

        assert db(sampled) < between_db < db(fitted)

    @pytest.mark.parametrize("factor", [2, 4])
    @pytest.mark.parametrize("blades", [0, 6])
    def test_sums_to_one_and_keeps_the_aperture_symmetry(self, factor, blades):
        k = coarse_kernel(23, factor, blades=blades, dtype=torch.float64)
        assert k.sum().item() == pytest.approx(1.0, abs=1e-12)
        assert torch.allclose(k, k.flip(-1), atol=1e-12)  # mirror symmetric like the aperture
        assert -0.2 * k.max() < k.min() < 0  # small negative taps (7-14 % of the peak)

    def test_factor_one_is_the_aperture(self):
        assert torch.equal(
            coarse_kernel(15, 1, blades=5, rotation=10.0),
            aperture_kernel(15, blades=5, rotation=10.0),
        )

    def test_device_dtype_and_bad_factor(self):
        assert coarse_kernel(9, 2, dtype=torch.float16).dtype == torch.float16
        for bad in (0, -2, 1.5, True):
            with pytest.raises(ValueError, match="factor"):
                coarse_kernel(9, bad)


class TestSchedules:
    def test_paper_growing(self):
        assert kernel_sizes() == [1, 3, 5, 7, 11, 15, 19, 23, 27, 33, 39, 45, 53, 61, 69]
        assert tuple(kernel_sizes(15, 69)) == PAPER_GROWING_SIZES

    def test_paper_uniform_steps_of_four(self):
        assert kernel_sizes(15, schedule="uniform") == list(range(1, 58, 4))

    @pytest.mark.parametrize("count", [5, 11, 19, 31])
    @pytest.mark.parametrize("top", [19, 49, 69, 89])
    @pytest.mark.parametrize("schedule", ["growing", "uniform"])
    def test_configurable(self, count, top, schedule):
        sizes = kernel_sizes(count, top, schedule)
        assert len(sizes) == count
        assert sizes[0] == 1 and abs(sizes[-1] - top) <= 1
        assert all(s % 2 == 1 for s in sizes)
        assert all(b >= a for a, b in zip(sizes, sizes[1:]))

    def test_growing_steps_grow(self):
        steps = [b - a for a, b in zip(PAPER_GROWING_SIZES, PAPER_GROWING_SIZES[1:])]
        assert steps == sorted(steps)

    def test_bad_schedule(self):
        with pytest.raises(ValueError, match="schedule"):
            kernel_sizes(15, schedule="log")
        with pytest.raises(ValueError, match="count"):
            kernel_sizes(0)


class TestEffectiveDiameter:
    def test_a_pixel_integrated_disc_draws_its_own_diameter(self):
        # a disc of diameter D, each pixel weighted by the disc's area over it (16x16
        # supersampled): its second moment is that of the disc plus a pixel's, and the
        # diameter read back from it is D (at 3 px it reads 2.82: the pixel's share is
        # exactly 1 / 12 only for a smooth spread)
        for diameter in (6.0, 11.0, 24.0):
            n = 2 * int(diameter / 2 + 2) + 1
            sub = 16
            fine = (torch.arange(n * sub, dtype=torch.float64) + 0.5) / sub - n / 2
            inside = (fine[:, None] ** 2 + fine[None, :] ** 2) <= (diameter / 2) ** 2
            k = inside.double().view(n, sub, n, sub).mean(dim=(1, 3))
            k = k / k.sum()
            x = torch.arange(n, dtype=torch.float64) - n // 2
            var = float((k * x[None, :] ** 2).sum())
            assert 4 * math.sqrt(var - 1 / 12) == pytest.approx(diameter, abs=0.05)

    def test_known_kernels(self):
        assert effective_diameter(1) == 0.0
        # the paper's soft disk reaches past its radius, most for small kernels
        soft = [effective_diameter(s) for s in (3, 5, 7, 11, 69)]
        assert soft == pytest.approx([2.97, 4.98, 6.74, 10.44, 68.02], abs=0.01)
        assert all(a < b for a, b in zip(soft, soft[1:], strict=False))
        # a hard disk of radius r draws nearly 2 r; an inscribed hexagon less than its disk
        assert effective_diameter(69, "hard") == pytest.approx(68.0, abs=0.2)
        assert effective_diameter(33, "soft", 6) < effective_diameter(33, "soft")
        with pytest.raises(ValueError, match="odd"):
            effective_diameter(4)
