"""``d2f-bench sources``: what each depth source costs, next to what it gives.

Times :meth:`D2F.prepare` of one photo from each depth source (``d2f``, ``scene``, and any
``transformers:MODEL`` or ``file:PATH`` asked for), in turns, round by round, at each size
(default 768x1024 and 12 MP), and prints each source's median time and its ratio against the
first source measured in the same rounds, with the load average. ``--chart`` draws time per
photo against accuracy, taking each source's accuracy from files the accuracy benches wrote:
``--depth-json`` (``d2f-bench depth --source ... --json``: mean Spearman on the 12 measured
photos) and ``--eval-csv SOURCE=FILE`` (``d2f-eval``'s CSV: bokeh PSNR on a held-out set).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["format_times", "main", "time_sources"]

DEFAULT_SIZES = ((768, 1024), (3000, 4000))


def _load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def _photo(size: tuple[int, int]) -> np.ndarray:
    """A bundled sample resized to ``size`` (a real photo: the teachers see a scene)."""
    from PIL import Image

    from ..bundled import sample_photos
    from ..io import load_image

    image = load_image(sample_photos()[0])
    u8 = Image.fromarray((image * 255 + 0.5).astype(np.uint8))
    h, w = size
    return np.asarray(u8.resize((w, h), Image.BICUBIC), dtype=np.float32) / 255.0


def time_sources(
    model: Any,
    sources: Sequence[str],
    sizes: Sequence[tuple[int, int]] = DEFAULT_SIZES,
    repeat: int = 5,
) -> list[dict[str, Any]]:
    """One row per size and source: the median, best and all times (ms) of ``prepare``, the
    ratio of the median to the first source's, the load average before and after. Each
    source runs once first (loading its weights), then ``repeat`` rounds take them in turn."""
    rows = []
    for size in sizes:
        image = _photo(size)
        times: dict[str, list[float]] = {s: [] for s in sources}
        outputs = {}
        for source in sources:  # warm-up: weights loaded, the first call's allocations
            outputs[source] = model.prepare(image, depth=source).disparity_output
        load_start = _load()
        for _ in range(repeat):
            for source in sources:
                t0 = time.perf_counter()
                model.prepare(image, depth=source)
                times[source].append((time.perf_counter() - t0) * 1000)
        load_end = _load()
        base = statistics.median(times[sources[0]])
        for source in sources:
            med = statistics.median(times[source])
            rows.append(
                {
                    "size": f"{size[0]}x{size[1]}",
                    "source": source,
                    "output": outputs[source],
                    "median_ms": med,
                    "best_ms": min(times[source]),
                    "times_ms": times[source],
                    "ratio": med / base,
                    "load": [load_start, load_end],
                }
            )
    return rows


def format_times(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of :func:`time_sources`' rows."""
    lines = [
        "| size | source | median ms | best ms | ratio to the first | load (start, end) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['source']} | {r['median_ms']:.0f} | {r['best_ms']:.0f} | "
            f"{r['ratio']:.2f}x | {r['load'][0]:.2f}, {r['load'][1]:.2f} |"
        )
    return "\n".join(lines)


def accuracy_of(
    depth_json: str | Path | None, eval_csv: dict[str, str]
) -> dict[str, dict[str, float]]:
    """Each source's accuracy from the accuracy benches' files: ``spearman`` (the 12
    measured photos' mean, from ``d2f-bench depth --json``'s column ``source NAME``) and
    ``psnr`` (the mean of the ``psnr`` column of ``d2f-eval``'s CSV)."""
    out: dict[str, dict[str, float]] = {}
    if depth_json is not None:
        summary = json.loads(Path(depth_json).read_text())["summary"]
        for column, scores in summary.items():
            if column.startswith("source "):
                name = column[len("source ") :]
                out.setdefault(name, {})["spearman"] = float(scores["mean_spearman"])
    for name, path in eval_csv.items():
        with open(path, newline="") as fh:
            values = [float(row["psnr"]) for row in csv.DictReader(fh) if row.get("psnr")]
        if not values:
            raise ValueError(f"{path}: no psnr column in this d2f-eval CSV")
        out.setdefault(name, {})["psnr"] = float(np.mean(values))
    return out


def draw_chart(
    rows: Sequence[dict[str, Any]], accuracy: dict[str, dict[str, float]], path: str | Path
) -> Path:
    """Time per photo at the first size against each accuracy measure, one panel each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    size = rows[0]["size"]
    at = {r["source"]: r["median_ms"] for r in rows if r["size"] == size}
    panels = [
        ("spearman", "mean Spearman, 12 measured-depth photos"),
        ("psnr", "bokeh PSNR (dB), generated held-out set"),
    ]
    panels = [p for p in panels if any(p[0] in a for a in accuracy.values())]
    if not panels:
        raise ValueError("no accuracy figures to draw: give --depth-json or --eval-csv")
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.0), squeeze=False)
    for ax, (key, label) in zip(axes[0], panels, strict=True):
        for source, ms in at.items():
            value = accuracy.get(source, {}).get(key)
            if value is None:
                continue
            ax.scatter([ms], [value], s=60)
            ax.annotate(source, (ms, value), textcoords="offset points", xytext=(6, 4))
        ax.margins(x=0.2, y=0.2)
        ax.set_xlabel(f"prepare time per {size} photo (ms, median)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle("Depth sources: time against accuracy")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be HxW, got {text!r}") from None
    if h < 16 or w < 16:
        raise argparse.ArgumentTypeError(f"size must be at least 16x16, got {text!r}")
    return h, w


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="d2f-bench sources", description=__doc__.split("\n\n")[0])
    p.add_argument("--sources", nargs="+", default=["d2f", "scene"], help="depth sources")
    p.add_argument("--sizes", nargs="+", type=_size, default=list(DEFAULT_SIZES))
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--weights", default=None, help="checkpoint (default: the shipped weights)")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    p.add_argument("--chart", type=Path, default=None, help="draw time against accuracy here")
    p.add_argument("--depth-json", type=Path, default=None, help="d2f-bench depth --json file")
    p.add_argument(
        "--eval-csv", action="append", default=[], metavar="SOURCE=FILE",
        help="d2f-eval's CSV of a source's renders",
    )  # fmt: skip
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error("--repeat must be >= 1")
    from ..depth.sources import parse_source
    from ..pipeline import D2F

    try:
        for source in args.sources:
            parse_source(source)
        evals = dict(spec.split("=", 1) for spec in args.eval_csv if "=" in spec)
        if len(evals) != len(args.eval_csv):
            raise ValueError("--eval-csv takes SOURCE=FILE")
        torch.set_num_threads(args.threads)
        model = D2F.from_pretrained(args.weights)
        rows = time_sources(model, args.sources, args.sizes, args.repeat)
    except (ValueError, FileNotFoundError) as exc:
        print(f"d2f-bench sources: error: {exc}", file=sys.stderr)
        return 1
    print(f"D2F.prepare per photo, {args.repeat} rounds in turns, {args.threads} thread(s)")
    print(format_times(rows))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1))
    if args.chart is not None:
        try:
            accuracy = accuracy_of(args.depth_json, evals)
            print(f"chart: {draw_chart(rows, accuracy, args.chart)}")
        except (ValueError, FileNotFoundError, KeyError) as exc:
            print(f"d2f-bench sources: error: --chart: {exc}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
