"""``d2f-bench depth``: how well a defocus network ranks depth on real photos.

Two test sets, both read from outside the package and skipped with a reason when absent:

- **Measured depth** (``../shared/data``): 12 real photos with phone, stereo or Kinect depth
  (the Lens Blur sample, the five Depthy ``split/`` scenes, two Apple portrait JPEGs, the pug
  HEIC, Middlebury Aloe, the Kinect room, and scikit-image's ``stereo_motorcycle``). Per photo:
  the tie-averaged Spearman rank correlation of the predicted disparity with the measured
  nearness over the valid pixels, and the scale/shift-invariant RMSE (prediction fitted to the
  measured nearness, normalised to [0, 1], in least squares). Sign matters: a map upside down
  scores about ``-rho``.
- **Held-out masks** (``../shared/datasets``): the masked photos that depth training never
  sees (:func:`d2f_core.train.depth_train.is_heldout`). Per photo the subject AUC: the chance that
  a random subject pixel is predicted nearer than a random background pixel (ties half),
  over the whole frame, within 8 px of the silhouette (:func:`edge_band`), where a map
  that ends in a soft blob scores about 0.5, and against the background no lower in the frame
  than the subject's lowest row (:func:`above_feet`): the ground in front of a standing
  subject is nearer than the subject, and a map that draws it so loses whole-frame AUC for
  it.

Beside every network it scores a plain ramp ("the bottom of the image is near") in the same
run, and ``--sheet`` draws a contact sheet: photo | measured | each predictor.

``--bokeh`` also renders each measured photo from each network's map and from its measured
map, with the same model at the same pass (:func:`measured_bokeh`): how far the network's
map takes a render from what the real depth would give, in dB.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..depth import sources as depth_sources
from ..train.depth_train import resize_array
from .depth_metrics import (
    EVAL_SIDE,
    above_feet,
    edge_band,
    rankdata,
    spearman,
    ssi_rmse,
    subject_auc,
)
from .depth_metrics import eval_size as _eval_size
from .depth_predictors import (
    Predictor,
    network_predictor,
    network_predictors,
    ramp_predictor,
    rank_mix,
    source_predictor,
    subject_blend_predictor,
    teacher_predictors,
    weight_specs,
)

__all__ = [
    "EVAL_SIDE",
    "MeasuredPhoto",
    "Predictor",
    "above_feet",
    "edge_band",
    "evaluate",
    "heldout_masks",
    "main",
    "measured_bokeh",
    "measured_photos",
    "network_predictor",
    "network_predictors",
    "ramp_predictor",
    "rank_mix",
    "rankdata",
    "spearman",
    "ssi_rmse",
    "subject_auc",
    "subject_blend_predictor",
    "target_fit",
    "teacher_predictors",
    "weight_specs",
]

logger = logging.getLogger(__name__)

_REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = _REPO.parent / "shared" / "data"
DEFAULT_DATASETS = _REPO.parent / "shared" / "datasets"


@dataclass
class MeasuredPhoto:
    """A photo with measured depth: image ``H x W x 3`` float in [0, 1], ``nearness``
    ``h x w`` (larger = nearer, any monotonic scale) and ``valid`` ``h x w`` bool."""

    name: str
    image: np.ndarray
    nearness: np.ndarray
    valid: np.ndarray


# ------------------------------------------------------------------------------ data


def _photo(name: str, image: np.ndarray, near: np.ndarray, valid: np.ndarray) -> MeasuredPhoto:
    size = _eval_size(*near.shape)
    good = resize_array(valid.astype(np.float32), size, nearest=True) > 0.5
    near = resize_array(np.where(valid, near, 0.0), size, nearest=True)
    return MeasuredPhoto(name, np.clip(image, 0, 1).astype(np.float32), near, good)


def measured_photos(root: str | Path = DEFAULT_DATA) -> list[MeasuredPhoto]:
    """The 12 measured-depth photos (see the module docstring), maps at :data:`EVAL_SIDE`.

    Raises:
        FileNotFoundError: ``root`` is not a folder.
    """
    from PIL import Image

    from ..io import load_image, load_photo

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"measured-depth data not found: {root}")

    def grey(path: Path) -> np.ndarray:
        with Image.open(path) as im:
            return np.asarray(im.convert("L"), dtype=np.float32)

    out = []
    photo = load_photo(root / "google_lensblur_depthy" / "lensblur_sample.jpg")
    out.append(
        _photo("lensblur", photo.image, photo.disparity, np.ones_like(photo.disparity, bool))
    )
    for scene in ("flowers", "hut", "mango", "shelf", "tunnel"):
        split = root / "google_lensblur_depthy" / "split"
        depth = grey(split / f"{scene}-depth.jpg")  # bright = far
        out.append(
            _photo(
                f"depthy-{scene}",
                load_image(split / f"{scene}-alternative.jpg"),
                255.0 - depth,
                np.ones_like(depth, bool),
            )
        )
    for name in ("image-with-depth.jpg", "image-with-matte.jpg"):
        photo = load_photo(root / "apple_portrait_jpeg_depth" / name)
        out.append(
            _photo(
                f"apple-{name.split('-')[-1][:-4]}",
                photo.image,
                photo.disparity,
                np.ones_like(photo.disparity, bool),
            )
        )
    photo = load_photo(root / "apple_heic_depth_pillow_heif" / "pug.heic")
    out.append(_photo("pug", photo.image, photo.disparity, np.ones_like(photo.disparity, bool)))
    aloe = grey(root / "middlebury_aloe_opencv" / "aloeGT.png")
    out.append(
        _photo("aloe", load_image(root / "middlebury_aloe_opencv" / "aloeL.jpg"), aloe, aloe > 0)
    )
    with Image.open(root / "rgbd_kinect2_esanet" / "sample_depth.png") as im:
        depth = np.asarray(im, dtype=np.float32)
    room = load_image(root / "rgbd_kinect2_esanet" / "sample_rgb.png")
    registered = room.max(axis=2) > 2 / 255  # black border: no colour registered
    valid = (depth > 0) & registered
    out.append(_photo("kinect-room", room, 1.0 / np.maximum(depth, 1.0), valid))
    from skimage import data as skdata

    left, _, disp = skdata.stereo_motorcycle()
    disp = disp.astype(np.float32)
    valid = np.isfinite(disp) & (disp > 0)
    out.append(
        _photo("motorcycle", left.astype(np.float32) / 255.0, np.where(valid, disp, 0.0), valid)
    )
    return out


def heldout_masks(
    root: str | Path = DEFAULT_DATASETS, limit: int | None = None
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, image, subject mask)`` of the held-out masked photos, masks at
    :data:`EVAL_SIDE`; photos whose subject covers under 1 % or over 90 % are left out."""
    from ..io import load_image
    from ..train.depth_train import is_heldout
    from ..train.teachers import iter_photos, read_mask

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"training datasets not found: {root}")
    out = []
    for photo in iter_photos(root):
        if photo.mask is None or not is_heldout(photo):
            continue
        image = load_image(photo.path)
        size = _eval_size(*image.shape[:2])
        mask = read_mask(photo, image.shape[:2])
        mask = resize_array(mask, size, nearest=True) > 0.5
        if not 0.01 <= mask.mean() <= 0.9:
            continue
        out.append((photo.key, image, mask))
        if limit is not None and len(out) >= limit:
            break
    return out


