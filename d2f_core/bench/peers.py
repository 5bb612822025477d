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

The same rows are also broken down by ``K`` (``--k-px`` gives it in px) and by what the
scene holds (:func:`scene_category`: plain occlusion, thin structures, highlights, or both),
overall and in the depth-edge band of ``d2f-bench accuracy`` (disparity jumps grown by
``clamp(K / 4, 2, 24)`` px).

Methods:

* ``d2f``: :func:`rendering.adaptive.render_adaptive` at the photo's size with the default
  budget (``"balanced"``), the settings ``D2F.render`` picks for a pass at the photo's size;
* ``d2f renderer``: :func:`rendering.render` at the photo's size, default options;
* ``d2f pipeline``: ``D2F.prepare(photo, disparity=...)`` and ``D2F.render`` with the shipped
  weights, as the app and the CLI run with a given map;
* ``gather``: a depth-aware per-pixel gather of the "scatter-as-gather" kind, written here:
  each pixel averages the neighbours whose own CoC disc reaches it, each weighted by the
  inverse of its disc's area (no occlusion model);
* ``paper`` and ``paper, FFT``: the paper's configuration of ``d2f-bench accuracy``
  (|defocus| order, 15 layers stretched to ``K``, full resolution; direct convolution, or
  FFT, the time baseline);
* ``Blender Defocus``: Blender's compositor Defocus node (circular bokeh, no z-buffer: the
  Z input is the CoC radius, 1 = ``z_scale`` px), run headless when ``blender`` is on
  ``PATH``; skipped with a note otherwise.

Times are medians of interleaved rounds, reported as ratios against ``paper, FFT`` (or, when
it is not run, the first method) in the same run, with the load average of each case beside
them; nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
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

from ..rendering import adaptive, render
from .accuracy import PAPER_OPTIONS
from .cases import Case, dilate, jump_pixels, load_cases, masked_metrics, reach_px

__all__ = [
    "CATEGORIES",
    "SCENE_CATEGORIES",
    "by_group",
    "edge_sides",
    "gather_render",
    "main",
    "run_peers",
    "scene_category",
    "thin_band",
]

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
#: What a scene holds, :func:`scene_category`'s answers.
SCENE_CATEGORIES: tuple[str, ...] = ("occlusion", "thin", "highlights", "mixed")
#: Layer kinds of the generator that count as thin structures (as :func:`thin_band`).
THIN_KINDS = ("fence", "stripes")
#: The method whose time the others are divided by, when it is run.
BASELINE = "paper, FFT"
#: Every method the bench knows, in its order (``--methods`` picks some).
METHODS: tuple[str, ...] = (
    "d2f",
    "d2f, no hidden surface",
    "d2f renderer",
    "d2f renderer, no hidden surface",
    "d2f pipeline",
    "d2f pipeline, no hidden surface",
    "gather",
    "paper",
    BASELINE,
    "Blender Defocus",
)
DEFAULT_METHODS: tuple[str, ...] = tuple(m for m in METHODS if m != "Blender Defocus")


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


def _scene_of(case: Case):
    """The case's scene, rebuilt from its seed (scenes are deterministic)."""
    from ..train.synth import make_scene

    return make_scene(case.size, seed=case.seed, margin=math.ceil(case.blur / 2) + 2)


def thin_band(case: Case, scene=None) -> np.ndarray:
    """Where the scene's thin structures are (fence and striped layers), grown by ``K / 4``;
    ``scene`` is the case's (rebuilt from its seed when not given)."""
    scene = _scene_of(case) if scene is None else scene
    h, w = case.size
    mask = np.zeros((h, w), bool)
    for layer in scene.layers:
        if layer.kind not in THIN_KINDS:
            continue
        lh, lw = layer.shape
        y0, x0 = max(0, layer.top), max(0, layer.left)
        y1, x1 = min(h, layer.top + lh), min(w, layer.left + lw)
        if y1 <= y0 or x1 <= x0:
            continue
        crop = layer.alpha[y0 - layer.top : y1 - layer.top, x0 - layer.left : x1 - layer.left]
        mask[y0:y1, x0:x1] |= crop > 0.5
    return dilate(mask, reach_px(case.blur, 4, 24))


def scene_category(thin: np.ndarray, lights: np.ndarray) -> str:
    """What a scene holds besides its occluding objects: ``"mixed"`` (thin structures and
    HDR lights in view), ``"thin"``, ``"highlights"`` or ``"occlusion"`` (neither), from the
    case's thin-structure band and its lights (``(H, W)`` bool)."""
    has_thin, has_lights = bool(thin.any()), bool(lights.any())
    if has_thin and has_lights:
        return "mixed"
    return "thin" if has_thin else "highlights" if has_lights else "occlusion"


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


