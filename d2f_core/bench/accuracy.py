"""Speed against accuracy: ``d2f-bench accuracy`` (``python -m d2f_core.bench accuracy``).

Renders a fixed, seeded set of generated layered scenes (:mod:`d2f_core.train.synth`) with a grid of
renderer settings and compares each result with the accumulation-buffer thin-lens ground truth
of the same scene, focus and ``K``. The renderer gets what a user would have: the pinhole
photo (sRGB, highlights clipped at 1) and the exact disparity; the ground truth is the
thin-lens view in linear radiance (HDR lights above 1), clipped and sRGB-encoded like a
camera would store it.

Settings vary one axis at a time around the default (depth order, 15 layers, growing schedule,
soft disk, ``quality="balanced"``, FFT, HDR boost on), plus the paper's configuration (paper
order, 15 layers, growing, soft, exact resolution, direct convolution), a few combined points
and the adaptive picker of :mod:`d2f_core.rendering.adaptive`. For each it reports the median
time per frame and PSNR/SSIM overall, in a band around occlusion edges (depth discontinuities of the
ground-truth disparity) and in a band around HDR lights; it writes ``accuracy.json`` and a
chart of time against PSNR with the Pareto front.

``--e2e`` also charts the whole pipeline (``D2F.prepare`` + ``D2F.render``) for both defocus
network variants and several low-resolution pass sizes on a held-out generated set.
``--calibrate`` measures the adaptive picker's table (PSNR against the exact reference only, no
ground truth needed). Nothing here asserts a time; figures are as measured on this machine.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..rendering import PLACEMENTS, adaptive, render
from .cases import PAPER_GPU_SECONDS, Case, load_cases, masked_metrics
from .charts import plot_accuracy, plot_e2e

__all__ = [
    "Setting",
    "calibrate",
    "default_settings",
    "main",
    "pareto_front",
    "run_grid",
]

logger = logging.getLogger("d2f_core.bench.accuracy")


DEFAULT_OPTIONS: dict[str, Any] = {
    "order": "depth",
    "num_layers": 15,
    "schedule": "growing",
    "kernel": "soft",
    "quality": "balanced",
    "method": "fft",
    "highlight_boost": True,
}


PAPER_OPTIONS: dict[str, Any] = {
    "order": "paper",
    "num_layers": 15,
    "schedule": "growing",
    "kernel": "soft",
    "quality": "exact",
    "method": "direct",
    "highlight_boost": True,
}


FULL = {
    "sizes": ((128, 192), (256, 384), (384, 576)),
    "seeds": (11, 12, 13, 14),
    "k_fracs": (0.03, 0.06, 0.1),
    "samples": 192,
    "repeat": 3,
}


QUICK = {
    "sizes": ((40, 56),),
    "seeds": (11,),
    "k_fracs": (0.12,),
    "samples": 24,
    "repeat": 1,
}


E2E_FULL = {"size": (384, 576), "seeds": (101, 102, 103), "k_frac": 0.06, "samples": 192}


E2E_QUICK = {"size": (48, 64), "seeds": (101,), "k_frac": 0.1, "samples": 16}


@dataclass(frozen=True)
class Setting:
    """One point of the grid: renderer options, or the adaptive picker (``adaptive`` set to
    its user-facing quality) on top of ``options``."""

    name: str
    axis: str
    options: tuple[tuple[str, Any], ...]
    adaptive: str | None = None

    @property
    def kwargs(self) -> dict[str, Any]:
        return dict(self.options)


def _setting(name: str, axis: str, adaptive_quality: str | None = None, **changes) -> Setting:
    opts = dict(DEFAULT_OPTIONS) | changes
    if adaptive_quality is not None:
        opts.pop("num_layers")
        opts.pop("quality")
    return Setting(name, axis, tuple(sorted(opts.items())), adaptive_quality)


def default_settings(quick: bool = False) -> list[Setting]:
    """The grid: one axis at a time around the default, plus combined points."""
    if quick:
        return [
            _setting("default", "default"),
            Setting("paper", "paper", tuple(sorted(PAPER_OPTIONS.items()))),
            _setting("layers 7", "layers", num_layers=7),
            _setting("paper order", "order", order="paper"),
            _setting("adaptive", "adaptive", "balanced"),
        ]
    out = [_setting("default", "default")]
    out += [_setting(f"layers {n}", "layers", num_layers=n) for n in (5, 7, 9, 11, 19, 23, 31)]
    out += [
        _setting("uniform schedule", "schedule", schedule="uniform"),
        _setting("hard disk", "kernel", kernel="hard"),
        _setting("quality exact", "resolution", quality="exact"),
        _setting("quality high", "resolution", quality="high"),
        _setting("quality fast", "resolution", quality="fast"),
        _setting("direct conv", "method", method="direct"),
        _setting("paper order", "order", order="paper"),
        _setting("paper placement", "placement", placement="paper"),
        _setting("no HDR boost", "hdr", highlight_boost=False),
        Setting("paper", "paper", tuple(sorted(PAPER_OPTIONS.items()))),
        _setting("paper, FFT", "combined", **(PAPER_OPTIONS | {"method": "fft"})),
        _setting("fast, 7 layers", "combined", quality="fast", num_layers=7),
        _setting("fast, 9 layers, hard", "combined", quality="fast", num_layers=9, kernel="hard"),
        _setting("exact, 31 layers", "combined", quality="exact", num_layers=31),
        _setting("adaptive high", "adaptive", "high"),
        _setting("adaptive", "adaptive", "balanced"),
        _setting("adaptive fast", "adaptive", "fast"),
    ]
    return out


def _runner(setting: Setting, case: Case) -> Callable[[], torch.Tensor]:
    image, disparity = case.tensors()
    kwargs = setting.kwargs
    if setting.adaptive is not None:

        def run() -> torch.Tensor:
            return adaptive.render_adaptive(
                image, disparity, case.focus, case.blur, quality=setting.adaptive, **kwargs
            )[0]

        return run

    def run_fixed() -> torch.Tensor:
        return render(image, disparity, case.focus, case.blur, **kwargs)

    return run_fixed


def run_grid(
    cases: Sequence[Case], settings: Sequence[Setting], *, repeat: int = 3
) -> list[dict[str, Any]]:
    """Time and score every setting on every case.

    Timing is interleaved (round robin over the settings, ``repeat`` rounds, after one warm-up
    round) so a change of machine load hits all settings alike. Returns one row per
    (setting, case) with ``ms`` (median), ``ms_all`` and the metrics of
    :func:`masked_metrics`.
    """
    rows = []
    with torch.no_grad():
        for case in cases:
            runners = [_runner(s, case) for s in settings]
            outputs = [run() for run in runners]  # warm-up (kernel spectra, allocator)
            times: list[list[float]] = [[] for _ in settings]
            for _ in range(repeat):
                for i, run in enumerate(runners):
                    t0 = time.perf_counter()
                    run()
                    times[i].append(1000.0 * (time.perf_counter() - t0))
            for setting, out, ms in zip(settings, outputs, times, strict=True):
                pred = out[0].permute(1, 2, 0).numpy()
                row = {
                    "setting": setting.name,
                    "axis": setting.axis,
                    "case": case.key,
                    "size": f"{case.size[0]}x{case.size[1]}",
                    "blur": case.blur,
                    "focus": case.focus,
                    "mode": case.mode,
                    "ms": statistics.median(ms),
                    "ms_all": [round(t, 2) for t in ms],
                }
                row |= masked_metrics(pred, case.target, case.bands)
                if setting.adaptive is not None:
                    _, disp = case.tensors()
                    picked = adaptive.choose_settings(
                        disp, case.focus, case.blur, quality=setting.adaptive
                    )
                    row["picked"] = picked.render_options() | {"identity": picked.identity}
                rows.append(row)
            base = masked_metrics(case.image, case.target, case.bands)
            rows.append(
                {
                    "setting": "input (no blur)",
                    "axis": "baseline",
                    "case": case.key,
                    "size": f"{case.size[0]}x{case.size[1]}",
                    "blur": case.blur,
                    "focus": case.focus,
                    "mode": case.mode,
                    "ms": 0.0,
                }
                | base
            )
            logger.info("case %s: %d settings done", case.key, len(settings))
    return rows


def _mean(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def summarise(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (size, setting): mean over cases of the median ms and of each metric."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["size"], row["setting"]), []).append(row)
    out = []
    for (size, name), group in groups.items():
        entry = {"size": size, "setting": name, "axis": group[0]["axis"], "cases": len(group)}
        for key in (
            "ms",
            "psnr",
            "ssim",
            "psnr_edges",
            "ssim_edges",
            "psnr_lights",
            "ssim_lights",
        ):
            entry[key] = _mean([r.get(key) for r in group])
        out.append(entry)
    for size in {e["size"] for e in out}:
        rows_at = [e for e in out if e["size"] == size and e["axis"] != "baseline"]
        front = pareto_front([(e["ms"], e["psnr"]) for e in rows_at])
        for i, e in enumerate(rows_at):
            e["pareto"] = i in front
    return out


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats (less or equal time and higher or equal
    PSNR, one of them strictly), sorted by time."""
    front = []
    for i, (t, q) in enumerate(points):
        dominated = any(
            (t2 <= t and q2 >= q) and (t2 < t or q2 > q)
            for j, (t2, q2) in enumerate(points)
            if j != i
        )
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