def measured_bokeh(
    weights: dict[str, str | Path | None],
    photos: Sequence[MeasuredPhoto],
    blur: float = 0.04,
    percentiles: Sequence[float] = (90.0, 50.0),
) -> dict[str, dict[str, float]]:
    """PSNR (dB) of each network's render of each photo against the same model's render from
    the photo's measured map, by photo: the mean over focal planes at ``percentiles`` of the
    measured map (90: the near subject; 50: the middle).

    The measured nearness is stretched to [0, 1] as a map given to the app is
    (:func:`~d2f_core.io.depth.normalize_disparity`: between its 0.5th and 99.5th percentiles,
    its extremes under 1000 valid pixels; holes count as farthest, and are left out of the PSNR)
    and rendered at the pass the network's map gets (``full_pass_side`` 0 for this render only),
    with blur ``K = blur`` x the long side. The network's render is focused as a click on the
    sharp part would be (:func:`d2f_core.evaluate.click_focus`: its own disparity where the
    measured map is in focus). Rendering is the same on both sides, so only the maps differ. The
    reference is as true as the measured map's spacing: the Depthy maps are grey levels of
    depth, not disparity, and the Kinect room's is the inverse of its depth.
    """
    import copy
    import dataclasses

    from ..evaluate import click_focus
    from ..io.depth import normalize_disparity
    from ..metrics import psnr
    from ..pipeline import D2F

    out: dict[str, dict[str, float]] = {}
    for name, path in weights.items():
        model = D2F.from_pretrained(path)
        ref_model = copy.deepcopy(model)  # the same networks, another pass size
        ref_model.config = dataclasses.replace(ref_model.config, full_pass_side=0)
        row = {}
        for ph in photos:
            h, w = ph.image.shape[:2]
            valid = ph.valid
            t = np.where(valid, normalize_disparity(ph.nearness, valid), 0.0).astype(np.float32)
            truth = resize_array(t, (h, w)).astype(np.float32)
            keep = resize_array(valid.astype(np.float32), (h, w), nearest=True) > 0.5
            reference = ref_model.prepare(ph.image, disparity=truth)
            scene = model.prepare(ph.image)
            own = scene.disparity_full()
            k = blur * max(h, w)
            scores = []
            for q in percentiles:
                focus = float(np.percentile(t[valid], q))
                want = ref_model.render(reference, focus, k).bokeh
                clicked = click_focus(own, truth, focus)
                got = model.render(scene, clicked, k).bokeh
                scores.append(psnr(got[keep], want[keep]))
            row[ph.name] = float(np.mean(scores))
        out[name] = row
    return out


