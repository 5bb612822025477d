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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..train.depth_train import resize_array

__all__ = [
    "MeasuredPhoto",
    "above_feet",
    "edge_band",
    "evaluate",
    "heldout_masks",
    "main",
    "measured_bokeh",
    "measured_photos",
    "network_predictors",
    "ramp_predictor",
    "rank_mix",
    "rankdata",
    "spearman",
    "ssi_rmse",
    "subject_auc",
    "target_fit",
]

logger = logging.getLogger(__name__)

_REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = _REPO.parent / "shared" / "data"
DEFAULT_DATASETS = _REPO.parent / "shared" / "datasets"
#: long side (px) at which maps are compared
EVAL_SIDE = 384


@dataclass
class MeasuredPhoto:
    """A photo with measured depth: image ``H x W x 3`` float in [0, 1], ``nearness``
    ``h x w`` (larger = nearer, any monotonic scale) and ``valid`` ``h x w`` bool."""

    name: str
    image: np.ndarray
    nearness: np.ndarray
    valid: np.ndarray


# ------------------------------------------------------------------------------ metrics


def rankdata(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of a 1-D array, ties given the mean of their ranks (float64)."""
    x = np.asarray(x).ravel()
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(x.size, np.float64)
    sorted_x = x[order]
    starts = np.r_[0, np.nonzero(np.diff(sorted_x))[0] + 1]
    ends = np.r_[starts[1:], x.size]
    mean_rank = (starts + ends + 1) / 2.0  # ranks start..end-1, 1-based
    ranks[order] = np.repeat(mean_rank, ends - starts)
    return ranks


def spearman(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Tie-averaged Spearman rank correlation over ``valid`` pixels (0 for a constant map)."""
    p, t = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} does not match truth shape {t.shape}")
    if valid is not None:
        p, t = p[valid], t[valid]
    rp, rt = rankdata(p), rankdata(t)
    rp -= rp.mean()
    rt -= rt.mean()
    den = np.sqrt((rp * rp).sum() * (rt * rt).sum())
    return float((rp * rt).sum() / den) if den > 0 else 0.0