def calibrate(
    sizes: Sequence[tuple[int, int]],
    seeds: Sequence[int],
    k_fracs: Sequence[float],
    placements: Sequence[str] = PLACEMENTS,
) -> dict[str, Any]:
    """Worst-case PSNR of every :data:`adaptive.CANDIDATES` entry against the exact
    15-layer reference, per largest-CoC bin of :data:`adaptive.COC_BINS`.

    Scenes are generated (pinhole view and exact disparity); three focal planes per scene
    (main subject, farthest object, nearest object), each with every layer placement of
    ``placements`` (``rendering.layer_plan``; the candidate against the reference of the same
    placement). No ground truth is needed.
    """
    from ..train.synth import linear_to_srgb, make_scene, render_pinhole

    nbins = len(adaptive.COC_BINS) + 1
    table: dict[tuple[int, str], list[float | None]] = {
        c: [None] * nbins for c in adaptive.CANDIDATES
    }
    points = []
    with torch.no_grad():
        for size in sizes:
            for seed in seeds:
                scene = make_scene(tuple(size), seed=seed)
                radiance, disp = render_pinhole(scene)
                image = torch.from_numpy(linear_to_srgb(radiance)).permute(2, 0, 1)[None]
                image = image.contiguous()
                d = torch.from_numpy(disp)[None, None].contiguous()
                orders = [float(lay.order) for lay in scene.layers]
                for focus in (scene.subject, min(orders[1:] or orders), max(orders)):
                    for k_frac, placement in itertools.product(k_fracs, placements):
                        blur = k_frac * size[1]
                        max_coc = blur * float((d - focus).abs().max())
                        kw = {"placement": placement}
                        ref = render(image, d, focus, blur, quality="exact", num_layers=15, **kw)
                        b = adaptive.coc_bin(max_coc)
                        for cand in adaptive.CANDIDATES:
                            if cand == (15, "exact"):
                                continue
                            out = render(
                                image, d, focus, blur, num_layers=cand[0], quality=cand[1], **kw
                            )
                            mse = float(((out - ref) ** 2).mean())
                            value = 100.0 if mse <= 1e-10 else -10 * math.log10(mse)
                            cell = table[cand][b]
                            table[cand][b] = value if cell is None else min(cell, value)
                            points.append(
                                {
                                    "size": list(size),
                                    "seed": seed,
                                    "focus": focus,
                                    "blur": blur,
                                    "max_coc": max_coc,
                                    "layers": cand[0],
                                    "quality": cand[1],
                                    "placement": placement,
                                    "psnr": value,
                                }
                            )
                logger.info("calibrated %s seed %d", size, seed)
    rounded = {
        f"{n},{q}": [None if v is None else round(v, 1) for v in row]
        for (n, q), row in table.items()
    }
    return {"coc_bins": list(adaptive.COC_BINS), "table": rounded, "points": points}


