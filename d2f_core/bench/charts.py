"""The accuracy bench's charts: time against PSNR of the renderer settings (``d2f-bench
accuracy --chart``) and of the whole pipeline (``--e2e``).
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .cases import PAPER_GPU_SECONDS

__all__ = [
    "log_axis",
]


_AXIS_COLOURS = {
    "default": "black",
    "layers": "tab:blue",
    "schedule": "tab:olive",
    "kernel": "tab:cyan",
    "resolution": "tab:green",
    "method": "tab:brown",
    "order": "tab:red",
    "placement": "tab:gray",
    "hdr": "tab:pink",
    "paper": "tab:red",
    "combined": "tab:purple",
    "adaptive": "tab:orange",
}


def log_axis(axis) -> None:
    """Log x scale labelled with plain numbers: at 1-9 x 10^k over less than a decade (so a
    narrow range still gets ticks), at 1, 2, 5 x 10^k over more."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    axis.axes.set_xscale("log")
    lo, hi = axis.axes.get_xlim()
    subs = tuple(range(1, 10)) if hi < 10 * lo else (1.0, 2.0, 5.0)
    axis.set_major_locator(LogLocator(base=10, subs=subs))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def plot_accuracy(summary: Sequence[dict[str, Any]], path: Path, title: str) -> None:
    """Time against PSNR per resolution, Pareto front, paper and default marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = sorted({e["size"] for e in summary}, key=lambda s: int(s.split("x")[0]))
    fig, axes = plt.subplots(
        1, len(sizes), figsize=(max(7.0, 5.2 * len(sizes)), 4.8), squeeze=False
    )
    for ax, size in zip(axes[0], sizes, strict=True):
        rows = [e for e in summary if e["size"] == size and e["axis"] != "baseline"]
        for e in rows:
            marker, ms = "o", 5
            if e["setting"] == "paper":
                marker, ms = "*", 15
            elif e["setting"] == "default":
                marker, ms = "D", 8
            elif e["axis"] == "adaptive":
                marker, ms = "^", 9
            ax.plot(
                e["ms"],
                e["psnr"],
                marker=marker,
                ms=ms,
                ls="none",
                color=_AXIS_COLOURS.get(e["axis"], "grey"),
                mec="black" if marker != "o" else "none",
                zorder=3,
            )
            if e["setting"] in ("paper", "default", "adaptive") or (
                e.get("pareto") and e["axis"] not in ("adaptive", "default")
            ):
                ax.annotate(
                    e["setting"],
                    (e["ms"], e["psnr"]),
                    textcoords="offset points",
                    xytext=(4, 3),
                    fontsize=7,
                )
        front = sorted((e for e in rows if e.get("pareto")), key=lambda e: e["ms"])
        if front:
            ax.step(
                [e["ms"] for e in front],
                [e["psnr"] for e in front],
                where="post",
                color="grey",
                lw=1,
                ls="--",
                zorder=2,
                label="Pareto front",
            )
        base = [e for e in summary if e["size"] == size and e["axis"] == "baseline"]
        if base:
            ax.axhline(base[0]["psnr"], color="grey", lw=0.8, ls=":", label="input (no blur)")
        log_axis(ax.xaxis)
        ax.set_xlabel("ms per frame (median, log scale)")
        ax.set_ylabel("PSNR vs thin-lens ground truth (dB)")
        ax.set_title(f"{size}, {rows[0]['cases'] if rows else 0} scene/K cases", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    handles = [
        plt.Line2D([], [], marker="*", ms=12, ls="none", color="tab:red", mec="black"),
        plt.Line2D([], [], marker="D", ms=7, ls="none", color="black"),
        plt.Line2D([], [], marker="^", ms=8, ls="none", color="tab:orange", mec="black"),
        plt.Line2D([], [], color="grey", ls="--"),
    ]
    labels = ["paper configuration", "default", "adaptive", "Pareto front"]
    for axis in ("layers", "resolution", "order", "placement", "combined"):
        handles.append(plt.Line2D([], [], marker="o", ls="none", color=_AXIS_COLOURS[axis]))
        labels.append(axis)
    fig.legend(
        handles, labels, loc="lower center", ncol=min(8, 4 * len(sizes)), fontsize=8, frameon=False
    )
    fig.suptitle(textwrap.fill(title, 60 * len(sizes)), fontsize=9)
    fig.tight_layout(rect=(0, 0.08 if len(sizes) > 1 else 0.12, 1, 0.93))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_e2e(rows: Sequence[dict[str, Any]], path: Path, title: str) -> None:
    """Time (prepare + render) against PSNR per series, one point per pass scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    colours = {"lite": "tab:blue", "lite-ctx": "tab:blue", "resnext50": "tab:red"}
    colours["given disparity"] = "tab:green"
    for series in dict.fromkeys(r["series"] for r in rows):
        pts = []
        for scale in sorted({r["scale"] for r in rows if r["series"] == series}):
            group = [r for r in rows if r["series"] == series and r["scale"] == scale]
            pts.append(
                (
                    float(np.mean([r["ms"] for r in group])),
                    float(np.mean([r["psnr"] for r in group])),
                    scale,
                )
            )
        ax.plot(
            [p[0] / 1000 for p in pts],
            [p[1] for p in pts],
            marker="o",
            color=colours.get(series, "grey"),
            label=series,
        )
        for t, q, scale in pts:
            ax.annotate(
                f"x{scale:g}", (t / 1000, q), textcoords="offset points", xytext=(4, 3), fontsize=7
            )
    ax.axvline(PAPER_GPU_SECONDS, color="black", lw=0.8, ls=":")
    ax.text(
        PAPER_GPU_SECONDS,
        ax.get_ylim()[0],
        " paper: 0.58 s (GTX 1080 GPU, 1024x1536)",
        rotation=90,
        va="bottom",
        ha="right",
        fontsize=7,
    )
    log_axis(ax.xaxis)
    ax.set_xlabel("prepare + render, s per photo (median, CPU, log scale)")
    ax.set_ylabel("PSNR vs thin-lens ground truth (dB)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, title="defocus network (x = low-res pass scale)", title_fontsize=8)
    ax.set_title(textwrap.fill(title, 90), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
