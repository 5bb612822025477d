"""``d2f-bench standing``: does a depth map put the subject in front of what stands behind it?

The cases where "the bottom of the frame is near" fails, held out of training:

- **Generated** (always available): scenes of :mod:`d2f_core.train.synth.standing` drawn from seeds
  that training never uses (:data:`SEED_BASE` on): a near post crossing the frame from top to
  bottom, a subject over water or a floor whose bottom rows are far, a near subject in front
  of far lights at night. Their subject mask and disparity are exact.
- **Bundled** (always available): the sample ``coffee.jpg``, a cup on a saucer seen from
  above on a table (:func:`~d2f_core.bundled.coffee_cup_mask` marks the cup); seen from
  above, the ground is all round the subject and its top is nearest.
- **Held-out photos** (``../shared/datasets``, skipped when absent): the held-out masked photos
  whose subject is tall (its box spans :data:`TALL` of the frame's height, a post, a person, a
  bottle standing across the frame) or, when the ADE20K teacher is given (``--teachers``),
  stands over ground, water or a floor (ground classes cover a fifth of the frame below it).

A case passes when the predictor's median disparity over the subject is above its median over
the background around it (a ring as wide as a tenth of the frame): the subject comes out
nearer than what is behind it. The table gives each predictor's share of passing cases, by
kind, beside the "bottom is near" ramp, with the median margin in brackets; after the
semicolon, the share of cases whose automatic focus on that map (what the app, the CLI and
the library focus on with no focus given) lands on the subject.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = [
    "SEED_BASE",
    "TALL",
    "bundled_cases",
    "generated_cases",
    "in_front",
    "main",
    "photo_cases",
    "score",
]

#: generated scenes for this check use seeds from here on (training draws below 2**30)
SEED_BASE = 1 << 31
#: a subject whose box spans this share of the frame's height is "tall"
TALL = 0.8
Case = tuple[str, str, np.ndarray, np.ndarray]  # (name, kind, image H x W x 3, mask H x W)


def generated_cases(n: int = 24, size: tuple[int, int] = (256, 384)) -> list[Case]:
    """``n`` held-out standing scenes, the kinds in turn, as sRGB images in [0, 1]."""
    from ..train.synth import linear_to_srgb, render_pinhole
    from ..train.synth.standing import STANDING_KINDS, make_standing_scene, subject_mask

    out = []
    for i in range(n):
        kind = STANDING_KINDS[i % len(STANDING_KINDS)]
        scene = make_standing_scene(size, seed=SEED_BASE + i, kind=kind, margin=0)
        radiance, _ = render_pinhole(scene)
        image = linear_to_srgb(np.clip(radiance, 0.0, 1.0)).astype(np.float32)
        out.append((f"generated-{kind}-{i}", f"generated {kind}", image, subject_mask(scene) > 0.5))
    return out


def bundled_cases() -> list[Case]:
    """The bundled sample's case: the cup of ``coffee.jpg`` seen from above."""
    from ..bundled import coffee_cup_mask, sample_photos
    from ..io import load_image

    path = next(p for p in sample_photos() if p.name == "coffee.jpg")
    image = load_image(path)
    mask = coffee_cup_mask(image.shape[1], image.shape[0]) > 0
    return [("coffee-cup", "photo seen from above", image, mask)]