# ------------------------------------------------------------------------------ evaluation


def evaluate(
    predictors: dict[str, Predictor],
    photos: Sequence[MeasuredPhoto],
    masks: Sequence[tuple[str, np.ndarray, np.ndarray]] = (),
) -> dict:
    """Scores of every predictor: per measured photo (Spearman, SSI-RMSE) and the held-out
    masks (subject AUC); also the predictions at eval size, for the sheet."""
    result: dict = {"photos": {}, "masks": {}, "maps": {}}
    for ph in photos:
        row = {}
        for name, fn in predictors.items():
            pred = resize_array(fn(ph.image), ph.nearness.shape)
            row[name] = {
                "spearman": spearman(pred, ph.nearness, ph.valid),
                "ssi_rmse": ssi_rmse(pred, ph.nearness, ph.valid),
            }
            result["maps"][(ph.name, name)] = pred
        result["photos"][ph.name] = row
    for key, image, mask in masks:
        band = edge_band(mask)
        upper = above_feet(mask)
        row = {}
        for name, fn in predictors.items():
            pred = resize_array(fn(image), mask.shape)
            row[name] = subject_auc(pred, mask)
            row[name + "@edge"] = subject_auc(pred[band], mask[band])
            # a subject that fills every row down to its feet leaves no background above
            # them: the whole-frame AUC stands
            row[name + "@above"] = (
                subject_auc(pred[upper], mask[upper]) if (~mask[upper]).any() else row[name]
            )
        result["masks"][key] = row
    return result


