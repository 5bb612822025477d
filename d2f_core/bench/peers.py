"""d2f against other renderers, by where renderers fail: ``d2f-bench peers``.

On seeded generated layered scenes (:mod:`d2f_core.train.synth`) with their accumulation-buffer
thin-lens ground truth (the cases of ``d2f-bench accuracy``, cached alike), every method gets
the pinhole photo and the exact disparity, and is scored by PSNR:

* overall, split by where the focus is: on the main subject (occluders in front of it are
  few; the background blurs behind a sharp edge) or on the farthest object (nearer objects
  blur over a sharp region);
* near depth edges: within 6 px of a disparity jump, on the near side and on the far side
  of it separately;
* on thin structures (the scenes' fences and striped blobs, grown by ``K / 4``);
* around HDR highlights (grown by ``K / 2``).

Methods:

* ``d2f renderer``: :func:`rendering.render` at the photo's size, default options;
* ``d2f pipeline``: ``D2F.prepare(photo, disparity=...)`` and ``D2F.render`` with the shipped
  weights, as the app and the CLI run with a given map;
* ``gather``: a depth-aware per-pixel gather of the "scatter-as-gather" kind, written here:
  each pixel averages the neighbours whose own CoC disc reaches it, each weighted by the
  inverse of its disc's area (no occlusion model);
* ``Blender Defocus``: Blender's compositor Defocus node (circular bokeh, no z-buffer: the
  Z input is the CoC radius, 1 = ``z_scale`` px), run headless when ``blender`` is on
  ``PATH``; skipped with a note otherwise.

Times are medians of interleaved rounds, reported as ratios against ``d2f renderer`` in the
same run; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..rendering import render
from .cases import Case, dilate, jump_pixels, load_cases, masked_metrics, reach_px

__all__ = ["CATEGORIES", "edge_sides", "gather_render", "main", "run_peers", "thin_band"]

logger = logging.getLogger(__name__)

#: Report columns: (name, band key or None for the whole frame, focus mode or None for both).
CATEGORIES: tuple[tuple[str, str | None, str | None], ...] = (
    ("all", None, None),
    ("focus near: all", None, "subject"),
    ("focus far: all", None, "far"),
    ("edge, near side", "edge_near", None),
    ("edge, far side", "edge_far", None),
    ("thin structures", "thin", None),
    ("highlights", "lights", None),
)
EDGE_PX = 6


def gather_render(image: torch.Tensor, disparity: torch.Tensor, focus: float, blur: float):
    """Depth-aware scatter-as-gather: each output pixel averages the neighbours whose own CoC
    disc (diameter ``blur * |d - focus|``, antialiased by half a pixel) covers it, weighted
    by ``1 / disc area``; no occlusion model. Vectorised over the offsets of the largest
    disc.

    Shape: image (1, 3, H, W), disparity (1, 1, H, W) -> (1, 3, H, W).
    """
    radius = blur * (disparity - focus).abs() / 2
    reach = int(math.ceil(float(radius.max()) + 0.5))
    h, w = disparity.shape[-2:]
    pad = (reach, reach, reach, reach)
    img_p = F.pad(image, pad)
    rad_p = F.pad(radius, pad, value=-1.0)  # outside the frame: no neighbour
    area = 1.0 / (math.pi * rad_p.clamp(min=0.5) ** 2)
    num = torch.zeros_like(image)
    den = torch.zeros_like(disparity)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            dist = math.hypot(dy, dx)
            if dist > reach:
                continue
            ys, xs = slice(reach + dy, reach + dy + h), slice(reach + dx, reach + dx + w)
            r = rad_p[..., ys, xs]
            weight = (r + 0.5 - dist).clamp(0, 1) * (r >= 0) * area[..., ys, xs]
            num += weight * img_p[..., ys, xs]
            den += weight
    return (num / den.clamp(min=1e-12)).clamp(0, 1)


def edge_sides(disparity: np.ndarray, width: int = EDGE_PX, jump: float = 0.02):
    """Pixels within ``width`` px of a disparity jump, split into the near side and the far
    side of it (the pixel's disparity nearer the window's largest or smallest value).

    Shape: ``(H, W) -> ((H, W), (H, W))`` bool.
    """
    d = disparity.astype(np.float32)
    band = dilate(jump_pixels(d, jump), width)
    t = torch.from_numpy(d)[None, None]
    reach = width + 1  # a band pixel's window holds both sides of its edge
    hi = F.max_pool2d(t, 2 * reach + 1, 1, reach)[0, 0].numpy()
    lo = -F.max_pool2d(-t, 2 * reach + 1, 1, reach)[0, 0].numpy()
    near = d - lo > hi - d
    return band & near, band & ~near


def thin_band(case: Case) -> np.ndarray:
    """Where the scene's thin structures are (fence and striped layers), grown by ``K / 4``;
    rebuilt from the case's seed (scenes are deterministic)."""
    from ..train.synth import make_scene

    scene = make_scene(case.size, seed=case.seed, margin=math.ceil(case.blur / 2) + 2)
    h, w = case.size
    mask = np.zeros((h, w), bool)
    for layer in scene.layers:
        if layer.kind not in ("fence", "stripes"):
            continue
        lh, lw = layer.shape
        y0, x0 = max(0, layer.top), max(0, layer.left)
        y1, x1 = min(h, layer.top + lh), min(w, layer.left + lw)
        if y1 <= y0 or x1 <= x0:
            continue
        crop = layer.alpha[y0 - layer.top : y1 - layer.top, x0 - layer.left : x1 - layer.left]
        mask[y0:y1, x0:x1] |= crop > 0.5
    return dilate(mask, reach_px(case.blur, 4, 24))