def run_e2e(
    cases: Sequence[Case],
    *,
    variants: Sequence[str] = ("shipped", "resnext50"),
    scales: Sequence[float] = (0.25, 0.5, 1.0),
    repeat: int = 1,
    weights: str | Path | None = None,
) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Time and score ``D2F.prepare`` + ``D2F.render`` on held-out cases.

    ``variants`` are defocus networks; ``"shipped"`` stands for the one of ``weights`` (the
    shipped weights by default). For each variant and low-resolution pass scale the model is
    loaded from the weights when they hold that variant, else randomly initialised (seeded);
    the ``"given disparity"`` series passes the ground-truth disparity to ``prepare`` (no
    defocus network) with the first variant's radiance and fusion networks, which isolates
    renderer and fusion. Returns rows and the weights used per variant.
    """
    from ..pipeline import D2F, D2FConfig, default_weights_path

    path = Path(weights) if weights else default_weights_path()
    loaded = None
    if path.is_file():
        try:
            loaded = D2F.from_checkpoint(path)
        except (ValueError, FileNotFoundError) as exc:
            logger.warning("weights %s not usable: %s", path, exc)
    shipped = loaded.config.defocus if loaded is not None else "lite"
    variants = [shipped if v == "shipped" else v for v in variants]
    sources: dict[str, str] = {}
    rows = []
    series = [(v, False) for v in variants] + [(variants[0], True)]
    with torch.no_grad():
        for variant, given in series:
            base_model = None
            if loaded is not None and loaded.config.defocus == variant:
                base_model = loaded
                sources[variant] = str(path)
            if base_model is None:
                torch.manual_seed(0)
                base_model = D2F.from_config({"defocus": variant})
                sources[variant] = "random init"
            state = base_model.state_dict()
            for scale in scales:
                cfg = base_model.config.to_dict() | {"render_scale": float(scale)}
                model = D2F(D2FConfig.from_dict(cfg)).eval()
                model.load_state_dict(state)
                name = "given disparity" if given else variant
                for case in cases:
                    disparity = case.disparity if given else None

                    def once(model=model, case=case, disparity=disparity):
                        t0 = time.perf_counter()
                        scene = model.prepare(case.image, disparity)
                        t1 = time.perf_counter()
                        res = model.render(scene, case.focus, case.blur)
                        t2 = time.perf_counter()
                        return res, 1000 * (t1 - t0), 1000 * (t2 - t1)

                    res, _, _ = once()  # warm-up
                    runs = [once() for _ in range(repeat)]
                    metrics = masked_metrics(res.bokeh, case.target, case.bands)
                    rows.append(
                        {
                            "series": name,
                            "variant": variant,
                            "scale": scale,
                            "case": case.key,
                            "prepare_ms": statistics.median(r[1] for r in runs),
                            "render_ms": statistics.median(r[2] for r in runs),
                            "ms": statistics.median(r[1] + r[2] for r in runs),
                        }
                        | metrics
                    )
                logger.info("e2e %s scale %.2f done", name, scale)
    return rows, sources


def _parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 256x384, got {text!r}") from None
    if min(h, w) < 16:
        raise argparse.ArgumentTypeError(f"size must be at least 16x16, got {text!r}")
    return h, w


def _headline(summary: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per size: adaptive (balanced) against the paper configuration and the default."""
    out = []
    for size in sorted({e["size"] for e in summary}, key=lambda s: int(s.split("x")[0])):
        by_name = {e["setting"]: e for e in summary if e["size"] == size}
        paper, ada, default = by_name.get("paper"), by_name.get("adaptive"), by_name.get("default")
        front = [e for e in by_name.values() if e.get("pareto")]
        if not (paper and ada):
            continue
        line = {
            "size": size,
            "paper_ms": paper["ms"],
            "paper_psnr": paper["psnr"],
            "adaptive_ms": ada["ms"],
            "adaptive_psnr": ada["psnr"],
            "speedup_vs_paper": paper["ms"] / max(ada["ms"], 1e-9),
            "adaptive_on_front": bool(ada.get("pareto")),
            # how far below the Pareto front the adaptive point sits at its own time
            "adaptive_db_below_front": max(
                [e["psnr"] for e in front if e["ms"] <= ada["ms"]] + [ada["psnr"]]
            )
            - ada["psnr"],
        }
        if default:
            line |= {"default_ms": default["ms"], "default_psnr": default["psnr"]}
        out.append(line)
    return out


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="d2f-bench accuracy",
        description="Renderer settings against accumulation-buffer ground truth "
        "(time vs PSNR/SSIM, Pareto front, adaptive settings).",
    )
    parser.add_argument("--quick", action="store_true", help="tiny scenes, few settings (CI)")
    parser.add_argument("--out", type=Path, default=Path("bench_out"), help="output folder")
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="folder for the generated scenes and their ground truth (default OUT/cache)",
    )
    parser.add_argument("--sizes", type=_parse_size, nargs="+", default=None, help="HxW ...")
    parser.add_argument("--seeds", type=int, nargs="+", default=None)
    parser.add_argument("--k-fracs", type=float, nargs="+", default=None, help="K / width")
    parser.add_argument("--samples", type=int, default=None, help="aperture samples of the GT")
    parser.add_argument("--repeat", type=int, default=None, help="timed rounds per case")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--e2e", action="store_true", help="also chart prepare + render")
    parser.add_argument("--e2e-only", action="store_true", help="only the end-to-end chart")
    parser.add_argument("--weights", type=Path, default=None, help="checkpoint for --e2e")
    parser.add_argument(
        "--calibrate", action="store_true", help="measure the adaptive picker's table and exit"
    )
    parser.add_argument(
        "--placements",
        nargs="+",
        choices=PLACEMENTS,
        default=list(PLACEMENTS),
        help="layer placements --calibrate measures (default: all)",
    )
    parser.add_argument("-v", "--verbose", action="store_true")
    return parser


