"""``d2f-bench batch``: photos per second of ``d2f batch`` on 1 and 2 local workers and on a
local Ray cluster, as ratios against the first engine of the same run, with the load average
beside each; the model's load time; the memory of one worker rendering a 12 MP photo.

Each engine renders the same generated library (the bundled samples, resized, cycled) with the
shipped weights, in a fresh ``d2f batch`` process, as a user runs it. ``wall`` photos/s counts
the whole command (process or cluster start, model loads); ``render`` photos/s counts the time
from the first photo's start to the last one's end in the workers, which is what a long run
approaches. The engines run in turn, ``--rounds`` times (this machine's speed drifts from
minute to minute); each figure is the best of its rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..lens import blur_px

#: name -> (engine, workers, threads per worker); the first is the baseline of the ratios.
CONFIGS = {
    "local-1x2": ("local", 1, 2),
    "local-2x1": ("local", 2, 1),
    "local-1x1": ("local", 1, 1),
    "ray-2x1": ("ray", 2, 1),
}
DEFAULT_CONFIGS = ("local-1x2", "local-2x1", "ray-2x1")

_MEMORY_CHILD = """
import resource, sys, time
from d2f_core.cli import main
import torch
torch.set_num_threads(int(sys.argv[1]))
start = time.perf_counter()
code = main(sys.argv[2:])
seconds = time.perf_counter() - start
print("MAXRSS_KB", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, seconds, code)
"""

_LOAD_CHILD = """
import time
t0 = time.perf_counter()
import torch
from d2f_core.pipeline import D2F
t1 = time.perf_counter()
D2F.from_pretrained()
t2 = time.perf_counter()
print("LOAD", t1 - t0, t2 - t1)
"""


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} {five:.2f} {fifteen:.2f}"


def make_library(folder: Path, count: int, size: tuple[int, int]) -> list[Path]:
    """``count`` JPEGs of ``size`` (h, w): the bundled samples, resized and cycled, each with a
    different crop so that no two photos are the same."""
    from PIL import Image

    from ..bundled import sample_photos

    h, w = size
    samples = [Image.open(p).convert("RGB") for p in sample_photos()]
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        img = samples[i % len(samples)]
        sw, sh = img.size
        shift = (i // len(samples)) * 0.03
        box = (int(sw * shift), int(sh * shift), sw - int(sw * shift / 2), sh)
        path = folder / f"photo{i:03d}.jpg"
        img.crop(box).resize((w, h), Image.Resampling.BICUBIC).save(path, quality=92)
        paths.append(path)
    return paths


def _rows(manifest: Path) -> list[dict]:
    with open(manifest, encoding="utf-8") as f:
        return [json.loads(line) for line in f if line.strip()]


def run_engine(
    library: Path, out: Path, engine: str, workers: int, threads: int, blur: float
) -> dict:
    """One ``d2f batch`` run in a fresh process; its figures."""
    cmd = [sys.executable, "-m", "d2f_core.cli", "batch", os.fspath(library), "-o",
           os.fspath(out), "--blur", str(blur), "--engine", engine, "--workers", str(workers),
           "--threads", str(threads), "-q"]  # fmt: skip
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    load_before = _load()
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{engine} run failed ({proc.returncode}): {proc.stderr[-2000:]}")
    rows = [r for r in _rows(out / "manifest.jsonl") if r["status"] == "done"]
    span = max(r["finished"] for r in rows) - min(r["finished"] - r["seconds"] for r in rows)
    return {
        "photos": len(rows),
        "wall_s": wall,
        "wall_pps": len(rows) / wall,
        "render_pps": len(rows) / span,
        "photo_s": float(np.median([r["seconds"] for r in rows])),
        "load_before": load_before,
        "load_after": _load(),
    }


def model_load_seconds() -> tuple[float, float]:
    """(import torch and d2f, ``D2F.from_pretrained()``) seconds in a fresh process."""
    proc = subprocess.run(
        [sys.executable, "-c", _LOAD_CHILD], capture_output=True, text=True, check=True
    )
    line = next(x for x in proc.stdout.splitlines() if x.startswith("LOAD"))
    _, imports, load = line.split()
    return float(imports), float(load)


def worker_memory(
    folder: Path, size: tuple[int, int], blur: float, threads: int
) -> tuple[float, float]:
    """(peak RSS in MiB, seconds) of a process that loads the model and renders one photo of
    ``size``, as a worker does."""
    photo = make_library(folder / "big", 1, size)[0]
    out = folder / "big_bokeh.jpg"
    argv = ["render", os.fspath(photo), "-o", os.fspath(out), "--blur", str(blur), "-q"]
    proc = subprocess.run([sys.executable, "-c", _MEMORY_CHILD, str(threads), *argv],
                          capture_output=True, text=True)  # fmt: skip
    line = next((x for x in proc.stdout.splitlines() if x.startswith("MAXRSS_KB")), None)
    if line is None or not line.endswith(" 0"):
        raise RuntimeError(f"the 12 MP render failed: {proc.stderr[-2000:]}")
    _, kib, seconds, _ = line.split()
    return int(kib) / 1024.0, float(seconds)


def _size(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="d2f-bench batch", description=__doc__)
    parser.add_argument("--photos", type=int, default=12, help="photos in the library")
    parser.add_argument("--size", type=_size, default=(768, 1024), metavar="HxW")
    parser.add_argument("--blur", type=float, default=40.0)
    parser.add_argument(
        "--configs", nargs="+", choices=sorted(CONFIGS), default=list(DEFAULT_CONFIGS),
        help="engine-workers x threads; the first is the baseline",
    )  # fmt: skip
    parser.add_argument("--memory-size", type=_size, default=(3000, 4000), metavar="HxW",
                        help="the photo of the memory figure (default 12 MP)")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=2, help="runs of each engine, in turn")
    parser.add_argument("--no-memory", action="store_true")
    parser.add_argument("--json", help="also write the figures to this JSON file")
    args = parser.parse_args(argv)

    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    h, w = args.size
    print(f"d2f-bench batch: {args.photos} photos of {w}x{h}, K = {args.blur:g} px, "
          f"{cpus} CPUs; load average (1, 5, 15 min) beside each figure")  # fmt: skip
    figures: dict = {"photos": args.photos, "size": [h, w], "cpus": cpus, "engines": {}}
    with tempfile.TemporaryDirectory(prefix="d2f-bench-batch-") as tmp:
        folder = Path(tmp)
        library = folder / "library"
        make_library(library, args.photos, args.size)
        imports, load = model_load_seconds()
        print(f"model load per worker: {load:.2f} s (+ {imports:.2f} s importing torch and d2f)"
              f"   load {_load()}")  # fmt: skip
        figures.update(model_load_s=load, import_s=imports)
        runs: dict[str, list[dict]] = {name: [] for name in args.configs}
        for _ in range(args.rounds):
            for name in args.configs:
                engine, workers, threads = CONFIGS[name]
                out = folder / f"out-{name}"
                try:
                    runs[name].append(run_engine(library, out, engine, workers, threads, args.blur))
                except RuntimeError as exc:
                    print(f"{name}: failed: {exc}")
                finally:
                    shutil.rmtree(out, ignore_errors=True)
        print(f"{'engine':<11}{'wall ph/s':>10}{'ratio':>7}{'render ph/s':>13}{'ratio':>7}"
              f"{'s/photo':>9}   load before -> after (each round)")  # fmt: skip
        base = None
        for name, rows in runs.items():
            if not rows:
                continue
            best = {k: max(r[k] for r in rows) for k in ("wall_pps", "render_pps")}
            best["photo_s"] = min(r["photo_s"] for r in rows)
            base = base or best
            figures["engines"][name] = {**best, "runs": rows}
            loads = "; ".join(f"{r['load_before']} -> {r['load_after']}" for r in rows)
            wall, render = best["wall_pps"], best["render_pps"]
            print(f"{name:<11}{wall:>10.3f}{wall / base['wall_pps']:>7.2f}"
                  f"{render:>13.3f}{render / base['render_pps']:>7.2f}{best['photo_s']:>9.2f}"
                  f"   {loads}")  # fmt: skip
        if not args.no_memory:
            mh, mw = args.memory_size
            blur = blur_px(1.4, max(mh, mw))  # the app's default aperture
            load_before = _load()
            mib, seconds = worker_memory(folder, args.memory_size, blur, threads=1)
            figures.update(memory_mib=mib, memory_size=[mh, mw], memory_photo_s=seconds)
            print(f"one worker at {mw}x{mh} ({mw * mh / 1e6:.0f} MP, K = {blur:.0f} px, 1 "
                  f"thread): peak RSS {mib:.0f} MiB, {seconds:.1f} s for the photo (model load "
                  f"included)   load {load_before} -> {_load()}")  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