def target_fit(
    predictors: dict[str, Predictor],
    datasets: str | Path,
    labels: str | Path,
    photos: int = 60,
    layout_teacher: float = 0.4,
    seed: int = 0,
) -> dict[str, float]:
    """Mean Spearman of each predictor's map with stage 0's targets on ``photos`` training
    photos drawn with ``seed`` (whole, at :data:`EVAL_SIDE`; scene targets where the labels
    hold the scene teachers' maps, the layout weighted by ``layout_teacher`` as in
    ``d2f-train depth --layout-teacher``): how much of its targets a network has learnt on
    photos it was trained on. Little above the ramp's agreement: the network has not learnt
    its targets (too small, too briefly trained, or targets it cannot tell from a photo);
    high here and low on the measured photos: it does not carry them over to new photos.

    Raises:
        ValueError: no labelled training photo (``datasets`` or ``labels`` missing or
            empty), or ``photos`` < 1.
    """
    import random

    from ..train.depth_train import RealDepthData

    if photos < 1:
        raise ValueError(f"photos must be at least 1, got {photos}")
    data = RealDepthData(datasets, labels, scene=True, layout_teacher=layout_teacher)
    chosen = sorted(data.photos, key=lambda ph: ph.key)
    chosen = random.Random(seed).sample(chosen, min(photos, len(chosen)))
    scores: dict[str, list[float]] = {name: [] for name in predictors}
    for photo in chosen:
        image, target, _ = data.photo_target(photo, EVAL_SIDE)
        for name, fn in predictors.items():
            pred = resize_array(fn(image), target.shape)
            scores[name].append(spearman(pred, target))
    return {name: float(np.mean(v)) for name, v in scores.items()}


def summary(result: dict, predictors: Sequence[str], baseline: str = "ramp") -> dict:
    """Means over photos, wins against ``baseline`` and the mean held-out AUC per predictor."""
    out = {}
    for name in predictors:
        rhos = [row[name]["spearman"] for row in result["photos"].values()]
        rmses = [row[name]["ssi_rmse"] for row in result["photos"].values()]
        wins = sum(
            row[name]["spearman"] > row[baseline]["spearman"] for row in result["photos"].values()
        )
        aucs = [row[name] for row in result["masks"].values()]
        edge = [row[name + "@edge"] for row in result["masks"].values()]
        above = [row[name + "@above"] for row in result["masks"].values()]
        out[name] = {
            "mean_spearman": float(np.mean(rhos)) if rhos else float("nan"),
            "mean_ssi_rmse": float(np.mean(rmses)) if rmses else float("nan"),
            "wins_vs_" + baseline: int(wins),
            "photos": len(rhos),
            "mean_subject_auc": float(np.mean(aucs)) if aucs else float("nan"),
            "mean_edge_auc": float(np.mean(edge)) if edge else float("nan"),
            "mean_above_feet_auc": float(np.mean(above)) if above else float("nan"),
            "subject_auc_over_0.5": int(sum(a > 0.5 for a in aucs)),
            "masks": len(aucs),
        }
    return out