def _load_average() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def _calibrate_step(args: argparse.Namespace, out_dir: Path, meta: dict[str, Any]) -> int:
    """``--calibrate``: the adaptive picker's table, written and printed."""
    cal_sizes = args.sizes or ((256, 384), (512, 768))
    cal_seeds = args.seeds or (201, 202, 203, 204, 205, 206)
    cal_k = args.k_fracs or (0.01, 0.02, 0.04, 0.07, 0.1, 0.15, 0.2)
    result = calibrate(cal_sizes, cal_seeds, cal_k, args.placements) | {"meta": meta}
    (out_dir / "calibration.json").write_text(json.dumps(result, indent=1))
    print(f"wrote {out_dir / 'calibration.json'}")
    for key, row in result["table"].items():
        print(f"    ({key.replace(',', ', ')!s}): {tuple(row)},")
    return 0


def _grid_step(
    args: argparse.Namespace, preset: dict[str, Any], cache: Path, out_dir: Path
) -> dict[str, Any]:
    """The settings grid on the generated cases: the report's part, the chart and the
    table printed."""
    sizes = args.sizes or preset["sizes"]
    seeds = args.seeds or preset["seeds"]
    k_fracs = args.k_fracs or preset["k_fracs"]
    samples = args.samples or preset["samples"]
    repeat = args.repeat or preset["repeat"]
    t0 = time.perf_counter()
    cases = load_cases(sizes, seeds, k_fracs, samples=samples, cache=cache)
    t_cases = time.perf_counter() - t0
    settings = default_settings(args.quick)
    t0 = time.perf_counter()
    rows = run_grid(cases, settings, repeat=repeat)
    summary = summarise(rows)
    report = {
        "cases": [
            {"key": c.key, "focus": c.focus, "blur": c.blur, "size": list(c.size)} for c in cases
        ],
        "settings": [
            {"name": s.name, "axis": s.axis, "options": s.kwargs, "adaptive": s.adaptive}
            for s in settings
        ],
        "summary": summary,
        "headline": _headline(summary),
        "rows": rows,
        "seconds": {"cases": t_cases, "grid": time.perf_counter() - t0},
    }
    title = (
        f"Layered renderer: time vs PSNR against thin-lens ground truth "
        f"({len(seeds)} scenes x K = {', '.join(f'{k:g}' for k in k_fracs)} x width, "
        f"{torch.get_num_threads()} CPU threads)"
    )
    plot_accuracy(summary, out_dir / "accuracy.png", title)

    def fmt(v):
        return "   -  " if v is None else f"{v:6.2f}"

    print(f"{'size':>8} {'setting':<22} {'ms':>8} {'PSNR':>6} {'edges':>6} {'lights':>6}")
    for e in sorted(summary, key=lambda e: (int(e["size"].split("x")[0]), e["ms"])):
        star = " *" if e.get("pareto") else ""
        print(
            f"{e['size']:>8} {e['setting']:<22} {e['ms']:8.1f} {fmt(e['psnr'])} "
            f"{fmt(e['psnr_edges'])} {fmt(e['psnr_lights'])}{star}"
        )
    for h in report["headline"]:
        print(
            f"{h['size']}: adaptive {h['adaptive_ms']:.1f} ms {h['adaptive_psnr']:.2f} dB, "
            f"paper {h['paper_ms']:.1f} ms {h['paper_psnr']:.2f} dB: "
            f"{h['speedup_vs_paper']:.1f}x faster; {h['adaptive_db_below_front']:.2f} dB "
            "below the Pareto front"
        )
    return report