def photo_cases(root: str | Path, teachers: str | Path | None = None) -> list[Case]:
    """The held-out masked photos whose subject is tall or stands over the ground (the latter
    only with the ADE20K teacher in ``teachers``)."""
    from .depth_bench import heldout_masks

    parse = None
    if teachers is not None:
        from PIL import Image

        from ..train.scene_targets import GROUND
        from ..train.scene_teachers import SceneTeachers

        net = SceneTeachers(teachers, 1)

        def parse(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
            rgb = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
            ade = Image.fromarray(net.parse(rgb)).resize((shape[1], shape[0]), Image.NEAREST)
            return np.isin(np.asarray(ade), GROUND)

    out = []
    for key, image, mask in heldout_masks(root):
        rows = np.nonzero(mask.any(axis=1))[0]
        if (rows[-1] - rows[0] + 1) >= TALL * mask.shape[0]:
            out.append((key, "photo tall", image, mask))
            continue
        if parse is not None:
            ground = parse(image, mask.shape)
            below = np.zeros_like(mask)
            below[rows[-1] - (rows[-1] - rows[0]) // 4 :] = True
            below &= ~mask
            if below.any() and ground[below].mean() >= 0.2:
                out.append((key, "photo over ground", image, mask))
    return out


def in_front(pred: np.ndarray, mask: np.ndarray) -> tuple[bool, float]:
    """``(passes, margin)``: the median of ``pred`` over ``mask`` less its median over the
    background ring around it (a tenth of the frame wide), in units of the map's 5-95 %
    range; the case passes when the margin is positive."""
    from scipy.ndimage import binary_dilation, binary_erosion

    h, w = mask.shape
    core = binary_erosion(mask, iterations=2)
    core = core if core.any() else mask
    r = max(2, int(0.1 * max(h, w)))
    step = max(1, r // 8)  # dilate a coarse copy: the ring's exact shape does not matter
    small = mask[::step, ::step]
    grown = binary_dilation(small, iterations=max(1, r // step))
    ring = np.repeat(np.repeat(grown, step, 0), step, 1)[:h, :w] & ~binary_dilation(
        mask, iterations=2
    )
    if not ring.any():
        ring = ~mask
    lo, hi = np.percentile(pred, [5, 95])
    margin = (float(np.median(pred[core])) - float(np.median(pred[ring]))) / max(hi - lo, 1e-6)
    return margin > 0, margin


def focuses_on(pred: np.ndarray, mask: np.ndarray) -> bool:
    """Whether the automatic focus on ``pred`` lands on the subject: the point
    :func:`~d2f_core.depth.subject.subject_in_map` picks (what the app, the CLI and the
    library focus on with no focus given) lies on ``mask`` or within 3 px of it."""
    from ..depth.subject import subject_in_map

    _, (x, y) = subject_in_map(np.asarray(pred, dtype=np.float32))
    return near_mask(mask, x, y, 3)


def near_mask(mask: np.ndarray, x: float, y: float, reach: int) -> bool:
    """Whether the pixel nearest ``(x, y)`` (clamped into the frame) lies on ``mask`` or
    within ``reach`` steps of it (city-block distance, as ``reach`` cross-shaped dilations
    reach), looking only at the pixels around it."""
    h, w = mask.shape
    xi, yi = min(max(round(x), 0), w - 1), min(max(round(y), 0), h - 1)
    y0, x0 = max(yi - reach, 0), max(xi - reach, 0)
    ys, xs = np.nonzero(mask[y0 : yi + reach + 1, x0 : xi + reach + 1])
    return bool((np.abs(ys + y0 - yi) + np.abs(xs + x0 - xi) <= reach).any())


def score(
    predictors: dict[str, Callable[[np.ndarray], np.ndarray]],
    cases: Sequence[Case],
    maps: dict | None = None,
) -> dict:
    """Per case and predictor ``(passes, margin)`` and whether the automatic focus lands on
    the subject (:func:`focuses_on`), and per kind and predictor the share of cases passing,
    the median margin and the share focused on the subject; ``maps`` (a dict) receives each
    predictor's map by ``(case name, predictor)``, for :func:`contact_sheet`."""
    from ..train.depth_train import resize_array

    per_case: dict[str, dict] = {}
    for name, kind, image, mask in cases:
        row = {}
        for pname, fn in predictors.items():
            pred = resize_array(fn(image), mask.shape)
            if maps is not None:
                maps[(name, pname)] = pred
            ok, margin = in_front(pred, mask)
            row[pname] = {"in_front": bool(ok), "margin": margin, "focused": focuses_on(pred, mask)}
        per_case[name] = {"kind": kind, **row}
    kinds = sorted({c[1] for c in cases})
    summary: dict[str, dict] = {}
    for kind in [*kinds, "all"]:
        rows = [r for r in per_case.values() if kind in ("all", r["kind"])]
        summary[kind] = {
            p: {
                "share": float(np.mean([r[p]["in_front"] for r in rows])),
                "median_margin": float(np.median([r[p]["margin"] for r in rows])),
                "focused": float(np.mean([r[p]["focused"] for r in rows])),
                "cases": len(rows),
            }
            for p in predictors
        }
    return {"cases": per_case, "summary": summary}


def contact_sheet(
    cases: Sequence[Case],
    maps: dict,
    result: dict,
    predictors: Sequence[str],
    path: str | Path,
    per_kind: int = 3,
    cell: int = 150,
) -> Path:
    """A sheet of ``per_kind`` cases of each kind: photo | subject | each predictor's map,
    with "in front" or "BEHIND" and the margin in each map's corner."""
    from PIL import Image, ImageDraw

    chosen: list[Case] = []
    for kind in sorted({c[1] for c in cases}):
        chosen += [c for c in cases if c[1] == kind][:per_kind]
    cols, header = 2 + len(predictors), 18
    sheet = Image.new("RGB", (cols * cell, header + len(chosen) * cell), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for j, title in enumerate(["photo", "subject", *predictors]):
        draw.text((j * cell + 4, 3), title, fill=(0, 0, 0))

    def tile(arr: np.ndarray) -> Image.Image:
        if arr.ndim == 2:
            lo, hi = np.percentile(arr, [1, 99])
            arr = np.repeat(np.clip((arr - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, 2)
        im = Image.fromarray((np.clip(arr, 0, 1) * 255).astype(np.uint8))
        im.thumbnail((cell, cell))
        return im

    for i, (name, kind, image, mask) in enumerate(chosen):
        y = header + i * cell
        tiles = [image, mask.astype(np.float32)] + [maps[(name, p)] for p in predictors]
        for j, arr in enumerate(tiles):
            sheet.paste(tile(arr), (j * cell, y))
        draw.text((4, y + 2), kind, fill=(255, 255, 0))
        for j, pname in enumerate(predictors):
            row = result["cases"][name][pname]
            word = "in front" if row["in_front"] else "BEHIND"
            colour = (80, 255, 80) if row["in_front"] else (255, 60, 60)
            draw.text(((2 + j) * cell + 4, y + 2), f"{word} {row['margin']:+.2f}", fill=colour)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


def format_table(result: dict, predictors: Sequence[str]) -> str:
    lines = [
        "| cases | n | " + " | ".join(predictors) + " |",
        "|" + " --- |" * (2 + len(predictors)),
    ]
    for kind, row in result["summary"].items():
        n = next(iter(row.values()))["cases"]
        cells = [
            f"{row[p]['share']:.0%} ({row[p]['median_margin']:+.2f}); {row[p]['focused']:.0%}"
            for p in predictors
        ]
        lines.append(f"| {kind} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    from .depth_bench import DEFAULT_DATASETS, network_predictors, ramp_predictor

    p = argparse.ArgumentParser(prog="d2f-bench standing", description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", action="append", default=None, metavar="[NAME=]PATH")
    p.add_argument("--datasets", type=Path, default=DEFAULT_DATASETS, help="held-out photos")
    p.add_argument("--teachers", type=Path, default=None, help="ADE20K teacher's folder")
    p.add_argument("--generated", type=int, default=24, help="how many generated scenes")
    p.add_argument("--no-photos", action="store_true", help="generated scenes only")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--sheet", type=Path, default=None, help="write a contact sheet here")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    predictors: dict[str, Callable] = {"ramp": ramp_predictor}
    try:
        predictors.update(network_predictors(args.weights))
    except (FileNotFoundError, ValueError) as exc:
        print(f"d2f-bench standing: error: {exc}", file=sys.stderr)
        return 1
    cases = generated_cases(args.generated)
    if not args.no_photos:
        cases += bundled_cases()
        if args.datasets.is_dir():
            cases += photo_cases(args.datasets, args.teachers)
        else:
            print(f"held-out photos skipped: {args.datasets} not found", file=sys.stderr)
    maps: dict = {}
    result = score(predictors, cases, maps)
    print(format_table(result, list(predictors)))
    if args.sheet is not None:
        print(f"contact sheet: {contact_sheet(cases, maps, result, list(predictors), args.sheet)}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
