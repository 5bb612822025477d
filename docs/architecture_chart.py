"""Draw a photo's way through the package: ``assets/charts/architecture.png``.

    python docs/architecture_chart.py [--out PATH]

One row per step, top to bottom in the order a render runs (load, depth source, networks,
plan, blur, composite, fusion, save). Left of the dashed line, what the public API offers for
the step (``from d2f_core import ...``); right of it, the module that holds the step and the
equation of the D2F paper it implements (``../shared/D2F_NOTES.md`` numbers the steps).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyBboxPatch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

#: (step, public entry, module(s), equation), in the order a render runs
STEPS = [
    (
        "load",
        "load_image, load_photo",
        "io/image.py, formats.py, embedded.py",
        "I_hr, H x W x 3 in [0, 1]",
    ),
    (
        "depth source",
        "depth_map, D2F.prepare(depth=)",
        "depth/sources.py, refine.py, subject.py",
        "step 2: disparity d (1 = near), D = |d - f|",
    ),
    (
        "networks",
        "D2F.prepare",
        "networks.py, pipeline/model.py",
        "steps 1-3: I_lr = resize(I_hr), d = f_d(I_lr), R0 = f_r(I_lr)",
    ),
    (
        "plan",
        "D2F.render, render, render_bokeh",
        "rendering/radiance.py, plan.py,\nadaptive.py, schedule.py, kernels.py",
        "step 4: R = M_h a I^b + (1 - M_h) R0;\nM_l = 0.5 + 0.5 tanh(g (1/(L-1) - |D - l/(L-1)|))",
    ),
    (
        "blur",
        "(inside render)",
        "rendering/blur.py, hidden.py, tiled.py",
        "K_l * (M_l X), kernel K(s_l) of the growing schedule",
    ),
    (
        "composite",
        "(inside render)",
        "rendering/composite.py",
        "step 5: acc = acc (1 - K_l M_l) + K_l (M_l X);\nB_lr = f_l(R I, D) / f_l(R, D)",
    ),
    (
        "fusion",
        "D2F.render",
        "pipeline/fusion.py (f_p: networks.py)",
        "step 6: B_hr = M_s I_hr + (1 - M_s) upsample(B_lr)",
    ),
    ("save", "save_image", "io/save.py", "Result.bokeh -> PNG / JPEG"),
]


def draw(out: Path) -> None:
    rows = len(STEPS)
    fig, ax = plt.subplots(figsize=(13.5, 0.95 * rows + 1.2), dpi=110)
    ax.set_xlim(0, 13.5)
    ax.set_ylim(-0.2, rows + 0.9)
    ax.axis("off")
    columns = [(0.2, "step"), (1.95, "public API (from d2f_core import ...)"),
               (5.15, "module (d2f_core/...)"), (8.55, "D2F equation")]  # fmt: skip
    for x, title in columns:
        ax.text(x, rows + 0.45, title, fontsize=10, fontweight="bold", va="center")
    for i, (step, public, module, equation) in enumerate(STEPS):
        y = rows - 1 - i + 0.5
        ax.add_patch(
            FancyBboxPatch(
                (0.2, y - 0.3),
                1.5,
                0.6,
                boxstyle="round,pad=0.02",
                facecolor="#dce9f5",
                edgecolor="#3b6ea5",
            )  # fmt: skip
        )
        ax.text(0.95, y, step, ha="center", va="center", fontsize=10)
        if i < rows - 1:
            ax.annotate("", xy=(0.95, y - 0.7), xytext=(0.95, y - 0.3),
                        arrowprops={"arrowstyle": "->", "color": "#3b6ea5"})  # fmt: skip
        ax.text(1.95, y, public, va="center", fontsize=8.5, family="monospace")
        ax.text(5.15, y, module, va="center", fontsize=8.5, family="monospace")
        ax.text(8.55, y, equation, va="center", fontsize=8.5)
    ax.plot([4.95, 4.95], [-0.1, rows + 0.75], ls="--", color="#b03030", lw=1.2)
    ax.text(4.9, -0.1, "public API ends here", color="#b03030", fontsize=8.5, ha="right")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "assets" / "charts" / "architecture.png")
    args = parser.parse_args(argv)
    draw(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