_BLENDER_SCRIPT = """
import bpy, sys
argv = sys.argv[sys.argv.index("--") + 1:]
src, coc, out, rmax = argv[0], argv[1], argv[2], float(argv[3])
scene = bpy.context.scene
scene.use_nodes = True
tree = scene.node_tree
for n in list(tree.nodes):
    tree.nodes.remove(n)
img = tree.nodes.new("CompositorNodeImage"); img.image = bpy.data.images.load(src)
z = tree.nodes.new("CompositorNodeImage"); z.image = bpy.data.images.load(coc)
z.image.colorspace_settings.name = "Non-Color"
defocus = tree.nodes.new("CompositorNodeDefocus")
# without a z-buffer the Z input is the blur radius: 1 (white) is z_scale px
defocus.bokeh = "CIRCLE"; defocus.use_zbuffer = False; defocus.use_gamma_correction = False
defocus.z_scale = rmax; defocus.blur_max = rmax; defocus.threshold = 1.0  # its default
comp = tree.nodes.new("CompositorNodeComposite")
tree.links.new(img.outputs[0], defocus.inputs[0])
tree.links.new(z.outputs[0], defocus.inputs[1])
tree.links.new(defocus.outputs[0], comp.inputs[0])
scene.render.resolution_x, scene.render.resolution_y = img.image.size[:]
scene.render.resolution_percentage = 100
scene.view_settings.view_transform = "Standard"  # not Filmic: pixels in = pixels out
scene.view_settings.look = "None"
scene.view_settings.exposure = 0.0
scene.view_settings.gamma = 1.0
scene.render.image_settings.file_format = "PNG"
scene.render.filepath = out
bpy.ops.render.render(write_still=True)
"""


def blender_available() -> str | None:
    """Path of ``blender`` on ``PATH``, or ``None``."""
    return shutil.which("blender")


def blender_render(image: np.ndarray, disparity: np.ndarray, focus: float, blur: float):
    """Blender's Defocus node on ``image`` (``H x W x 3`` in [0, 1]) with the CoC radius as
    its Z input (a 16-bit PNG of radius / largest radius). Needs ``blender`` on ``PATH``.

    Shape: ``(H, W, 3) -> (H, W, 3)``.
    """
    from PIL import Image

    exe = blender_available()
    if exe is None:
        raise RuntimeError("blender is not on PATH")
    radius = blur * np.abs(disparity - focus) / 2
    rmax = max(float(radius.max()), 1e-3)
    with tempfile.TemporaryDirectory() as tmp:
        src, coc, out = Path(tmp, "in.png"), Path(tmp, "coc.png"), Path(tmp, "out.png")
        Image.fromarray((np.clip(image, 0, 1) * 255).round().astype(np.uint8)).save(src)
        Image.fromarray(np.round(radius / rmax * 65535).astype(np.uint16)).save(coc)
        script = Path(tmp, "defocus.py")
        script.write_text(_BLENDER_SCRIPT)
        subprocess.run(
            [exe, "-b", "--factory-startup", "-P", str(script), "--",
             str(src), str(coc), str(out), repr(rmax)],
            check=True, capture_output=True, timeout=600,
        )  # fmt: skip
        with Image.open(out) as im:
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0


def _methods(weights: str | Path | None, with_blender: bool) -> dict[str, Callable]:
    from ..pipeline import D2F

    model = D2F.from_pretrained(weights)

    def renderer(case: Case, hidden: bool = True) -> np.ndarray:
        img, disp = case.tensors()
        out = render(img, disp, case.focus, case.blur, hidden=hidden)
        return out[0].permute(1, 2, 0).numpy()

    def pipeline(case: Case, hidden: bool = True) -> np.ndarray:
        scene = model.prepare(case.image, disparity=case.disparity)
        return model.render(scene, case.focus, case.blur, hidden=hidden).bokeh

    def gather(case: Case) -> np.ndarray:
        img, disp = case.tensors()
        return gather_render(img, disp, case.focus, case.blur)[0].permute(1, 2, 0).numpy()

    methods = {
        "d2f renderer": renderer,
        "d2f renderer, no hidden surface": lambda c: renderer(c, hidden=False),
        "d2f pipeline": pipeline,
        "d2f pipeline, no hidden surface": lambda c: pipeline(c, hidden=False),
        "gather": gather,
    }
    if with_blender:
        methods["Blender Defocus"] = lambda c: blender_render(c.image, c.disparity, c.focus, c.blur)
    return methods