def _e2e_step(args: argparse.Namespace, cache: Path, out_dir: Path) -> dict[str, Any]:
    """Prepare + render of the pipeline on held-out scenes: the report's part, the chart
    and the rows printed."""
    e2e = E2E_QUICK if args.quick else E2E_FULL
    e2e_cases = load_cases(
        [e2e["size"]], e2e["seeds"], [e2e["k_frac"]], samples=e2e["samples"], cache=cache
    )
    variants = ("shipped",) if args.quick else ("shipped", "resnext50")
    scales = (0.5,) if args.quick else (0.25, 0.5, 1.0)
    e2e_rows, sources = run_e2e(e2e_cases, variants=variants, scales=scales, weights=args.weights)
    random_init = [v for v, s in sources.items() if s == "random init"]
    note = f" (random init: {', '.join(random_init)})" if random_init else ""
    h, w = e2e["size"]
    title = (
        f"D2F pipeline prepare + render, {len(e2e_cases)} held-out generated {h}x{w} scenes, "
        f"K = {e2e['k_frac']:g} x width{note}"
    )
    plot_e2e(e2e_rows, out_dir / "e2e.png", title)
    for r in e2e_rows:
        print(
            f"e2e {r['series']:<16} x{r['scale']:<5g} {r['case']:<28} "
            f"prepare {r['prepare_ms']:7.1f} ms render {r['render_ms']:7.1f} ms "
            f"PSNR {r['psnr']:.2f}"
        )
    return {"rows": e2e_rows, "weights": sources, "paper_gpu_s": PAPER_GPU_SECONDS}


def main(argv: list[str] | None = None) -> int:
    """``d2f-bench accuracy [--quick] [--out DIR] [--cache DIR] [--e2e] [--calibrate]``."""
    argv = list(argv) if argv is not None else None
    if argv and argv[0] == "--":
        # `d2f-bench accuracy -- --quick`: the dispatcher's REMAINDER keeps the separator
        argv = argv[1:]
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s"
    )
    torch.set_num_threads(max(1, args.threads))
    out_dir: Path = args.out
    cache = args.cache or out_dir / "cache"
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {
        "quick": args.quick,
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_1min_at_start": _load_average(),
    }
    if args.calibrate:
        return _calibrate_step(args, out_dir, meta)
    report: dict[str, Any] = {"meta": meta}
    if not args.e2e_only:
        report |= _grid_step(args, QUICK if args.quick else FULL, cache, out_dir)
    if args.e2e or args.e2e_only:
        report["e2e"] = _e2e_step(args, cache, out_dir)
    report["meta"]["load_average_1min_at_end"] = _load_average()
    (out_dir / "accuracy.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"wrote {out_dir / 'accuracy.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