def ssi_rmse(pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None = None) -> float:
    """RMSE after fitting ``a * pred + b`` to ``truth`` normalised to [0, 1] (its 1st to 99th
    percentile, clipped, so that a few outlying pixels do not squash the rest)."""
    p, t = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} does not match truth shape {t.shape}")
    if valid is not None:
        p, t = p[valid], t[valid]
    p, t = p.ravel(), t.ravel()
    lo, hi = np.percentile(t, 1), np.percentile(t, 99)
    t = np.clip((t - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    a = np.stack([p, np.ones_like(p)], 1)
    coef, *_ = np.linalg.lstsq(a, t, rcond=None)
    return float(np.sqrt(np.mean((a @ coef - t) ** 2)))


def subject_auc(pred: np.ndarray, mask: np.ndarray) -> float:
    """Chance that a random subject pixel (``mask``) is predicted nearer than a random
    background pixel, ties counted half (Mann-Whitney U over the two sets)."""
    pred = np.asarray(pred, np.float64).ravel()
    m = np.asarray(mask, bool).ravel()
    n1, n0 = int(m.sum()), int((~m).sum())
    if n1 == 0 or n0 == 0:
        raise ValueError("the mask must hold both subject and background pixels")
    ranks = rankdata(pred)
    u = ranks[m].sum() - n1 * (n1 + 1) / 2.0
    return float(u / (n1 * n0))


def edge_band(mask: np.ndarray, width: int = 8) -> np.ndarray:
    """Pixels within ``width`` px of the mask's silhouette, on either side."""
    from skimage.morphology import dilation, disk, erosion

    m = np.asarray(mask, bool)
    fp = disk(width)
    return dilation(m, fp) & ~erosion(m, fp)


def above_feet(mask: np.ndarray) -> np.ndarray:
    """The subject and the background in rows no lower than the subject's lowest row: the
    pixels left when the ground in front of a standing subject is set aside."""
    m = np.asarray(mask, bool)
    rows = np.nonzero(m.any(axis=1))[0]
    if rows.size == 0:
        raise ValueError("the mask holds no subject pixel")
    keep = np.zeros_like(m)
    keep[: rows[-1] + 1] = True
    return keep | m


# ------------------------------------------------------------------------------ data


def _eval_size(h: int, w: int, side: int = EVAL_SIDE) -> tuple[int, int]:
    s = side / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


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


# ------------------------------------------------------------------------------ predictors

Predictor = Callable[[np.ndarray], np.ndarray]


def ramp_predictor(image: np.ndarray) -> np.ndarray:
    """ "The bottom of the image is near": row index over height, ``H x W``."""
    h, w = image.shape[:2]
    return np.broadcast_to(np.linspace(0, 1, h, dtype=np.float32)[:, None], (h, w)).copy()


def network_predictor(weights: str | Path | None = None) -> Predictor:
    """The disparity :meth:`D2F.prepare` gives a photo with no depth (the app's path)."""
    from ..pipeline import D2F

    model = D2F.from_pretrained(weights)
    # a mix asks for the same photo's map again
    return _remember_last(lambda image: model.prepare(image).disparity_full())


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


def weight_specs(specs: Sequence[str] | None) -> dict[str, str | None]:
    """``--weights [NAME=]PATH`` options by name (the shipped weights, as ``"network"``,
    when there are none; a path without a name is named by its stem)."""
    out: dict[str, str | None] = {}
    for spec in specs or [None]:
        if spec is not None and "=" in spec:
            name, path = spec.split("=", 1)
        else:
            name, path = ("network" if spec is None else Path(spec).stem), spec
        out[name] = path
    return out


def network_predictors(specs: Sequence[str] | None) -> dict[str, Predictor]:
    """``--weights [NAME=]PATH`` options as predictors, by name (:func:`weight_specs`)."""
    return {name: network_predictor(path) for name, path in weight_specs(specs).items()}


def subject_blend_predictor(weights: Any, base: Predictor) -> Predictor | None:
    """``base``'s map with the subjects of the network in ``weights`` (a checkpoint's path,
    ``None`` for the shipped weights, or a :class:`~d2f_core.pipeline.D2F`) stood on it as
    :meth:`D2F.prepare` stands them on the network's own map (:meth:`D2F.stand`, with the
    scene head's subject and sky maps resized to ``base``'s); ``None`` for a network that
    stands none (no scene head, or no lift and no blend). On stage 0's targets it is the
    map the shipped recipe would give if the network learnt its targets exactly."""
    from ..pipeline import D2F
    from ..rendering.inputs import image_tensor

    model = weights if isinstance(weights, D2F) else D2F.from_pretrained(weights)
    if not model.stands_subjects:
        return None

    def predict(image: np.ndarray) -> np.ndarray:
        b = np.asarray(base(image), dtype=np.float32)
        maps = model.scene_maps(image_tensor(image))[0].numpy()
        subject, sky = (resize_array(m, b.shape) for m in maps)
        return model.stand(b, np.clip(subject, 0, 1), np.clip(sky, 0, 1))

    return predict


def _remember_last(fn: Callable[[np.ndarray], Any]) -> Callable[[np.ndarray], Any]:
    """``fn`` that keeps its result for the photo it last ran on, for predictors that ask
    for the same photo's maps in turn (photos are never changed in place)."""
    last: list = [None, None]

    def call(image: np.ndarray) -> Any:
        if last[0] is not image:
            last[:] = [image, fn(image)]
        return last[1]

    return call


def rank_mix(*predictors: Predictor) -> Predictor:
    """The mean of several predictors' maps after ranking each (ties averaged), resized to
    the first one's size: a blend that neither map's scale can dominate."""
    if not predictors:
        raise ValueError("rank_mix needs at least one predictor")

    def predict(image: np.ndarray) -> np.ndarray:
        maps = [fn(image) for fn in predictors]
        shape = np.shape(maps[0])
        ranks = np.mean([rankdata(resize_array(m, shape)) for m in maps], axis=0)
        return (ranks / ranks.size).reshape(shape).astype(np.float32)

    return predict


def teacher_predictors(folder: str | Path, threads: int = 1) -> dict[str, Predictor]:
    """The labelling teachers as predictors, to show how good stage 0's targets are on the
    measured photos (training only: the teachers never ship):

    - ``"teacher"``: the indoor depth teacher's smoothed, ranked disparity;
    - ``"layout"``: the ramp blended with it by
      :func:`~d2f_core.train.scene_targets.teacher_weight`, the background of the older targets;
    - ``"targets"``: the older targets on a photo without a mask: that layout with the VOC
      teacher's subject stood on it by :func:`~d2f_core.train.scene_targets.subject_target`.

    With the scene teachers in ``folder`` (:mod:`d2f_core.train.scene_teachers`), also:

    - ``"sky+ground"``: ADE20K's scene model alone
      (:func:`~d2f_core.train.scene_targets.scene_layout`: sky farthest, a ground plane, things
      standing on it), blended with ``"layout"`` where the photo shows little scene;
    - ``"silhouette"``: the ramp with U^2-Net-p's silhouette stood on it, wherever it is found;
    - ``"scene targets"``: what stage 0 now trains towards on a photo without a mask
      (:func:`~d2f_core.train.scene_targets.scene_target`).
    """
    from PIL import Image

    from ..train.scene_targets import (
        ramp,
        subject_target,
        teacher_layout,
        teacher_subject,
        teacher_weight,
    )
    from ..train.scene_teachers import ADE_FILE, SceneTeachers
    from ..train.teachers import Teachers, label_maps

    folder = Path(folder)
    if not (folder / "deeplabv3_mobilenetv2_voc.onnx").is_file():
        raise FileNotFoundError(f"no teachers in {folder}")
    net = Teachers(folder, threads)
    scene_net = SceneTeachers(folder, threads) if (folder / ADE_FILE).is_file() else None

    @_remember_last  # several predictors ask for each photo's maps
    def maps(image: np.ndarray) -> dict[str, Any]:
        # at the size the maps are scored at (the subject's ring grows with the frame)
        rgb = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
        size = _eval_size(*image.shape[:2])
        fg, disp = label_maps(*net(rgb), size)
        weight = teacher_weight(disp)
        out: dict[str, Any] = {"fg": fg, "disp": disp, "weight": weight}
        out["layout"] = teacher_layout(disp, weight)
        out["voc"] = teacher_subject(fg)
        if scene_net is not None:
            h, w = size
            labels = scene_net(rgb)
            out["ade"] = np.asarray(Image.fromarray(labels["ade"]).resize((w, h), Image.NEAREST))
            sal = Image.fromarray(labels["sal"]).resize((w, h), Image.BILINEAR)
            out["sal"] = np.asarray(sal, dtype=np.float32) / 255.0
        return out

    def teacher(image: np.ndarray) -> np.ndarray:
        return maps(image)["disp"]

    def layout(image: np.ndarray) -> np.ndarray:
        return maps(image)["layout"]

    def targets(image: np.ndarray) -> np.ndarray:
        m = maps(image)
        return m["layout"] if m["voc"] is None else subject_target(m["layout"], m["voc"])

    found = {"teacher": teacher, "layout": layout, "targets": targets}
    if scene_net is None:
        return found
    from ..train.scene_targets import scene_layout, scene_target

    def sky_ground(image: np.ndarray) -> np.ndarray:
        m = maps(image)
        return scene_layout(m["ade"], m["layout"], m["weight"])[0]

    def silhouette(image: np.ndarray) -> np.ndarray:
        sal = maps(image)["sal"]
        base = ramp(*sal.shape)
        return subject_target(base, sal) if (sal >= 0.5).any() else base

    def new_targets(image: np.ndarray) -> np.ndarray:
        m = maps(image)
        return scene_target(m["ade"], m["layout"], m["weight"], sal=m["sal"], voc=m["voc"])

    found.update({"sky+ground": sky_ground, "silhouette": silhouette, "scene targets": new_targets})
    return found


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


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="d2f-bench depth", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--weights",
        action="append",
        default=None,
        metavar="[NAME=]PATH",
        help="checkpoint(s) to score (default: the shipped weights); NAME labels the column",
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
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.WARNING)
    predictors: dict[str, Predictor] = {"ramp": ramp_predictor}
    try:
        networks = network_predictors(args.weights)
        predictors.update(networks)
        if args.teachers is not None:
            found = teacher_predictors(args.teachers, args.threads)
            predictors.update(found)
            # how far the first network's map and the teachers' maps go together: a
            # ceiling for what stage 0 can learn from these teachers
            net = next(iter(networks))
            for key in ("layout", "targets", "scene targets"):
                if key in found:
                    predictors[f"{net}+{key}"] = rank_mix(predictors[net], found[key])
            # the targets with the first network's subjects stood on them, as its own map
            # gets them: what that recipe reaches if the network learns its targets
            if "scene targets" in found:
                path = weight_specs(args.weights)[net]
                blended = subject_blend_predictor(path, found["scene targets"])
                if blended is not None:
                    predictors[f"scene targets+{net}'s subjects"] = blended
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