def run_peers(
    cases: Sequence[Case],
    *,
    weights: str | Path | None = None,
    repeat: int = 3,
    blender: bool | None = None,
) -> dict[str, Any]:
    """Score and time every method on every case; returns rows and notes."""
    with_blender = blender_available() is not None if blender is None else blender
    notes = [] if with_blender else ["Blender Defocus skipped: blender is not on PATH"]
    methods = _methods(weights, with_blender)
    rows = []
    with torch.no_grad():
        for case in cases:
            near, far = edge_sides(case.disparity)
            bands = {
                "edge_near": near,
                "edge_far": far,
                "thin": thin_band(case),
                "lights": case.bands.get("lights", np.zeros(case.size, bool)),
            }
            outputs = {name: fn(case) for name, fn in methods.items()}  # also the warm-up
            times: dict[str, list[float]] = {name: [] for name in methods}
            for _ in range(repeat):
                for name, fn in methods.items():
                    if name == "Blender Defocus" and times[name]:
                        continue  # one timed run: it starts a process per call
                    t0 = time.perf_counter()
                    fn(case)
                    times[name].append(1000.0 * (time.perf_counter() - t0))
            for name, out in outputs.items():
                metrics = masked_metrics(out, case.target, bands)
                rows.append(
                    {"method": name, "case": case.key, "mode": case.mode, "blur": case.blur,
                     "size": f"{case.size[0]}x{case.size[1]}", "ms": statistics.median(times[name])}
                    | metrics
                )  # fmt: skip
            logger.info("peers: %s done", case.key)
    return {"rows": rows, "notes": notes}


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Mean PSNR per method and category (:data:`CATEGORIES`) and the time ratio against
    ``d2f renderer`` (mean over cases of the per-case ratio)."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    base = {r["case"]: r["ms"] for r in rows if r["method"] == "d2f renderer"}
    out: dict[str, dict[str, float | None]] = {}
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        entry: dict[str, float | None] = {}
        for name, band, mode in CATEGORIES:
            key = "psnr" if band is None else f"psnr_{band}"
            vals = [r[key] for r in mine if (mode is None or r["mode"] == mode)]
            vals = [v for v in vals if v is not None]
            entry[name] = float(np.mean(vals)) if vals else None
        ratios = [r["ms"] / base[r["case"]] for r in mine if base.get(r["case"])]
        entry["time ratio"] = float(np.mean(ratios)) if ratios else None
        out[m] = entry
    return out


def format_table(table: dict[str, dict[str, float | None]]) -> str:
    cols = [name for name, _, _ in CATEGORIES] + ["time ratio"]
    lines = ["| method | " + " | ".join(cols) + " |", "|" + " --- |" * (len(cols) + 1)]
    for method, entry in table.items():
        cells = []
        for c in cols:
            v = entry.get(c)
            cells.append("-" if v is None else (f"{v:.2f}x" if c == "time ratio" else f"{v:.2f}"))
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="d2f-bench peers", description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["384x576"], help="HxW of the scenes")
    p.add_argument("--seeds", nargs="+", type=int, default=[11, 12, 13, 14])
    p.add_argument("--k-fracs", nargs="+", type=float, default=[0.02, 0.06, 0.1],
                   help="K as a fraction of the width")  # fmt: skip
    p.add_argument("--samples", type=int, default=128, help="aperture samples of the truth")
    p.add_argument("--cache", default="runs/acc_cache", help="ground-truth cache folder")
    p.add_argument("--weights", default=None, help="D2F checkpoint of 'd2f pipeline'")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--no-blender", action="store_true", help="skip Blender even if present")
    p.add_argument("--json", default=None, help="write rows and the table here")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
    cases = load_cases(sizes, args.seeds, args.k_fracs, samples=args.samples, cache=args.cache)
    result = run_peers(
        cases, weights=args.weights, repeat=args.repeat, blender=False if args.no_blender else None
    )
    table = summary(result["rows"])
    print(
        f"d2f-bench peers: {len(cases)} generated scenes ({', '.join(args.sizes)}), "
        f"K = {', '.join(f'{k:g}' for k in args.k_fracs)} x width, PSNR (dB) against the "
        f"thin-lens truth, {args.threads} torch threads"
    )
    print(format_table(table))
    for note in result["notes"]:
        print(note)
    if args.json:
        Path(args.json).write_text(json.dumps({"table": table} | result, indent=1))
    return 0
