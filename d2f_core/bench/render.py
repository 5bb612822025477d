"""Benchmarks: ``python -m d2f_core.bench render|accuracy|depth|peers`` (``d2f-bench``); the
app's latency bench lives with the app (``python -m app.bench``), so the core never imports it.

Figures are printed as measured here, with ratios against a baseline measured in the same run;
nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .. import rendering
from ..metrics import psnr
from ..rendering import render

__all__ = ["bench_scene", "machine_speed", "main", "plot_render", "time_call"]

log = logging.getLogger(__name__)

RENDER_SIZES = ((384, 576), (512, 768), (1024, 1536))
#: Sections of ``d2f-bench render``: presets by size, a K sweep at 1024x1536, 12 MP with
#: peak memory, and 2 against 1 thread beside a busy process.
RENDER_SECTIONS = ("sizes", "ksweep", "12mp", "contention")
K_SWEEP_PX = (10, 30, 100, 200, 300)
BASELINE_COMMIT = "00e22a4"
#: The renderer at BASELINE_COMMIT, frozen: a file of the repository's benchmarks/ folder,
#: which the installed package does not carry.
FROZEN_RENDERER = Path(__file__).resolve().parents[2] / "benchmarks" / "rendering_00e22a4.py"
#: Slider re-render targets (ms) of the default preset, by frame size.
RENDER_TARGETS_MS = {"384x576": 40.0, "512x768": 120.0}
#: The least PSNR (dB) against the exact reference a reduced-resolution preset may reach.
RENDER_MIN_PSNR = 45.0
# Exact renders match the float64 reference to float32 rounding (~140 dB); drawn at this height.
_CHART_TOP_DB = 80.0


def time_call(fn: Callable[[], object], repeat: int, warmup: int = 1) -> list[float]:
    """Wall-clock seconds of ``repeat`` calls of ``fn`` after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def machine_speed(repeat: int = 10) -> tuple[float, float]:
    """This machine's speed right now: fp32 1024x1024 matmul GFLOP/s and copy GB/s (best of
    ``repeat``), at the current torch thread count.

    Shared virtual machines slow down by a third and more from minute to minute; printing this
    next to timings says how fast the machine was while they were taken.
    """
    a = torch.rand(1024, 1024)
    b = torch.rand(1024, 1024)
    matmul = min(time_call(lambda: a @ b, repeat))
    src = torch.rand(16 * 1024 * 1024)
    dst = torch.empty_like(src)
    copy = min(time_call(lambda: dst.copy_(src), repeat))
    return 2 * 1024**3 / matmul / 1e9, 2 * src.numel() * 4 / copy / 1e9