def contact_sheet(
    result: dict,
    photos: Sequence[MeasuredPhoto],
    predictors: Sequence[str],
    path: str | Path,
    cell: int = 160,
) -> Path:
    """PNG: one row per photo, columns photo | measured | each predictor (bright = near)."""
    from PIL import Image, ImageDraw

    cols = 2 + len(predictors)
    header = 18
    sheet = Image.new("RGB", (cols * cell, header + len(photos) * cell), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for j, title in enumerate(["photo", "measured", *predictors]):
        draw.text((j * cell + 4, 3), title, fill=(0, 0, 0))

    def fit(arr: np.ndarray) -> Image.Image:
        im = Image.fromarray(arr)
        im.thumbnail((cell, cell))
        return im

    def grey(m: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        v = m[valid] if valid is not None else m.ravel()
        lo, hi = np.percentile(v, 1), np.percentile(v, 99)
        g = np.clip((m - lo) / max(hi - lo, 1e-9), 0, 1)
        rgbm = np.repeat((g * 255).astype(np.uint8)[..., None], 3, 2)
        if valid is not None:
            rgbm[~valid] = (200, 60, 60)
        return rgbm

    for i, ph in enumerate(photos):
        y = header + i * cell
        tiles = [(ph.image * 255).astype(np.uint8), grey(ph.nearness, ph.valid)]
        tiles += [grey(result["maps"][(ph.name, name)]) for name in predictors]
        for j, tile in enumerate(tiles):
            sheet.paste(fit(tile), (j * cell, y))
        draw.text((4, y + 2), ph.name, fill=(255, 255, 0))
        for j, name in enumerate(predictors):
            rho = result["photos"][ph.name][name]["spearman"]
            draw.text(((2 + j) * cell + 4, y + 2), f"{rho:+.2f}", fill=(255, 255, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path


def format_table(result: dict, predictors: Sequence[str]) -> str:
    """Markdown table: per photo Spearman / SSI-RMSE of each predictor, then the means."""
    head = "| photo | " + " | ".join(f"{p} rho / rmse" for p in predictors) + " |"
    lines = [head, "|" + " --- |" * (1 + len(predictors))]
    for name, row in result["photos"].items():
        cells = [f"{row[p]['spearman']:+.3f} / {row[p]['ssi_rmse']:.3f}" for p in predictors]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    s = summary(result, predictors)
    cells = [f"**{s[p]['mean_spearman']:+.3f}** / {s[p]['mean_ssi_rmse']:.3f}" for p in predictors]
    lines.append("| mean | " + " | ".join(cells) + " |")
    lines.append(
        "| beats ramp | "
        + " | ".join(f"{s[p]['wins_vs_ramp']} of {s[p]['photos']}" for p in predictors)
        + " |"
    )
    if result["masks"]:
        lines.append(
            "| held-out subject AUC | "
            + " | ".join(
                f"{s[p]['mean_subject_auc']:.3f} ({s[p]['subject_auc_over_0.5']} of "
                f"{s[p]['masks']} > 0.5)"
                for p in predictors
            )
            + " |"
        )
        lines.append(
            "| held-out subject AUC within 8 px of the silhouette | "
            + " | ".join(f"{s[p]['mean_edge_auc']:.3f}" for p in predictors)
            + " |"
        )
        lines.append(
            "| held-out subject AUC, background no lower than the subject's feet | "
            + " | ".join(f"{s[p]['mean_above_feet_auc']:.3f}" for p in predictors)
            + " |"
        )
    return "\n".join(lines)


def format_bokeh(scores: dict[str, dict[str, float]]) -> str:
    """Markdown table of :func:`measured_bokeh`: per photo, then the mean and, for every
    network after the first, the photos where it beats the first."""
    names = list(scores)
    photos = list(scores[names[0]])
    lines = ["| photo | " + " | ".join(names) + " |", "|" + " --- |" * (1 + len(names))]
    for ph in photos:
        lines.append(f"| {ph} | " + " | ".join(f"{scores[n][ph]:.2f}" for n in names) + " |")
    means = [float(np.mean(list(scores[n].values()))) for n in names]
    lines.append("| mean | " + " | ".join(f"**{m:.2f}**" for m in means) + " |")
    if len(names) > 1:
        first = scores[names[0]]
        wins = [sum(scores[n][ph] > first[ph] for ph in photos) for n in names[1:]]
        lines.append(
            f"| beats {names[0]} | - | " + " | ".join(f"{w} of {len(photos)}" for w in wins) + " |"
        )
    return "\n".join(lines)


def _predictors(args: argparse.Namespace) -> tuple[dict[str, Predictor], dict[str, Predictor]]:
    """Every map the command scores, by name (the ramp, the networks of ``--weights``, the
    sources of ``--source``, the teachers' columns of ``--teachers``), and the networks
    alone."""
    predictors: dict[str, Predictor] = {"ramp": ramp_predictor}
    networks = network_predictors(args.weights)
    predictors.update(networks)
    net = next(iter(networks))  # the first network: the sources and subjects use its weights
    first = weight_specs(args.weights)[net]
    for source in args.source:
        depth_sources.parse_source(source)  # a bad name fails before anything runs
        predictors[f"source {source}"] = source_predictor(source, first)
    if args.teachers is not None:
        found = teacher_predictors(args.teachers, args.threads)
        predictors.update(found)
        # how far the first network's map and the teachers' maps go together: a
        # ceiling for what stage 0 can learn from these teachers
        for key in ("layout", "targets", "scene targets"):
            if key in found:
                predictors[f"{net}+{key}"] = rank_mix(predictors[net], found[key])
        # the targets with the first network's subjects stood on them, as its own map
        # gets them: what that recipe reaches if the network learns its targets
        if "scene targets" in found:
            blended = subject_blend_predictor(first, found["scene targets"])
            if blended is not None:
                predictors[f"scene targets+{net}'s subjects"] = blended
    return predictors, networks


def build_parser() -> argparse.ArgumentParser:
    """The ``d2f-bench depth`` argument parser."""
    p = argparse.ArgumentParser(prog="d2f-bench depth", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--weights",
        action="append",
        default=None,
        metavar="[NAME=]PATH",
        help="checkpoint(s) to score (default: the shipped weights); NAME labels the column",
    )
    p.add_argument(
        "--source",
        action="append",
        default=[],
        metavar="SOURCE",
        help="also score the map D2F.prepare gives from this depth source (scene, d2f), with "
        "the first network's weights; one column each",
    )
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="measured-depth photos")
    p.add_argument("--datasets", type=Path, default=DEFAULT_DATASETS, help="held-out masks")
    p.add_argument("--masks", type=int, default=None, help="at most this many held-out masks")
    p.add_argument("--no-masks", action="store_true", help="skip the held-out masks")
    p.add_argument("--sheet", type=Path, default=None, help="write the contact sheet here")
    p.add_argument("--json", type=Path, default=None, help="write the scores here")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument(
        "--teachers",
        type=Path,
        default=None,
        metavar="DIR",
        help="also score the labelling teachers found here, the stage-0 targets built "
        "from them, the first network's map rank-averaged with each, and the scene targets "
        "with the first network's subjects stood on them (needs .[teach])",
    )
    p.add_argument(
        "--fit",
        type=Path,
        default=None,
        metavar="LABELS",
        help="also score each network against stage 0's targets on training photos, with "
        "the labels in LABELS (d2f-train label / label-scene)",
    )
    p.add_argument(
        "--bokeh",
        action="store_true",
        help="also render each measured photo from each network's map and from its measured "
        "map, and print the PSNR between the two (dB)",
    )
    p.add_argument("--fit-photos", type=int, default=60, help="training photos for --fit")
    p.add_argument(
        "--fit-layout",
        type=float,
        default=0.4,
        help="--layout-teacher of the targets --fit compares with",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    try:
        predictors, networks = _predictors(args)
        photos = measured_photos(args.data)
        masks = [] if args.no_masks else heldout_masks(args.datasets, args.masks)
    except (FileNotFoundError, ValueError) as exc:
        print(f"d2f-bench depth: error: {exc}", file=sys.stderr)
        return 1
    except ImportError as exc:
        print(f"d2f-bench depth: error: --teachers needs .[teach] ({exc})", file=sys.stderr)
        return 1
    names = list(predictors)
    result = evaluate(predictors, photos, masks)
    print(format_table(result, names))
    if args.fit is not None:
        fitted = {"ramp": ramp_predictor, **networks}
        try:
            result["fit"] = target_fit(
                fitted, args.datasets, args.fit, args.fit_photos, args.fit_layout
            )
        except ValueError as exc:
            print(f"d2f-bench depth: error: --fit: {exc}", file=sys.stderr)
            return 1
        print(
            f"\nagreement with stage 0's targets on {args.fit_photos} training photos "
            f"(mean Spearman): "
            + ", ".join(f"{name} {v:+.3f}" for name, v in result["fit"].items())
        )
    if args.bokeh:
        result["bokeh"] = measured_bokeh(weight_specs(args.weights), photos)
        print("\nrender from the network's map against the render from the measured map (dB)")
        print(format_bokeh(result["bokeh"]))
    if args.sheet is not None:
        print(f"contact sheet: {contact_sheet(result, photos, names, args.sheet)}")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "photos": result["photos"],
            "masks": result["masks"],
            "summary": summary(result, names),
        }
        for key in ("fit", "bokeh"):
            if key in result:
                payload[key] = result[key]
        args.json.write_text(json.dumps(payload, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
