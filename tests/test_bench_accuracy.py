"""The speed/accuracy bench (d2f_core.bench.accuracy): quick run, metrics, K convention."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from d2f_core.bench import render as bench
from d2f_core.bench.accuracy import main, pareto_front
from d2f_core.bench.cases import edge_band, light_band, load_cases, masked_metrics
from d2f_core.metrics import psnr
from d2f_core.rendering import render
from d2f_core.train.synth import Layer, Scene, render_pinhole, render_thin_lens

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


pytestmark = pytest.mark.usefixtures("two_threads")


class TestQuickRun:
    @pytest.mark.slow
    def test_quick_mode_writes_json_and_charts(self, tmp_path, capsys):
        out, cache = tmp_path / "out", tmp_path / "cache"
        # through the d2f-bench dispatcher, as CI and the README run it
        rc = bench.main(["accuracy", "--quick", "--e2e", "--out", str(out), "--cache", str(cache)])
        assert rc == 0
        report = json.loads((out / "accuracy.json").read_text())
        names = {e["setting"] for e in report["summary"]}
        assert {"default", "paper", "adaptive", "input (no blur)"} <= names
        for e in report["summary"]:
            assert e["ms"] >= 0 and 0 < e["ssim"] <= 1 and np.isfinite(e["psnr"])
        assert any(e.get("pareto") for e in report["summary"])
        assert report["headline"] and "speedup_vs_paper" in report["headline"][0]
        assert report["e2e"]["rows"] and report["e2e"]["paper_gpu_s"] == 0.58
        for chart in ("accuracy.png", "e2e.png"):
            assert (out / chart).read_bytes()[:8] == PNG_MAGIC
        cached = sorted(cache.glob("*.npz"))
        assert cached

        # a re-run reads the ground truth from the cache instead of rendering it again
        mtimes = [p.stat().st_mtime_ns for p in cached]
        assert main(["--quick", "--out", str(out), "--cache", str(cache)]) == 0
        assert [p.stat().st_mtime_ns for p in cached] == mtimes
        assert "adaptive" in capsys.readouterr().out


class TestPieces:
    def test_render_bench_rows(self, tmp_path, capsys):
        # the renderer bench at a tiny size with K = 38 px (layers at 1/2 resolution): the exact
        # preset must match the float64 direct full-frame reference to rounding, the
        # reduced-resolution one stay above 45 dB
        path = tmp_path / "render.json"
        argv = [
            "render",
            "--sections",  # the size table only (the K sweep and 12 MP runs take minutes)
            "sizes",
            "--sizes",
            "64x96",
            "--blur-frac",
            "0.4",
            "--quality",
            "balanced",
            "exact",
        ]
        argv += ["--repeat", "1", "--baseline-repeat", "1", "--threads", "2", "--json", str(path)]
        chart = tmp_path / "render.png"
        argv += ["--chart", str(chart)]
        rc = bench.main(argv)
        assert rc == 0
        assert chart.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and chart.stat().st_size > 10_000
        rows = {r["quality"]: r for r in json.loads(path.read_text())}
        assert rows["exact"]["psnr_vs_exact"] > 100
        assert 45 <= rows["balanced"]["psnr_vs_exact"] < rows["exact"]["psnr_vs_exact"]
        for r in rows.values():
            assert 0 < r["best_ms"] <= r["ms"] and r["speedup"] > 0 and r["size"] == "64x96"
            assert r["page_faults_per_render"] >= 0
            assert all(
                v > 0 for v in r["machine_gflops_start_end"] + r["machine_copy_gbs_start_end"]
            )
        assert "GFLOP/s" in capsys.readouterr().out

    def test_authors_baseline_is_the_same_model_unstacked(self, monkeypatch):
        # the baseline convolves each layer on its own (no strips): same pixels, one
        # convolution of C channels per layer
        from d2f_core import rendering

        image, disp = bench.bench_scene(40, 60)
        calls = []
        conv = rendering.blur.F.conv2d
        monkeypatch.setattr(
            rendering.blur.F,
            "conv2d",
            lambda x, w, **k: calls.append(x.shape[1]) or conv(x, w, **k),
        )
        with torch.no_grad():
            base = bench._authors_render(image, disp, 0.6, 30.0)
            (c,) = set(calls)  # alpha and colour (and the weight, with highlights)
            assert c in (4, 5) and rendering.blur.LANES == 16
            calls.clear()
            ours = rendering.render(
                image, disp, 0.6, 30.0, quality="exact", method="direct", full_frame=True
            )
            assert all(n % c == 0 for n in calls) and max(calls) == 16 // c * c
        torch.testing.assert_close(base, ours, atol=1e-5, rtol=0)

    def test_pareto_front_known_answer(self):
        points = [(10, 30.0), (5, 29.0), (20, 29.5), (5, 28.0), (40, 31.0), (10, 30.0)]
        # (20, 29.5) is beaten by (10, 30); (5, 28) by (5, 29); the duplicates both stay
        assert pareto_front(points) == [1, 0, 5, 4]

    def test_masked_metrics_identical_and_empty_band(self):
        g = np.random.default_rng(0)
        img = g.random((32, 40, 3)).astype(np.float32)
        band = np.zeros((32, 40), bool)
        band[4:10, 4:10] = True
        m = masked_metrics(img, img, {"edges": band, "lights": np.zeros_like(band)})
        assert m["psnr"] == 100.0 and m["psnr_edges"] == 100.0
        assert m["ssim"] == pytest.approx(1.0) and m["ssim_edges"] == pytest.approx(1.0)
        assert m["psnr_lights"] is None and m["ssim_lights"] is None

    def test_masked_psnr_counts_only_the_band(self):
        a = np.zeros((20, 20, 3), np.float32)
        b = a.copy()
        b[:10] = 0.1  # error of 0.1 in the top half only: 20 dB there
        top = np.zeros((20, 20), bool)
        top[:10] = True
        m = masked_metrics(a, b, {"edges": top, "lights": ~top})
        assert m["psnr_edges"] == pytest.approx(20.0)
        assert m["psnr_lights"] == 100.0
        assert m["psnr"] == pytest.approx(20.0 + 10 * np.log10(2))

    def test_edge_band_surrounds_depth_steps(self):
        disp = np.zeros((40, 60), np.float32)
        disp[:, 30:] = 0.8
        band = edge_band(disp, blur=16.0)  # radius 4 px
        cols = np.flatnonzero(band[20])
        assert cols.min() == 29 - 4 and cols.max() == 30 + 4
        assert not edge_band(np.full((20, 20), 0.3, np.float32), 16.0).any()

    def test_light_band_grows_with_blur(self):
        lights = np.zeros((50, 50), bool)
        lights[25, 25] = True
        assert light_band(lights, 8.0).sum() < light_band(lights, 30.0).sum()


class TestConventions:
    """The renderer's ``blur`` and the synth ground truth's ``blur`` mean the same ``K``."""

    @staticmethod
    def _plane(disparity: float, focus: float, blur: float, **options):
        g = np.random.default_rng(3)
        h, w, m = 64, 96, 24
        yy, xx = np.mgrid[-m : h + m, -m : w + m]
        checker = ((yy // 5 + xx // 5) % 2).astype(np.float32) * 0.7 + 0.15
        rgb = np.stack([checker, 1 - checker, 0.5 + 0 * checker]) * g.uniform(0.8, 1, (3, 1, 1))
        layer = Layer(rgb.astype(np.float32), np.ones(rgb.shape[1:], np.float32), -m, -m, disparity)
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
            kernel="hard",
            highlight_boost=False,
            **options,
        )
        crop = int(blur * abs(disparity - focus) / 2) + 2
        pred = out[0].permute(1, 2, 0).numpy()[crop:-crop, crop:-crop]
        return psnr(pred, target[crop:-crop, crop:-crop]), psnr(
            np.clip(pinhole, 0, 1)[crop:-crop, crop:-crop], target[crop:-crop, crop:-crop]
        )

    def test_plane_in_front_of_focus_matches_ground_truth(self):
        # a 10 px CoC: a K off by 20 % costs more than 15 dB here
        got, unblurred = self._plane(0.9, 0.4, 20.0)
        assert unblurred < 15
        assert got > 40

    def test_plane_behind_focus_matches_ground_truth(self):
        # behind the focal plane the nearer of two overlapping layers is the sharper one;
        # "nearest" placement puts pixels half a layer back, "paper" placement draws this
        # 10 px CoC with the 7 px kernel
        got, unblurred = self._plane(0.1, 0.6, 20.0)
        assert unblurred < 15
        assert got > 40
        paper, _ = self._plane(0.1, 0.6, 20.0, placement="paper")
        assert paper < 25

    @pytest.mark.parametrize("coc", [2.0, 4.0, 6.0, 10.0])
    def test_both_sides_of_focus_get_the_same_blur(self, coc):
        # a CoC on a kernel's diameter (size - 1 px) is drawn with that kernel on either side
        # of the focal plane; with placement="paper", behind focus measures 20-24 dB here
        front, _ = self._plane(0.9, 0.4, coc / 0.5)
        behind, unblurred = self._plane(0.1, 0.6, coc / 0.5)
        assert behind > 38 and front > 38
        assert abs(behind - front) < 1.0
        assert behind > unblurred + 10


class TestPeers:
    def test_gather_known_answers(self):
        from d2f_core.bench.peers import gather_render

        flat = torch.full((1, 3, 20, 30), 0.4)
        disp = torch.rand(1, 1, 20, 30)
        assert torch.allclose(gather_render(flat, disp, 0.5, 12.0), flat, atol=1e-6)
        img = torch.rand(1, 3, 20, 30)
        sharp = gather_render(img, torch.full((1, 1, 20, 30), 0.5), 0.5, 12.0)
        assert torch.allclose(sharp, img, atol=1e-6)  # every CoC 0: the photo
        # one bright far pixel on a dark in-focus... plane of its own CoC: a disc of radius 5
        dot = torch.zeros(1, 3, 41, 41)
        dot[..., 20, 20] = 1.0
        out = gather_render(dot, torch.zeros(1, 1, 41, 41), 1.0, 10.0)[0, 0]
        lit = out > 1e-6
        ys, xs = torch.nonzero(lit, as_tuple=True)
        assert int(ys.min()) == 15 and int(ys.max()) == 25 and int(xs.min()) == 15
        assert float(out[20, 20]) == pytest.approx(float(out[20, 24]), rel=1e-5)  # flat disc

    def test_edge_sides(self):
        from d2f_core.bench.peers import edge_sides

        d = np.zeros((20, 40), np.float32)
        d[:, 20:] = 1.0
        near, far = edge_sides(d, width=3)
        assert near[:, 20:24].all() and not near[:, :20].any() and not near[:, 24:].any()
        assert far[:, 16:20].all() and not far[:, 20:].any() and not (near & far).any()

    def test_run_peers_reports_every_category(self, tmp_path):
        from d2f_core.bench.peers import (
            CATEGORIES,
            DEFAULT_METHODS,
            by_group,
            format_groups,
            format_table,
            run_peers,
            summary,
        )

        cases = load_cases([(40, 56)], [11, 12], [0.12], samples=16, cache=tmp_path)
        cases += load_cases([(40, 56)], [11], k_px=[3.0], samples=16, cache=tmp_path)
        result = run_peers(cases, repeat=1, methods=DEFAULT_METHODS + ("Blender Defocus",))
        if "Blender Defocus" not in {r["method"] for r in result["rows"]}:
            assert "Blender Defocus skipped" in result["notes"][0]
        table = summary(result["rows"])
        assert set(DEFAULT_METHODS) <= set(table)
        assert table["paper, FFT"]["time ratio"] == pytest.approx(1.0)  # the baseline
        for entry in table.values():
            assert entry["all"] is not None and 5 < entry["all"] < 100
            assert {name for name, _, _ in CATEGORIES} <= set(entry)
        assert format_table(table).count("\n") == len(table) + 1
        by_k = by_group(result["rows"], "blur")
        assert list(by_k["d2f"]) == [3.0, 6.72]  # sorted; 0.12 x 56 px
        assert by_k["d2f"][6.72]["cases"] == 2 and by_k["d2f"][3.0]["cases"] == 1
        # a group's figure is the mean over its cases
        rows = [r for r in result["rows"] if r["method"] == "gather" and r["blur"] == 6.72]
        assert by_k["gather"][6.72]["psnr"] == pytest.approx(np.mean([r["psnr"] for r in rows]))
        assert by_k["gather"][6.72]["psnr_edges"] == pytest.approx(
            np.mean([r["psnr_edges"] for r in rows])
        )
        lines = format_groups(by_k, "blur").splitlines()
        assert lines[0].startswith("| K (px) | cases | d2f |") and len(lines) == 4
        assert set(by_group(result["rows"], "category")["d2f"]) <= {
            "occlusion",
            "thin",
            "highlights",
            "mixed",
        }

    def test_scene_category(self):
        from d2f_core.bench.peers import scene_category

        none, some = np.zeros((8, 8), bool), np.eye(8, dtype=bool)
        assert scene_category(none, none) == "occlusion"
        assert scene_category(some, none) == "thin"
        assert scene_category(none, some) == "highlights"
        assert scene_category(some, some) == "mixed"

    def test_load_cases_k_in_px_shares_the_cache(self, tmp_path):
        by_frac = load_cases([(40, 56)], [11], [0.25], samples=8, cache=tmp_path)
        files = sorted(tmp_path.glob("*.npz"))
        by_px = load_cases([(40, 56)], [11], k_px=[14.0], samples=8, cache=tmp_path)
        assert sorted(tmp_path.glob("*.npz")) == files  # 0.25 x 56 = 14 px: read, not made
        assert by_px[0].key == by_frac[0].key and by_px[0].blur == 14.0
        np.testing.assert_array_equal(by_px[0].target, by_frac[0].target)
        with pytest.raises(ValueError, match="at least one K"):
            load_cases([(40, 56)], [11], samples=8)
        with pytest.raises(ValueError, match="finite and > 0"):
            load_cases([(40, 56)], [11], k_px=[0.0], samples=8)

    def test_peers_cli_refuses_unknown_method(self, capsys):
        from d2f_core.bench.peers import main as peers_main

        with pytest.raises(SystemExit) as exc:
            peers_main(["--methods", "nope", "--k-px", "4"])
        assert exc.value.code == 2
        assert "unknown method 'nope'" in capsys.readouterr().err

    def test_blender_peer_when_installed(self):
        """Blender's Defocus node as the bench runs it: pixels in = pixels out where nothing
        is blurred, a flat photo stays flat, and a bright square spreads by its CoC radius."""
        from d2f_core.bench.peers import blender_available, blender_render

        if blender_available() is None:
            pytest.skip("blender is not on PATH (Debian: apt-get install blender)")
        rng = np.random.default_rng(0)
        img = rng.random((40, 56, 3)).astype(np.float32)
        flat_d = np.zeros((40, 56), np.float32)
        same = blender_render(img, flat_d, 0.0, 16.0)
        assert np.abs(same - np.round(img * 255) / 255).max() <= 1.5 / 255
        flat = blender_render(np.full((40, 56, 3), 0.4, np.float32), flat_d, 1.0, 16.0)
        assert np.abs(flat - 0.4).max() <= 1.5 / 255
        dot = np.zeros((40, 56, 3), np.float32)
        dot[18:22, 26:30] = 1.0
        ys, xs = np.nonzero(blender_render(dot, flat_d, 1.0, 16.0).mean(-1) > 0.005)
        assert 11 <= ys.min() <= 14 and 27 <= ys.max() <= 30  # radius 8 around rows 18-21


def test_e2e_runs_the_weights_own_defocus_network(tmp_path, tiny_checkpoint):
    """``"shipped"`` is the defocus network the weights hold, loaded from them; a variant
    the weights do not hold is randomly initialised and said to be."""
    from d2f_core.bench.accuracy import run_e2e

    cases = load_cases([(40, 56)], [11], [0.12], samples=16, cache=tmp_path)
    rows, sources = run_e2e(cases, variants=("shipped",), scales=(0.5,), weights=tiny_checkpoint)
    assert sources == {"lite": str(tiny_checkpoint)}
    assert {r["series"] for r in rows} == {"lite", "given disparity"}
    assert all(np.isfinite(r["psnr"]) for r in rows)
    _, sources = run_e2e(cases, variants=("lite-ctx",), scales=(0.5,), weights=tiny_checkpoint)
    assert sources == {"lite-ctx": "random init"}