def _methods(
    weights: str | Path | None, names: Sequence[str], with_blender: bool
) -> dict[str, Callable]:
    unknown = [n for n in names if n not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}; the methods are {list(METHODS)}")
    model = None
    if any(n.startswith("d2f pipeline") for n in names):
        from ..pipeline import D2F

        model = D2F.from_pretrained(weights)

    def hwc(out: torch.Tensor) -> np.ndarray:
        return out[0].permute(1, 2, 0).numpy()

    def ours(case: Case, hidden: bool = True) -> np.ndarray:
        img, disp = case.tensors()
        return hwc(adaptive.render_adaptive(img, disp, case.focus, case.blur, hidden=hidden)[0])

    def renderer(case: Case, hidden: bool = True, **options) -> np.ndarray:
        img, disp = case.tensors()
        return hwc(render(img, disp, case.focus, case.blur, hidden=hidden, **options))

    def pipeline(case: Case, hidden: bool = True) -> np.ndarray:
        scene = model.prepare(case.image, disparity=case.disparity)
        return model.render(scene, case.focus, case.blur, hidden=hidden).bokeh

    def gather(case: Case) -> np.ndarray:
        img, disp = case.tensors()
        return hwc(gather_render(img, disp, case.focus, case.blur))

    every = {
        "d2f": ours,
        "d2f, no hidden surface": lambda c: ours(c, hidden=False),
        "d2f renderer": renderer,
        "d2f renderer, no hidden surface": lambda c: renderer(c, hidden=False),
        "d2f pipeline": pipeline,
        "d2f pipeline, no hidden surface": lambda c: pipeline(c, hidden=False),
        "gather": gather,
        "paper": lambda c: renderer(c, **PAPER_OPTIONS),
        BASELINE: lambda c: renderer(c, **(PAPER_OPTIONS | {"method": "fft"})),
        "Blender Defocus": lambda c: blender_render(c.image, c.disparity, c.focus, c.blur),
    }
    return {n: every[n] for n in names if n != "Blender Defocus" or with_blender}