def bench_scene(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A real photo with its measured disparity: Middlebury 'motorcycle' from scikit-image.

    Returns ``image (1, 3, H, W)`` and ``disparity (1, 1, H, W)`` in [0, 1] (1 = nearest),
    holes filled with the farthest value.
    """
    from skimage import data
    from skimage.transform import resize

    left, _, disp = data.stereo_motorcycle()
    disp = np.nan_to_num(disp.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    image = resize(left, (height, width), anti_aliasing=True).astype(np.float32)
    disp = resize(disp, (height, width), order=0, anti_aliasing=False)
    valid = disp[disp > 0]
    lo, hi = np.percentile(valid, 1), np.percentile(valid, 99)
    disp = np.clip((disp - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)
    img_t = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].contiguous()
    return img_t, torch.from_numpy(disp)[None, None].contiguous()


@functools.cache
def frozen_renderer():
    """The module :data:`FROZEN_RENDERER` (its ``render`` is the baseline's), loaded by path.

    Raises:
        FileNotFoundError: not a checkout of the repository (an installed package).
    """
    if not FROZEN_RENDERER.is_file():
        raise FileNotFoundError(
            f"d2f-bench render compares with the frozen renderer {FROZEN_RENDERER}, "
            "found in a checkout of the repository only"
        )
    spec = importlib.util.spec_from_file_location("d2f_frozen_rendering", FROZEN_RENDERER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def _minor_faults() -> int:
    """Minor page faults of this process so far (0 where ``resource`` is missing): memory the
    kernel mapped and zero-filled afresh, a cost that moves render times between runs."""
    try:
        import resource
    except ImportError:  # not POSIX
        return 0
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _authors_render(image, disparity, focus: float, blur: float) -> torch.Tensor:
    """The authors' way: every layer over the whole frame at full resolution, one direct
    depthwise convolution per layer (no strips stacked along channels), float32."""
    lanes = rendering.blur.LANES
    rendering.blur.LANES = 1
    try:
        return render(
            image, disparity, focus, blur, quality="exact", method="direct", full_frame=True
        )
    finally:
        rendering.blur.LANES = lanes


def _bench_render(args: argparse.Namespace) -> int:
    baseline = frozen_renderer()
    torch.set_num_threads(args.threads)
    rows = []
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    print(
        f"# layered render, depth order, focus {args.focus}, blur = {args.blur_frac} x width, "
        f"{torch.get_num_threads()} threads, median and best of {args.repeat} rounds "
        "(presets take turns)"
    )
    speed_start = machine_speed()
    print(
        f"# machine now: {speed_start[0]:.0f} GFLOP/s fp32 matmul, {speed_start[1]:.0f} GB/s copy"
    )
    header = (
        f"{'size':>10} {'blur':>5} {'quality':>9} {'ms':>8} {'best ms':>8} {'x authors':>9} "
        f"{'PSNR vs exact':>13} {'faults':>8} {'x today':>8}"
    )
    print(f"# x today: time over that of the renderer at commit {BASELINE_COMMIT}, per round")
    if "sizes" in args.sections:
        print(header)
    for height, width in sizes if "sizes" in args.sections else ():
        image, disp = bench_scene(height, width)
        blur = args.blur_frac * width
        with torch.no_grad():
            ref_method = "direct" if height * width <= args.direct_max_pixels else "fft"
            start = time.perf_counter()
            reference = render(
                image.double(),
                disp.double(),
                args.focus,
                blur,
                quality="exact",
                method=ref_method,
                full_frame=True,
            )
            ref_s = time.perf_counter() - start
            # the authors' way: every layer over the whole frame, direct convolution, float32
            authors = time_call(
                lambda im=image, d=disp, b=blur: _authors_render(im, d, args.focus, b),
                repeat=1 if height * width > 400_000 else args.baseline_repeat,
                warmup=0,
            )
            base_ms = 1000 * statistics.median(authors)
            # presets take turns, round by round, so a slow minute of the shared machine
            # falls on all of them alike
            times: dict[str, list[float]] = {q: [] for q in args.quality}
            today: dict[str, list[float]] = {q: [] for q in args.quality}
            faults = dict.fromkeys(args.quality, 0)
            for quality in args.quality:  # warm-up
                render(image, disp, args.focus, blur, quality=quality)
                baseline.render(image, disp, args.focus, blur, quality=quality)
            for _ in range(args.repeat):
                for quality in args.quality:
                    today[quality] += time_call(
                        lambda im=image, d=disp, b=blur, q=quality: baseline.render(
                            im, d, args.focus, b, quality=q
                        ),
                        repeat=1,
                        warmup=0,
                    )
                    before = _minor_faults()
                    times[quality] += time_call(
                        lambda im=image, d=disp, b=blur, q=quality: render(
                            im, d, args.focus, b, quality=q
                        ),
                        repeat=1,
                        warmup=0,
                    )
                    faults[quality] += _minor_faults() - before
            for quality in args.quality:
                out = render(image, disp, args.focus, blur, quality=quality)
                ms = 1000 * statistics.median(times[quality])
                row = {
                    "size": f"{height}x{width}",
                    "blur": blur,
                    "quality": quality,
                    "ms": ms,
                    "best_ms": 1000 * min(times[quality]),
                    "authors_ms": base_ms,
                    "baseline_ms": 1000 * statistics.median(today[quality]),
                    "x_baseline": statistics.median(
                        [a / b for a, b in zip(times[quality], today[quality], strict=True)]
                    ),
                    "speedup": base_ms / ms,
                    "psnr_vs_exact": psnr(out.double(), reference),
                    "page_faults_per_render": faults[quality] / args.repeat,
                    "reference": f"float64 {ref_method}, full frame, all layers ({ref_s:.1f} s)",
                }
                rows.append(row)
                print(
                    f"{row['size']:>10} {blur:5.0f} {quality:>9} {ms:8.1f} {row['best_ms']:8.1f} "
                    f"{row['speedup']:8.1f}x {row['psnr_vs_exact']:10.1f} dB "
                    f"{row['page_faults_per_render']:8.0f} {row['x_baseline']:8.2f}"
                )
            print(
                f"{'':>10} {'':>5} {'authors':>9} {base_ms:8.1f} {'':>8} {1.0:8.1f}x   "
                f"(reference: {row['reference']})"
            )
    if "ksweep" in args.sections:
        rows += _bench_k_sweep(args)
    if "12mp" in args.sections:
        rows += _bench_large(args)
    if "contention" in args.sections:
        rows += _bench_contention(args)
    speed_end = machine_speed()
    print(f"# machine at the end: {speed_end[0]:.0f} GFLOP/s, {speed_end[1]:.0f} GB/s")
    for row in rows:
        row["machine_gflops_start_end"] = [speed_start[0], speed_end[0]]
        row["machine_copy_gbs_start_end"] = [speed_start[1], speed_end[1]]
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=2)
    if args.chart:
        plot_render([r for r in rows if "section" not in r], args.chart)
        print(f"# chart: {args.chart}")
    return 0


def _interleaved(calls: dict[str, Callable[[], object]], repeat: int) -> dict[str, list[float]]:
    """Seconds per call of each entry, one call of each per round (after one warm-up each),
    so that a slow minute of a shared machine falls on all of them alike."""
    for fn in calls.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeat):
        for name, fn in calls.items():
            times[name] += time_call(fn, repeat=1, warmup=0)
    return times


def _ratio(times: dict[str, list[float]], a: str, b: str) -> float:
    """Median over rounds of the time of ``a`` over that of ``b`` in the same round."""
    return statistics.median(x / y for x, y in zip(times[a], times[b], strict=True))


def _bench_k_sweep(args: argparse.Namespace) -> list[dict]:
    """The default preset at 1024x1536 for K from 10 to 300 px, against today's renderer
    and the exact (float32) reference."""
    baseline = frozen_renderer()
    height, width = 1024, 1536
    image, disp = bench_scene(height, width)
    print(f"\n# K sweep at {height}x{width}, {args.sweep_quality} preset, focus {args.focus}")
    print(f"{'K px':>6} {'ms':>8} {'today ms':>9} {'x today':>8} {'PSNR vs exact':>13}")
    rows = []
    with torch.no_grad():
        for blur in args.k_sweep:
            reference = render(image, disp, args.focus, blur, quality="exact")
            times = _interleaved(
                {
                    "new": lambda b=blur: render(
                        image, disp, args.focus, b, quality=args.sweep_quality
                    ),
                    "today": lambda b=blur: baseline.render(
                        image, disp, args.focus, b, quality=args.sweep_quality
                    ),
                },
                args.sweep_repeat,
            )
            out = render(image, disp, args.focus, blur, quality=args.sweep_quality)
            row = {
                "section": "ksweep",
                "size": f"{height}x{width}",
                "blur": float(blur),
                "quality": args.sweep_quality,
                "ms": 1000 * statistics.median(times["new"]),
                "baseline_ms": 1000 * statistics.median(times["today"]),
                "x_baseline": _ratio(times, "new", "today"),
                "psnr_vs_exact": psnr(out, reference),
            }
            rows.append(row)
            print(
                f"{blur:6.0f} {row['ms']:8.1f} {row['baseline_ms']:9.1f} "
                f"{row['x_baseline']:8.2f} {row['psnr_vs_exact']:10.1f} dB"
            )
    return rows


# Run in a child process by _bench_large: one render of a saved scene, its time and the
# process's peak RSS.
_CHILD = """
import json, resource, sys, time
import numpy as np, torch
torch.set_num_threads(int(sys.argv[5]))
if sys.argv[1] == "today":
    import importlib.util, os
    spec = importlib.util.spec_from_file_location("frozen", os.environ["D2F_FROZEN_RENDERER"])
    frozen = sys.modules["frozen"] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(frozen)
    render = frozen.render
else:
    from d2f_core.rendering import render
scene = np.load(sys.argv[2])
image, disp = torch.from_numpy(scene["image"]), torch.from_numpy(scene["disp"])
def peak_mb():
    # VmHWM starts afresh at exec; ru_maxrss keeps the parent's peak from before it
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
before = peak_mb()
with torch.no_grad():
    start = time.perf_counter()
    out = render(image, disp, float(sys.argv[3]), float(sys.argv[4]), quality=sys.argv[6])
    seconds = time.perf_counter() - start
if len(sys.argv) > 7:
    np.save(sys.argv[7], out.numpy())
print(json.dumps({"s": seconds, "peak_mb": peak_mb(), "before_mb": before}))
"""


def _child_render(
    which: str, scene: str, focus: float, blur: float, threads: int, quality: str, save=None
) -> dict:
    command = [sys.executable, "-c", _CHILD, which, scene, str(focus), str(blur), str(threads)]
    command += [quality] + ([save] if save else [])
    env = dict(os.environ, D2F_FROZEN_RENDERER=str(FROZEN_RENDERER))
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if done.returncode:
        raise RuntimeError(f"render child failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _bench_large(args: argparse.Namespace) -> list[dict]:
    """12 MP (3000x4000) at K = blur_frac x width: today's renderer and this one, each
    render in a fresh process (its peak RSS is the render's), taking turns."""
    height, width = args.large
    blur = args.blur_frac * width
    print(
        f"\n# {height}x{width} at K = {blur:.0f} px, {args.quality[0]} preset, one render per "
        "fresh process (peak RSS includes Python, torch and the inputs), taking turns"
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        image, disp = bench_scene(height, width)
        scene = os.path.join(tmp, "scene.npz")
        np.savez(scene, image=image.numpy(), disp=disp.numpy())
        del image, disp
        quality = args.quality[0]
        runs: dict[str, list[dict]] = {"new": [], "today": []}
        outs = {name: os.path.join(tmp, f"{name}.npy") for name in runs}
        # each renderer against its own exact model (this one draws the hidden surface,
        # today's did not)
        exact = {name: os.path.join(tmp, f"{name}_exact.npy") for name in runs}
        for name in runs:
            _child_render(name, scene, args.focus, blur, args.threads, "exact", exact[name])
        for i in range(args.large_repeat):
            for name in runs:
                save = outs[name] if i == 0 else None
                runs[name].append(
                    _child_render(name, scene, args.focus, blur, args.threads, quality, save)
                )
        print(
            f"{'renderer':>9} {'s':>7} {'peak RSS MB':>12} {'inputs MB':>10} {'PSNR vs exact':>13}"
        )
        for name, got in runs.items():
            row = {
                "section": "12mp",
                "size": f"{height}x{width}",
                "blur": blur,
                "quality": quality,
                "renderer": name,
                "s": statistics.median(r["s"] for r in got),
                "ms_per_mp": 1000 * statistics.median(r["s"] for r in got) / (height * width / 1e6),
                "peak_rss_mb": max(r["peak_mb"] for r in got),
                "rss_before_render_mb": max(r["before_mb"] for r in got),
                "psnr_vs_exact": psnr(
                    torch.from_numpy(np.load(outs[name])), torch.from_numpy(np.load(exact[name]))
                ),
            }
            rows.append(row)
        times = {name: [r["s"] for r in got] for name, got in runs.items()}
        ratio = _ratio(times, "new", "today")
        for row in rows:
            row["x_baseline"] = ratio if row["renderer"] == "new" else 1.0
            print(
                f"{row['renderer']:>9} {row['s']:7.2f} {row['peak_rss_mb']:12.0f} "
                f"{row['rss_before_render_mb']:10.0f} {row['psnr_vs_exact']:10.1f} dB"
            )
        print(f"# new / today: {ratio:.2f} (median of per-round ratios)")
    return rows


_BUSY = "import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end:\n    pass\n"


def _bench_contention(args: argparse.Namespace) -> list[dict]:
    """1 against 2 threads with one busy loop beside the render (a child process on one
    core, which stops by itself after ``--busy-seconds``), this renderer and today's."""
    baseline = frozen_renderer()
    height, width = (int(v) for v in args.contention_size.lower().split("x"))
    image, disp = bench_scene(height, width)
    blur = args.blur_frac * width
    quality = args.quality[0]
    print(
        f"\n# contention: {height}x{width}, {quality} preset, one busy loop beside the render "
        f"(stops by itself after {args.busy_seconds:g} s)"
    )
    threads = torch.get_num_threads()
    busy = subprocess.Popen(
        [sys.executable, "-c", _BUSY.format(seconds=float(args.busy_seconds))],
        stdout=subprocess.DEVNULL,
    )
    try:
        if hasattr(os, "sched_setaffinity"):
            try:
                os.sched_setaffinity(busy.pid, {min(os.sched_getaffinity(0))})
            except OSError:
                pass

        def timed(module, n):
            def call():
                torch.set_num_threads(n)
                module.render(image, disp, args.focus, blur, quality=quality)

            return call

        with torch.no_grad():
            times = _interleaved(
                {
                    "new 1": timed(rendering, 1),
                    "new 2": timed(rendering, 2),
                    "today 1": timed(baseline, 1),
                    "today 2": timed(baseline, 2),
                },
                args.contention_repeat,
            )
        still_busy = busy.poll() is None
    finally:
        busy.kill()
        busy.wait()
        torch.set_num_threads(threads)
    print(f"{'renderer':>9} {'1 thr ms':>9} {'2 thr ms':>9} {'2 / 1':>6}")
    rows = []
    for name in ("new", "today"):
        row = {
            "section": "contention",
            "size": f"{height}x{width}",
            "blur": blur,
            "quality": quality,
            "renderer": name,
            "ms_1_thread": 1000 * statistics.median(times[f"{name} 1"]),
            "ms_2_threads": 1000 * statistics.median(times[f"{name} 2"]),
            "two_over_one": _ratio(times, f"{name} 2", f"{name} 1"),
            "busy_loop_ran_throughout": still_busy,
        }
        rows.append(row)
        print(
            f"{name:>9} {row['ms_1_thread']:9.1f} {row['ms_2_threads']:9.1f} "
            f"{row['two_over_one']:6.2f}"
        )
    if not still_busy:
        print("# the busy loop ended before the last round: raise --busy-seconds")
    return rows


def plot_render(rows: list[dict], path: str) -> None:
    """Median ms against PSNR vs the exact reference, one panel per size: each preset, the
    authors' way, the size's target time and the 45 dB floor (``rows`` as written by
    ``--json``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .charts import log_axis

    sizes = list(dict.fromkeys(r["size"] for r in rows))
    fig, axes = plt.subplots(1, len(sizes), figsize=(4.6 * len(sizes), 4.2), squeeze=False)
    for ax, size in zip(axes[0], sizes, strict=True):
        part = [r for r in rows if r["size"] == size]
        for r in part:
            db = min(r["psnr_vs_exact"], _CHART_TOP_DB)
            ax.plot(r["ms"], db, "o", ms=7)
            label = r["quality"]
            if db < r["psnr_vs_exact"]:  # drawn at the top of the panel
                label += f" ({r['psnr_vs_exact']:.0f} dB)"
            ax.annotate(label, (r["ms"], db), textcoords="offset points", xytext=(5, 4), fontsize=8)
        authors = part[0]["authors_ms"]
        ax.plot(authors, _CHART_TOP_DB, "*", ms=13, color="black")
        ax.annotate(
            "authors' way",
            (authors, _CHART_TOP_DB),
            textcoords="offset points",
            xytext=(-10, -14),
            fontsize=8,
            ha="right",
        )
        ax.axhline(RENDER_MIN_PSNR, color="grey", ls=":", lw=1)
        if size in RENDER_TARGETS_MS:
            target = RENDER_TARGETS_MS[size]
            ax.axvline(target, color="grey", ls="--", lw=1)
            ax.annotate(
                f"{target:g} ms",
                (target, RENDER_MIN_PSNR - 4),
                xytext=(3, 0),
                textcoords="offset points",
                fontsize=8,
                color="grey",
            )
        log_axis(ax.xaxis)
        ax.set_ylim(RENDER_MIN_PSNR - 5, _CHART_TOP_DB + 5)
        ax.set_title(f"{size}, K = {part[0]['blur']:.0f} px", fontsize=9)
        ax.set_xlabel("ms per render (median, log scale)")
        ax.set_ylabel("PSNR vs exact reference (dB)")
        ax.grid(alpha=0.3)
    fig.suptitle(
        "Renderer presets: time against error vs the exact model (dotted: 45 dB floor, "
        "dashed: slider target; authors' way drawn at the top)",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _bench_accuracy(args: argparse.Namespace) -> int:
    from .accuracy import main as accuracy_main

    return int(accuracy_main(args.rest) or 0)


def _bench_depth(args: argparse.Namespace) -> int:
    from .depth_bench import main as depth_main

    return int(depth_main(args.rest) or 0)


def _bench_standing(args: argparse.Namespace) -> int:
    from .standing import main as standing_main

    return int(standing_main(args.rest) or 0)


def _bench_sources(args: argparse.Namespace) -> int:
    from .sources import main as sources_main

    return int(sources_main(args.rest) or 0)


def _bench_peers(args: argparse.Namespace) -> int:
    from .peers import main as peers_main

    return int(peers_main(args.rest) or 0)


def _bench_batch(args: argparse.Namespace) -> int:
    from .batch import main as batch_main

    return int(batch_main(args.rest) or 0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="d2f-bench", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("render", help="renderer ms per frame and PSNR against the exact model")
    p.add_argument("--sizes", nargs="+", default=[f"{h}x{w}" for h, w in RENDER_SIZES])
    p.add_argument("--quality", nargs="+", default=["balanced", "fast", "high", "exact"])
    p.add_argument("--focus", type=float, default=0.6)
    p.add_argument("--blur-frac", type=float, default=69 / 768, help="K as a fraction of width")
    p.add_argument("--repeat", type=int, default=7)
    p.add_argument("--baseline-repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--direct-max-pixels",
        type=int,
        default=512 * 768,
        help="larger frames use a float64 FFT reference (direct float64 takes many minutes)",
    )
    p.add_argument("--sections", nargs="+", choices=RENDER_SECTIONS, default=list(RENDER_SECTIONS))
    p.add_argument("--k-sweep", type=float, nargs="+", default=list(K_SWEEP_PX))
    p.add_argument("--sweep-quality", default="balanced")
    p.add_argument("--sweep-repeat", type=int, default=3)
    p.add_argument("--large", type=int, nargs=2, default=[3000, 4000], metavar=("H", "W"))
    p.add_argument("--large-repeat", type=int, default=2)
    p.add_argument("--contention-size", default="512x768")
    p.add_argument("--contention-repeat", type=int, default=5)
    p.add_argument("--busy-seconds", type=float, default=120.0)
    p.add_argument("--json", help="also write the rows to this JSON file")
    p.add_argument("--chart", help="also draw ms against PSNR to this PNG (needs matplotlib)")
    p.set_defaults(func=_bench_render)
    for name, func, text in (
        ("accuracy", _bench_accuracy, "renderer settings against ground truth"),
        ("depth", _bench_depth, "defocus network's depth on real photos against measured depth"),
        ("peers", _bench_peers, "d2f against other renderers, by category, against ground truth"),
        ("standing", _bench_standing, "whether a depth map puts held-out subjects in front"),
        ("sources", _bench_sources, "each depth source's prepare time, beside its accuracy"),
        ("batch", _bench_batch, "d2f batch photos/s on local workers and Ray, memory at 12 MP"),
    ):
        q = sub.add_parser(name, help=text, add_help=False)
        q.set_defaults(func=func)
    # everything after "accuracy" / "depth" / "peers" (--help included) belongs to that bench
    args, rest = parser.parse_known_args(argv)
    if args.command == "render" and rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    args.rest = rest
    logging.basicConfig(level=logging.WARNING)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
