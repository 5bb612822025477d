"""Synthetic scenes and their accumulation-buffer ground truth (d2f_core.train.synth)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from scipy.signal import fftconvolve

from d2f_core.train.synth import (
    Layer,
    Scene,
    aperture_samples,
    builtin_textures,
    generate_dataset,
    linear_to_srgb,
    main,
    make_pair,
    make_scene,
    render_pinhole,
    render_thin_lens,
    srgb_to_linear,
)

H = W = 64
MARGIN = 14


pytestmark = pytest.mark.usefixtures("two_threads")


def _opaque(img: np.ndarray, disparity: float, top: int = -MARGIN, left: int = -MARGIN) -> Layer:
    return Layer(img.astype(np.float32), np.ones(img.shape[1:], np.float32), top, left, disparity)


def _photo(h: int, w: int, y: int = 100, x: int = 150) -> np.ndarray:
    """Linear radiance crop of the astronaut photo, (3, h, w)."""
    return srgb_to_linear(builtin_textures()[0][y : y + h, x : x + w]).transpose(2, 0, 1).copy()


def _square(colour, size: int, top: int, left: int, disparity: float) -> Layer:
    rgb = np.broadcast_to(np.asarray(colour, np.float32)[:, None, None], (3, size, size))
    return Layer(rgb.copy(), np.ones((size, size), np.float32), top, left, disparity)


def _disk_kernel(radius: float, supersample: int = 8) -> np.ndarray:
    """Pixel-area coverage of a disk of the given radius, summing to 1."""
    r = int(np.ceil(radius)) + 1
    n = 2 * r + 1
    sub = (np.arange(n * supersample) + 0.5) / supersample - r - 0.5
    yy, xx = np.meshgrid(sub, sub, indexing="ij")
    inside = (yy**2 + xx**2 <= radius**2).astype(np.float64)
    k = inside.reshape(n, supersample, n, supersample).mean((1, 3))
    return k / k.sum()


class TestHelpers:
    def test_aperture_samples_cover_the_unit_disk(self):
        for pattern in ("fibonacci", "concentric"):
            pts = aperture_samples(256, pattern=pattern)
            r = np.hypot(pts[:, 0], pts[:, 1])
            assert r.max() <= 1.0 + 1e-9
            np.testing.assert_allclose(pts.mean(0), 0.0, atol=0.01)
            # Uniform over the disk: E[r^2] = 1/2.
            assert abs((r**2).mean() - 0.5) < 0.01

    def test_aperture_samples_bad_input(self):
        with pytest.raises(ValueError, match="n must be >= 1, got 0"):
            aperture_samples(0)
        for bad in (float("nan"), float("inf"), 8.5, "8"):
            with pytest.raises(ValueError, match="n must be a whole number"):
                aperture_samples(bad)
        assert aperture_samples(8.0).shape == aperture_samples(np.int64(8)).shape == (8, 2)
        with pytest.raises(ValueError, match="pattern"):
            aperture_samples(8, pattern="grid")

    def test_srgb_round_trip(self):
        x = np.linspace(0, 1, 101, dtype=np.float32)
        np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-5)
        assert srgb_to_linear(np.float32(0.5)) == pytest.approx(0.2140, abs=1e-4)


class TestThinLens:
    def test_zero_blur_is_the_pinhole_view(self):
        scene = make_scene((H, W), seed=1, margin=MARGIN)
        pinhole, _ = render_pinhole(scene)
        np.testing.assert_array_equal(render_thin_lens(scene, 0.3, 0.0), pinhole)

    def test_layers_on_the_focal_plane_stay_sharp(self):
        # Exercises the warping path: zero shift for every aperture point.
        bg = _opaque(_photo(H + 2 * MARGIN, W + 2 * MARGIN), 0.5)
        light = _square((12.0, 9.0, 4.0), 3, 30, 30, 0.5)
        scene = Scene([bg, _square((0.9, 0.1, 0.1), 20, 10, 12, 0.5), light], (H, W), MARGIN, 0.5)
        out = render_thin_lens(scene, 0.5, 24.0, samples=64)
        np.testing.assert_allclose(out, render_pinhole(scene)[0], atol=2e-3, rtol=1e-4)

    @pytest.mark.parametrize("blur", [8.0, 16.0])
    def test_single_layer_equals_fft_disk_blur(self, blur):
        img = _photo(H + 2 * MARGIN, W + 2 * MARGIN)
        scene = Scene([_opaque(img, 0.0)], (H, W), MARGIN, 0.0)
        ref = np.stack(
            [fftconvolve(c.astype(np.float64), _disk_kernel(blur / 2), "same") for c in img]
        )
        ref = ref[:, MARGIN:-MARGIN, MARGIN:-MARGIN].transpose(1, 2, 0)
        err64 = np.abs(render_thin_lens(scene, 1.0, blur, samples=64) - ref)
        err256 = np.abs(render_thin_lens(scene, 1.0, blur, samples=256) - ref)
        # Measured (64 samples, K = 16): max 0.012, mean 0.0016; 256 samples: 0.0022 / 0.0004.
        # The residual is aperture sampling noise; it shrinks with more samples.
        assert err64.mean() < 0.003 and err64.max() < 0.025
        assert err256.mean() < 0.6 * err64.mean()
        # The blur itself is much larger than the tolerance.
        assert np.abs(ref - img[:, MARGIN:-MARGIN, MARGIN:-MARGIN].transpose(1, 2, 0)).mean() > 0.01

    def test_near_object_spills_over_the_focused_background(self):
        bg = _opaque(_photo(H + 2 * MARGIN, W + 2 * MARGIN), 0.3)
        obj = _square((0.9, 0.02, 0.02), 16, 24, 24, 1.0)  # rows/cols 24..39
        scene = Scene([bg, obj], (H, W), MARGIN, 0.3)
        pinhole, disp = render_pinhole(scene)
        out = render_thin_lens(scene, 0.3, 20.0, samples=128)  # CoC 14 px, radius 7
        ring = (slice(18, 22), slice(26, 38))  # 2-5 px above the silhouette
        # Share of the object's colour mixed into each ring pixel (0 in the pinhole view).
        towards = np.asarray([0.9, 0.02, 0.02]) - pinhole[ring]
        share = ((out[ring] - pinhole[ring]) * towards).sum(-1) / (towards**2).sum(-1)
        assert share.mean() > 0.1 and share.min() > 0.02
        # Far from the object the in-focus background is untouched.
        np.testing.assert_allclose(out[:8], pinhole[:8], atol=2e-3)
        assert disp[30, 30] == pytest.approx(1.0) and disp[5, 5] == pytest.approx(0.3)

    def test_far_object_does_not_spill_over_a_sharp_foreground(self):
        bg = _opaque(np.full((3, H + 2 * MARGIN, W + 2 * MARGIN), 0.05, np.float32), 0.0)
        far = _square((0.95, 0.0, 0.0), 30, 2, 2, 0.1)
        near = _opaque(_photo(24, 24), 0.8, top=20, left=20)  # rows/cols 20..43
        scene = Scene([bg, far, near], (H, W), MARGIN, 0.8)
        pinhole, _ = render_pinhole(scene)
        out = render_thin_lens(scene, 0.8, 30.0, samples=128)
        inner = (slice(21, 43), slice(21, 43))
        np.testing.assert_allclose(out[inner], pinhole[inner], atol=2e-3)
        # ...while the red object itself is blurred beyond its silhouette.
        assert out[33:40, 5, 0].mean() > 0.1 + pinhole[33:40, 5, 0].mean()

    def test_hdr_light_gives_a_bright_disc(self):
        def scene_with(radiance: float) -> Scene:
            bg = _opaque(np.full((3, H + 2 * MARGIN, W + 2 * MARGIN), 0.01, np.float32), 0.0)
            yy, xx = np.mgrid[0:9, 0:9]
            cov = np.clip(0.5 - (np.hypot(yy - 4, xx - 4) - 1.5), 0, 1).astype(np.float32)
            light = Layer(radiance * cov[None].repeat(3, 0), cov, 28, 28, 0.1)
            return Scene([bg, light], (H, W), MARGIN, 0.1)

        blur = 25.0  # CoC diameter 25 * 0.9 = 22.5 px
        out = render_thin_lens(scene_with(20.0), 1.0, blur, samples=256)[..., 0]
        clipped = render_thin_lens(scene_with(1.0), 1.0, blur, samples=256)[..., 0]
        r = np.hypot(*np.mgrid[0:H, 0:W] - 32.0)
        radius = blur * 0.9 / 2
        # The light itself reaches 2 px from its centre, bilinear sampling 1 px more.
        inner, outer = out[r < 0.6 * radius], out[r > radius + 3.5]
        assert inner.mean() > 5 * clipped[r < 0.6 * radius].mean()
        assert inner.mean() > 0.25  # a visible disc, not a faint smear
        assert inner.std() < 0.15 * inner.mean()  # flat top: a disc, not a Gaussian
        np.testing.assert_allclose(outer, 0.01, atol=2e-3)
        assert render_pinhole(scene_with(20.0))[0].max() == pytest.approx(20.0)

    def test_sloped_plane_is_sharp_only_at_the_focal_row(self):
        img = np.random.default_rng(0).random((3, H + 2 * MARGIN, W + 2 * MARGIN), np.float32)
        slope = 0.6 / H
        plane = Layer(img, np.ones(img.shape[1:], np.float32), -MARGIN, -MARGIN, 0.5, (slope, 0.0))
        scene = Scene([plane], (H, W), MARGIN, 0.5)
        pinhole, disp = render_pinhole(scene)
        rows = np.arange(H)
        np.testing.assert_allclose(disp[:, 0], 0.5 + slope * (rows - (H - 1) / 2), atol=1e-6)
        row = 20
        out = render_thin_lens(scene, float(disp[row, 0]), 10.0, samples=64)
        diff = np.abs(out - pinhole).mean(axis=(1, 2))
        assert diff[row] < 1e-4
        # CoC grows linearly away from the focal row: about 0.2, 0.75 and 1.9 px here.
        assert diff[row + 20] > diff[row + 8] > diff[row + 2] > 100 * diff[row]
        assert diff[row - 8] > diff[row - 2] > 100 * diff[row]

    def test_bad_input(self):
        scene = make_scene((32, 32), seed=0, margin=4)
        with pytest.raises(ValueError, match="focus"):
            render_thin_lens(scene, 1.5, 4.0)
        with pytest.raises(ValueError, match="blur"):
            render_thin_lens(scene, 0.5, -1.0)
        with pytest.raises(TypeError, match="scene"):
            render_thin_lens("scene", 0.5, 4.0)
        with pytest.raises(ValueError, match="size"):
            make_scene((8, 8), seed=0)


class TestScenes:
    @pytest.mark.parametrize(("seed", "size"), [(18, (128, 192)), (31, (256, 384))])
    def test_no_margin(self, seed, size):
        # these seeds place a blob centre beyond the view; with margin 0 its box was empty
        scene = make_scene(size, seed=seed, margin=0)
        radiance, disp = render_pinhole(scene)
        assert radiance.shape == (*size, 3) and disp.shape == size
        assert np.isfinite(radiance).all() and 0.0 <= disp.min() <= disp.max() <= 1.0

    def test_same_seed_same_scene(self):
        a, b = make_scene((H, W), seed=5), make_scene((H, W), seed=5)
        assert [lay.describe() for lay in a.layers] == [lay.describe() for lay in b.layers]
        for la, lb in zip(a.layers, b.layers, strict=True):
            np.testing.assert_array_equal(la.rgb, lb.rgb)
            np.testing.assert_array_equal(la.alpha, lb.alpha)
        c = make_scene((H, W), seed=6)
        assert not np.array_equal(render_pinhole(a)[0], render_pinhole(c)[0])

    def test_scene_contents(self):
        kinds, widths, radiances = set(), [], []
        for seed in range(12):
            scene = make_scene((96, 128), seed=seed)
            orders = [lay.order for lay in scene.layers]
            assert scene.layers[0].kind == "background" and orders[1:] == sorted(orders[1:])
            assert all(0.0 <= o <= 1.0 for o in orders)
            for lay in scene.layers:
                kinds.add(lay.kind)
                assert lay.rgb.shape == (3, *lay.alpha.shape) and lay.rgb.dtype == np.float32
                assert lay.alpha.min() >= 0 and lay.alpha.max() <= 1
                if lay.kind in ("bar", "branch"):
                    widths.append(lay.info["width_px"])
                if lay.kind == "light":
                    radiances.append(lay.info["radiance"])
                if lay.kind == "ground":
                    assert lay.slope[0] > 0
        assert {"background", "blob", "stripes", "ground", "light", "branch", "bar"} <= kinds
        assert 1.0 <= min(widths) and max(widths) <= 3.0
        assert 3.0 <= min(radiances) and max(radiances) <= 30.0


class TestDataset:
    def test_make_pair(self):
        pair = make_pair((40, 56), seed=3, samples=16)
        again = make_pair((40, 56), seed=3, samples=16)
        for arr, ref in ((pair.image, again.image), (pair.bokeh, again.bokeh)):
            assert arr.shape == (40, 56, 3) and arr.dtype == np.float32
            assert arr.min() >= 0 and arr.max() <= 1
            np.testing.assert_array_equal(arr, ref)
        assert pair.disparity.shape == (40, 56) and 0 <= pair.disparity.min() <= 1
        assert {"focus", "blur", "samples", "seed", "size", "layers"} <= set(pair.params)
        assert not np.array_equal(pair.image, pair.bokeh)

    def test_focus_mix(self):
        modes = []
        for seed in range(20):
            p = make_pair((24, 32), seed=seed, samples=1, subject_share=0.7).params
            modes.append(p["mode"])
            if p["mode"] == "subject":
                assert p["blur"] == pytest.approx(0.06 * 32, abs=1e-3)
                subject = [lay for lay in p["layers"] if lay.get("subject")]
                assert p["focus"] == pytest.approx(subject[0]["disparity"], abs=1e-4)
            else:
                assert 0.02 * 32 <= p["blur"] <= 0.12 * 32
        assert 0 < modes.count("random") < modes.count("subject")

    def test_generate_dataset_layout_and_round_trip(self, tmp_path):
        ids = generate_dataset(tmp_path, 2, seed=9, size=(32, 48), samples=8, start_id=7)
        assert ids == ["00007", "00008"]
        for sub, ext in (
            ("original", "png"),
            ("bokeh", "png"),
            ("disparity", "png"),
            ("params", "json"),
        ):
            assert sorted(p.name for p in (tmp_path / sub).iterdir()) == [f"{i}.{ext}" for i in ids]
        params = json.loads((tmp_path / "params" / "00008.json").read_text())
        assert params["size"] == [32, 48] and params["samples"] == 8
        pair = make_pair((32, 48), seed=params["seed"], samples=8)
        assert pair.params["focus"] == params["focus"] and pair.params["blur"] == params["blur"]
        with Image.open(tmp_path / "disparity" / "00008.png") as im:
            assert im.mode.startswith("I;16") or im.mode == "I"
            disp = np.asarray(im).astype(np.int64)
        np.testing.assert_array_equal(disp, np.round(pair.disparity * 65535).astype(np.int64))
        with Image.open(tmp_path / "bokeh" / "00008.png") as im:
            saved = np.asarray(im.convert("RGB")).astype(np.int64)
        assert np.abs(saved - np.round(pair.bokeh * 255)).max() <= 1

    def test_generate_dataset_jpg_and_bad_input(self, tmp_path):
        generate_dataset(tmp_path, 1, seed=0, size=(24, 24), samples=4, fmt="jpg")
        assert (tmp_path / "original" / "00000.jpg").is_file()
        assert (tmp_path / "disparity" / "00000.png").is_file()
        with pytest.raises(ValueError, match="fmt"):
            generate_dataset(tmp_path, 1, seed=0, fmt="bmp")

    def test_cli(self, tmp_path):
        out = tmp_path / "set"
        argv = [str(out), "--count", "2", "--seed", "1", "--size", "24x32", "--samples", "4"]
        assert main(argv + ["--start-id", "3", "--format", "jpg"]) == 0
        assert sorted(p.name for p in (out / "bokeh").iterdir()) == ["00003.jpg", "00004.jpg"]
        assert main(argv + ["--subject-share", "2"]) == 2
        with pytest.raises(SystemExit) as exc:
            main([str(out), "--size", "big"])
        assert exc.value.code == 2
