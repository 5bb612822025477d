"""d2f-eval: fusion baselines (known answers) and the CLI's CSV output."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest
import torch
from test_data import write_pairs

from d2f_core import metrics
from d2f_core.evaluate import (
    FUSION_METHODS,
    alpha_blend,
    click_focus,
    disparity_errors,
    gaussian_background_baseline,
    gaussian_baseline,
    laplacian_pyramid_blend,
    main,
    poisson_blend,
)
from d2f_core.pipeline import D2F
from d2f_core.train.data import EBBDataset

pytestmark = pytest.mark.usefixtures("one_thread")


def _pair(seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    return (
        rng.random((h, w, 3), dtype=np.float32),
        rng.random((h, w, 3), dtype=np.float32),
    )


def _box_mask(h=24, w=32):
    mask = np.zeros((h, w), np.float32)
    mask[6:18, 8:20] = 1
    return mask


class TestBlends:
    def test_alpha(self):
        image, bokeh = _pair()
        mask = _box_mask()
        out = alpha_blend(image, bokeh, mask)
        np.testing.assert_allclose(out[mask > 0], image[mask > 0])
        np.testing.assert_allclose(out[mask == 0], bokeh[mask == 0])

    def test_poisson_offset_image_gives_bokeh(self):
        pytest.importorskip("scipy")
        # the image's gradients equal the bokeh's, and the boundary is the bokeh: f = bokeh
        _, bokeh = _pair()
        image = bokeh * 0.5 + 0.3
        bokeh = bokeh * 0.5
        out = poisson_blend(image, bokeh, _box_mask())
        np.testing.assert_allclose(out, bokeh, atol=1e-5)

    def test_poisson_smooth_image_keeps_detail(self):
        pytest.importorskip("scipy")
        image, _ = _pair()
        image = 0.45 + 0.1 * image  # small detail: the solution stays inside [0, 1] unclipped
        bokeh = np.full_like(image, 0.5)
        mask = _box_mask()
        out = poisson_blend(image, bokeh, mask)
        # inside: the image up to a smooth correction, so the Laplacian is the image's
        lap = lambda x: x[1:-1, 1:-1] * 4 - x[:-2, 1:-1] - x[2:, 1:-1] - x[1:-1, :-2] - x[1:-1, 2:]  # noqa: E731
        inner = np.zeros_like(mask, dtype=bool)
        inner[7:17, 9:19] = True
        np.testing.assert_allclose(
            lap(out)[inner[1:-1, 1:-1]], lap(image)[inner[1:-1, 1:-1]], atol=1e-4
        )
        np.testing.assert_array_equal(out[mask == 0], bokeh[mask == 0])

    def test_poisson_trivial_masks(self):
        pytest.importorskip("scipy")
        image, bokeh = _pair()
        np.testing.assert_array_equal(poisson_blend(image, bokeh, np.zeros((24, 32))), bokeh)
        np.testing.assert_array_equal(poisson_blend(image, bokeh, np.ones((24, 32))), image)

    def test_laplacian_pyramid(self):
        image, bokeh = _pair(h=40, w=48)
        ones, zeros = np.ones((40, 48), np.float32), np.zeros((40, 48), np.float32)
        np.testing.assert_allclose(laplacian_pyramid_blend(image, bokeh, ones), image, atol=1e-5)
        np.testing.assert_allclose(laplacian_pyramid_blend(image, bokeh, zeros), bokeh, atol=1e-5)
        half = np.zeros((40, 48), np.float32)
        half[:, :24] = 1
        out = laplacian_pyramid_blend(image, bokeh, half, levels=3)
        # far from the seam each side is its source
        np.testing.assert_allclose(out[:, :8], image[:, :8], atol=0.05)
        np.testing.assert_allclose(out[:, -8:], bokeh[:, -8:], atol=0.05)

    def test_gaussian_baseline(self):
        flat = np.full((10, 12, 3), 0.4, np.float32)
        np.testing.assert_allclose(gaussian_baseline(flat, 2.0), flat, atol=1e-6)
        image, _ = _pair()
        assert (
            np.abs(np.diff(gaussian_baseline(image, 2.0), axis=1)).mean()
            < np.abs(np.diff(image, axis=1)).mean()
        )

    def test_shape_errors(self):
        image, bokeh = _pair()
        with pytest.raises(ValueError, match="mask"):
            alpha_blend(image, bokeh, np.zeros((3, 3)))
        with pytest.raises(ValueError, match="image"):
            laplacian_pyramid_blend(image[..., :2], bokeh, np.zeros((24, 32)))


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    data = write_pairs(root / "data", 3, (48, 64), blur=60.0)
    torch.manual_seed(0)
    weights = root / "w.pt"
    D2F.from_config({"network_size": 64}).save(weights)
    return data, weights, root


def _rows(path):
    with path.open() as fh:
        return list(csv.DictReader(fh))


class TestDisparityErrors:
    def test_affine_copy_is_perfect(self):
        rng = np.random.default_rng(1)
        gt = rng.random((20, 30))
        rho, rmse = disparity_errors(0.3 * gt + 0.2, gt)
        assert rho == pytest.approx(1.0) and rmse == pytest.approx(0.0, abs=1e-12)

    def test_reversed_order_and_noise(self):
        gt = np.linspace(0, 1, 200).reshape(10, 20)
        rho, rmse = disparity_errors(1 - gt, gt)
        assert rho == pytest.approx(-1.0)
        assert rmse == pytest.approx(0.0, abs=1e-12)  # an affine map with a negative scale
        rho, rmse = disparity_errors(np.random.default_rng(2).random((10, 20)), gt)
        assert abs(rho) < 0.3 and rmse > 0.2  # unrelated maps


def test_gaussian_background_baseline_keeps_focus_sharp():
    rng = np.random.default_rng(3)
    image = rng.random((32, 40, 3)).astype(np.float32)
    disp = np.zeros((32, 40), np.float32)
    disp[:, :20] = 1.0  # left half in focus
    out = gaussian_background_baseline(image, disp, 1.0, 40.0)
    np.testing.assert_array_equal(out[:, :20], image[:, :20])
    assert out[:, 25:].std() < 0.5 * image[:, 25:].std()


def test_click_focus():
    true = np.zeros((4, 4))
    true[:2] = 0.8  # the sharp subject at 0.8
    predicted = np.where(true > 0, 0.6, 0.1)
    predicted[0, 0] = 0.9
    assert click_focus(predicted, true, 0.8) == 0.6  # median over the subject's pixels
    assert click_focus(predicted, true, 0.4) == 0.4  # nothing in focus: the given focus


class TestCLI:
    def test_focus_by_click(self, setup, tmp_path, capsys):
        """With the true disparity, clicking the in-focus pixels picks the given focus
        back (the pairs' focus lies on a plane), so both protocols agree exactly."""
        data, weights, _ = setup
        argv = [str(data), "--weights", str(weights), "--split", "all", "--use-gt-disparity"]
        assert main([*argv, "--out", str(tmp_path / "a")]) == 0
        assert main([*argv, "--out", str(tmp_path / "b"), "--focus-by", "click"]) == 0
        a, b = _rows(tmp_path / "a" / "eval_all.csv"), _rows(tmp_path / "b" / "eval_all.csv")
        assert [r["psnr"] for r in a] == [r["psnr"] for r in b]

    def test_focus_by_subject_ignores_the_pairs_focus(self, setup, tmp_path):
        """The subject focus is the model's own: with the true disparity (the near half as
        the subject) it renders every pair as at its focus on the near half, whatever focus
        the pair records; the range a flat subject gets is nil."""
        data, weights, _ = setup
        far = tmp_path / "far"
        shutil.copytree(data, far)
        for path in (far / "params").glob("*.json"):
            path.write_text(json.dumps({"focus": 0.0, "blur": 60.0}))
        common = ["--weights", str(weights), "--split", "all", "--use-gt-disparity"]
        runs = {
            "near": [str(data), *common],
            "far": [str(far), *common],
            "subject": [str(far), *common, "--focus-by", "subject"],
            "range": [str(far), *common, "--focus-by", "subject-range"],
        }
        psnr = {}
        for name, argv in runs.items():
            assert main([*argv, "--out", str(tmp_path / name)]) == 0
            psnr[name] = [r["psnr"] for r in _rows(tmp_path / name / "eval_all.csv")]
        assert psnr["subject"] == psnr["near"] == psnr["range"]
        assert psnr["far"] != psnr["near"]
        # a baseline or the fusion comparison takes no focus of the model's: refused
        for extra in (["--baseline", "gaussian"], ["--fusion"]):
            argv = [str(far), *common, *extra, "--focus-by", "subject"]
            assert main([*argv, "--out", str(tmp_path / "refused")]) == 2
        assert not (tmp_path / "refused").exists()

    def test_eval_csv(self, setup, tmp_path, capsys):
        data, weights, _ = setup
        assert main([str(data), "--weights", str(weights), "--out", str(tmp_path)]) == 0
        rows = _rows(tmp_path / "eval_val470.csv")
        assert list(rows[0]) == ["id", "psnr", "ssim", "ms", "disp_spearman", "disp_si_rmse"]
        # the pairs carry ground-truth disparity, so the predicted map is scored against it
        assert -1.0 <= float(rows[0]["disp_spearman"]) <= 1.0
        assert 0.0 <= float(rows[0]["disp_si_rmse"]) <= 1.0
        assert [r["id"] for r in rows] == ["0002"]
        assert "PSNR" in capsys.readouterr().out

    def test_identity_baseline_known(self, setup, tmp_path):
        data, _, _ = setup
        assert (
            main([str(data), "--baseline", "identity", "--out", str(tmp_path), "--split", "all"])
            == 0
        )
        rows = _rows(tmp_path / "eval_all.csv")
        ds = EBBDataset(data, split="all")
        for row, i in zip(rows, range(3), strict=True):
            item = ds[i]
            expected = metrics.psnr(item["image"][None], item["target"][None])
            assert float(row["psnr"]) == pytest.approx(expected, rel=1e-5)

    def test_fusion_comparison(self, setup, tmp_path):
        pytest.importorskip("scipy")
        data, weights, _ = setup
        argv = [str(data), "--weights", str(weights), "--out", str(tmp_path), "--fusion"]
        assert main([*argv, "--split", "all", "--use-gt-disparity", "--limit", "2"]) == 0
        rows = _rows(tmp_path / "fusion_all.csv")
        assert [r["method"] for r in rows] == list(FUSION_METHODS) * 2
        by = {(r["id"], r["method"]): float(r["psnr"]) for r in rows}
        # the far half is blurred in the target, so any fusion keeps the near half sharp
        # and must beat plain upsampling there: alpha >= upsample
        assert by[("0000", "alpha")] >= by[("0000", "upsample")] - 1e-6

    def test_errors(self, setup, tmp_path):
        data, _, _ = setup
        assert main([str(data), "--out", str(tmp_path)]) == 2
        assert main([str(data), "--weights", str(tmp_path / "no.pt"), "--out", str(tmp_path)]) == 2
        assert (
            main([str(tmp_path / "nodata"), "--baseline", "identity", "--out", str(tmp_path)]) == 2
        )