def run_peers(
    cases: Sequence[Case],
    *,
    weights: str | Path | None = None,
    repeat: int = 3,
    blender: bool | None = None,
    methods: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Score and time every method (``methods``, default :data:`DEFAULT_METHODS` and Blender
    when it is on ``PATH``) on every case; returns rows and notes."""
    if methods is None:
        methods = DEFAULT_METHODS + (("Blender Defocus",) if blender is not False else ())
    with_blender = "Blender Defocus" in methods and (
        blender_available() is not None if blender is None else blender
    )
    notes = []
    if "Blender Defocus" in methods and not with_blender:
        notes.append("Blender Defocus skipped: blender is not on PATH")
    methods = _methods(weights, methods, with_blender)
    rows = []
    with torch.no_grad():
        for case in cases:
            near, far = edge_sides(case.disparity)
            lights = case.bands.get("lights", np.zeros(case.size, bool))
            thin = thin_band(case)
            bands = {
                "edges": case.bands.get("edges", np.zeros(case.size, bool)),
                "edge_near": near,
                "edge_far": far,
                "thin": thin,
                "lights": lights,
            }
            category = scene_category(thin, lights)
            outputs = {name: fn(case) for name, fn in methods.items()}  # also the warm-up
            times: dict[str, list[float]] = {name: [] for name in methods}
            for _ in range(repeat):
                for name, fn in methods.items():
                    if name == "Blender Defocus" and times[name]:
                        continue  # one timed run: it starts a process per call
                    t0 = time.perf_counter()
                    fn(case)
                    times[name].append(1000.0 * (time.perf_counter() - t0))
            load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
            for name, out in outputs.items():
                metrics = masked_metrics(out, case.target, bands)
                rows.append(
                    {"method": name, "case": case.key, "mode": case.mode, "blur": case.blur,
                     "size": f"{case.size[0]}x{case.size[1]}", "category": category,
                     "ms": statistics.median(times[name]) if times[name] else None,
                     "load": load}
                    | metrics
                )  # fmt: skip
            logger.info("peers: %s done", case.key)
    return {"rows": rows, "notes": notes}


def _baseline(rows: Sequence[dict[str, Any]]) -> str:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    return BASELINE if BASELINE in methods else methods[0]


def _ratios(mine: Sequence[dict[str, Any]], base: dict[str, float]) -> list[float]:
    return [r["ms"] / base[r["case"]] for r in mine if r["ms"] is not None and base.get(r["case"])]


def summary(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Mean PSNR per method and category (:data:`CATEGORIES`) and the time ratio against
    the baseline (``paper, FFT`` when run, else the first method; mean over cases of the
    per-case ratio)."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    base = {r["case"]: r["ms"] for r in rows if r["method"] == _baseline(rows)}
    out: dict[str, dict[str, float | None]] = {}
    for m in methods:
        mine = [r for r in rows if r["method"] == m]
        entry: dict[str, float | None] = {}
        for name, band, mode in CATEGORIES:
            key = "psnr" if band is None else f"psnr_{band}"
            vals = [r[key] for r in mine if (mode is None or r["mode"] == mode)]
            vals = [v for v in vals if v is not None]
            entry[name] = float(np.mean(vals)) if vals else None
        ratios = _ratios(mine, base)
        entry["time ratio"] = float(np.mean(ratios)) if ratios else None
        out[m] = entry
    return out


def by_group(rows: Sequence[dict[str, Any]], key: str) -> dict[str, dict[Any, dict[str, Any]]]:
    """Per method and value of ``key`` (``"blur"``, ``"category"``...): the number of cases,
    mean PSNR overall and in the edge band, and the mean time ratio against the baseline."""
    base = {r["case"]: r["ms"] for r in rows if r["method"] == _baseline(rows)}
    out: dict[str, dict[Any, dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(r["method"], {}).setdefault(r[key], []).append(r)
    for method, groups in out.items():
        for value, mine in groups.items():
            edges = [r["psnr_edges"] for r in mine if r.get("psnr_edges") is not None]
            ratios = _ratios(mine, base)
            groups[value] = {
                "cases": len(mine),
                "psnr": float(np.mean([r["psnr"] for r in mine])),
                "psnr_edges": float(np.mean(edges)) if edges else None,
                "time ratio": float(np.mean(ratios)) if ratios else None,
            }
        out[method] = dict(sorted(groups.items(), key=lambda kv: _order(key, kv[0])))
    return out


def _order(key: str, value: Any):
    if key == "category" and value in SCENE_CATEGORIES:
        return (0, SCENE_CATEGORIES.index(value))
    return (1, value)


def format_groups(groups: dict[str, dict[Any, dict[str, Any]]], key: str) -> str:
    """:func:`by_group` as a markdown table: one row per value of ``key``, each method's
    PSNR / edge-band PSNR in a column."""
    methods = list(groups)
    values = list(dict.fromkeys(v for g in groups.values() for v in g))
    label = "K (px)" if key == "blur" else key
    lines = [f"| {label} | cases | " + " | ".join(methods) + " |"]
    lines.append("|" + " --- |" * (len(methods) + 2))
    for v in values:
        n = max(groups[m].get(v, {}).get("cases", 0) for m in methods)
        cells = []
        for m in methods:
            e = groups[m].get(v)
            if e is None:
                cells.append("-")
                continue
            edge = "-" if e["psnr_edges"] is None else f"{e['psnr_edges']:.2f}"
            cells.append(f"{e['psnr']:.2f} / {edge}")
        shown = f"{v:g}" if isinstance(v, float) else str(v)
        lines.append(f"| {shown} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


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
    p.add_argument("--k-fracs", nargs="+", type=float, default=None,
                   help="K as a fraction of the width (default 0.02 0.06 0.1)")  # fmt: skip
    p.add_argument("--k-px", nargs="+", type=float, default=[], help="K in px (also)")
    p.add_argument("--samples", type=int, default=128, help="aperture samples of the truth")
    p.add_argument("--cache", default="runs/acc_cache", help="ground-truth cache folder")
    p.add_argument("--weights", default=None, help="D2F checkpoint of 'd2f pipeline'")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--no-blender", action="store_true", help="skip Blender even if present")
    p.add_argument("--json", default=None, help="write rows and the table here")
    p.add_argument("--methods", nargs="+", default=None, metavar="NAME",
                   help=f"methods to run (default all but Blender's, which --no-blender "
                        f"also leaves out): {', '.join(repr(m) for m in METHODS)}")  # fmt: skip
    args = p.parse_args(argv)
    bad = [m for m in args.methods or () if m not in METHODS]
    if bad:
        p.error(f"unknown method {bad[0]!r}; the methods are {', '.join(map(repr, METHODS))}")
    if args.repeat < 0:
        p.error(f"--repeat must be >= 0, got {args.repeat}")
    k_fracs = args.k_fracs if args.k_fracs is not None else [] if args.k_px else [0.02, 0.06, 0.1]
    torch.set_num_threads(args.threads)
    try:
        sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes]
        cases = load_cases(
            sizes, args.seeds, k_fracs, samples=args.samples, cache=args.cache, k_px=args.k_px
        )
    except ValueError as exc:
        p.error(str(exc))
    methods = args.methods
    if methods is None:
        methods = DEFAULT_METHODS + (() if args.no_blender else ("Blender Defocus",))
    load_start = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    result = run_peers(cases, weights=args.weights, repeat=args.repeat, methods=methods)
    load_end = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    rows = result["rows"]
    table = summary(rows)
    ks = [f"{k:g} x width" for k in k_fracs] + [f"{k:g} px" for k in args.k_px]
    print(
        f"d2f-bench peers: {len(cases)} generated scenes ({', '.join(args.sizes)}), "
        f"K = {', '.join(ks)}, PSNR (dB) against the thin-lens truth, {args.threads} torch "
        f"threads, times against {_baseline(rows)!r}, load average {load_start:.2f} at the "
        f"start, {load_end:.2f} at the end"
    )
    print(format_table(table))
    groups = {key: by_group(rows, key) for key in ("blur", "category")}
    for key, title in (("blur", "by K"), ("category", "by what the scene holds")):
        print(f"\nPSNR / edge-band PSNR (dB), {title}:")
        print(format_groups(groups[key], key))
    for note in result["notes"]:
        print(note)
    if args.json:
        report = {"table": table, "by_k": groups["blur"], "by_category": groups["category"]}
        report["load_average"] = [load_start, load_end]
        Path(args.json).write_text(json.dumps(report | result, indent=1, default=str))
    return 0
