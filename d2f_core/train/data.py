"""EBB!-format paired data sets (all-in-focus input, shallow-DoF target) for training D2F.

Layouts found under ``root`` (one or the other):

* ``original/<id>.jpg|png`` with ``bokeh/<id>.jpg|png`` (same stem): EBB! and ``d2f-synth``;
* ``<id>.src.jpg`` with ``<id>.tgt.jpg`` in ``root`` itself (the paired-file variant).

Optional per pair: ``disparity/<id>.png`` (16-bit, value / 65535, 1 = nearest) and
``params/<id>.json`` with ``"focus"`` (disparity of the focal plane) and ``"blur"`` (K, the CoC
diameter in px for ``|d - focus| = 1`` at the pair's resolution), as ``d2f-synth`` writes them.

Splits (ids are the file stems read as integers; pairs are ordered by id):

* A full EBB! set (largest id >= 4693) uses the paper's id ranges: ``"train"`` = ids 0-4223,
  ``"val470"`` = ids 4224-4693, ``"val294"`` = ids 4400-4693, ``"all"`` = every pair.
* A smaller set (e.g. ``d2f-synth`` output) is split by position in id order with the same
  proportions: the last ``max(1, round(n * 470 / 4694))`` pairs are ``"val470"``, the last
  ``max(1, round(n * 294 / 4694))`` are ``"val294"``, the rest is ``"train"``. Stems that are
  not integers are ordered by name and split the same way.

Images are read with :func:`d2f_core.io.load_image` / :func:`d2f_core.io.read_depth_array`.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import Dataset

from .. import io as d2f_io

__all__ = ["EBB_SIZE", "SPLITS", "EBBDataset", "PairFiles", "find_pairs", "split_pairs"]

logger = logging.getLogger(__name__)

#: Number of pairs in EBB!'s training folder, and the paper's validation boundaries.
EBB_SIZE = 4694
VAL470_START = 4224
VAL294_START = 4400
SPLITS = ("train", "val470", "val294", "all")
_IMAGE_EXTS = (".jpg", ".jpeg", ".png")


@dataclass(frozen=True)
class PairFiles:
    """Files of one pair. ``number`` is the stem as an integer (``None`` if not numeric)."""

    id: str
    number: int | None
    input: Path
    target: Path
    disparity: Path | None = None
    params: Path | None = None


def _images_by_stem(folder: Path) -> dict[str, Path]:
    found: dict[str, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.is_file() and path.suffix.lower() in _IMAGE_EXTS:
            found.setdefault(path.stem, path)
    return found


def find_pairs(root: str | Path) -> list[PairFiles]:
    """All pairs under ``root`` (either layout), ordered by numeric id, then by name.

    Raises:
        FileNotFoundError: ``root`` does not exist.
        ValueError: no pairs were found.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"data folder not found: {root}")
    pairs: dict[str, tuple[Path, Path]] = {}
    if (root / "original").is_dir() and (root / "bokeh").is_dir():
        inputs = _images_by_stem(root / "original")
        targets = _images_by_stem(root / "bokeh")
        unmatched = sorted(set(inputs) ^ set(targets))
        if unmatched:
            logger.warning(
                "%d files in %s have no partner (e.g. %s); skipped",
                len(unmatched),
                root,
                unmatched[:3],
            )
        for stem in set(inputs) & set(targets):
            pairs[stem] = (inputs[stem], targets[stem])
    for src in sorted(root.glob("*.src.*")):
        stem = src.name[: -len(".src" + src.suffix)]
        if src.suffix.lower() not in _IMAGE_EXTS or stem in pairs:
            continue
        tgt = next(
            (p for p in (root / f"{stem}.tgt{ext}" for ext in _IMAGE_EXTS) if p.is_file()), None
        )
        if tgt is None:
            logger.warning("%s has no .tgt partner; skipped", src)
            continue
        pairs[stem] = (src, tgt)
    if not pairs:
        raise ValueError(
            f"no image pairs in {root}: expected original/ + bokeh/ folders or "
            f"<id>.src.jpg + <id>.tgt.jpg files"
        )
    out = []
    for stem, (inp, tgt) in pairs.items():
        disp = root / "disparity" / f"{stem}.png"
        params = root / "params" / f"{stem}.json"
        number = int(stem) if re.fullmatch(r"\d+", stem) else None
        out.append(
            PairFiles(
                stem,
                number,
                inp,
                tgt,
                disp if disp.is_file() else None,
                params if params.is_file() else None,
            )
        )
    numeric = all(p.number is not None for p in out)
    out.sort(key=lambda p: (p.number, p.id) if numeric else (0, p.id))
    return out


def split_pairs(pairs: Sequence[PairFiles], split: str) -> list[PairFiles]:
    """Select ``split`` (see the module docstring for the rule). Empty splits raise."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    pairs = list(pairs)
    if split == "all":
        return pairs
    numbers = [p.number for p in pairs]
    if all(n is not None for n in numbers) and max(numbers) >= EBB_SIZE - 1:
        start = {"val470": VAL470_START, "val294": VAL294_START}.get(split)
        if split == "train":
            chosen = [p for p in pairs if p.number < VAL470_START]
        else:
            chosen = [p for p in pairs if start <= p.number < EBB_SIZE]
    else:
        n = len(pairs)
        n470 = max(1, round(n * 470 / EBB_SIZE))
        n294 = max(1, round(n * 294 / EBB_SIZE))
        chosen = {
            "train": pairs[: n - n470],
            "val470": pairs[n - n470 :],
            "val294": pairs[n - n294 :],
        }[split]
    if not chosen:
        raise ValueError(f"split {split!r} is empty for a set of {len(pairs)} pairs")
    return chosen


def _parse_crop(crop: int | Sequence[int] | None) -> tuple[int, int] | None:
    if crop is None:
        return None
    if isinstance(crop, int):
        crop = (crop, crop)
    crop = tuple(int(c) for c in crop)
    if len(crop) != 2 or min(crop) < 1:
        raise ValueError(f"crop must be a positive int or (height, width), got {crop!r}")
    return crop


def _read_params(path: Path) -> tuple[float, float]:
    try:
        data = json.loads(path.read_text())
        focus, blur = float(data["focus"]), float(data["blur"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: needs numeric 'focus' and 'blur' ({exc})") from exc
    if not (math.isfinite(focus) and 0 <= focus <= 1 and math.isfinite(blur) and blur >= 0):
        raise ValueError(f"{path}: focus must be in [0, 1] and blur >= 0, got {focus}, {blur}")
    return focus, blur


def _to_chw(image: np.ndarray) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)


class EBBDataset(Dataset):
    """Paired bokeh data set in EBB! layout.

    Args:
        root: data folder (see the module docstring for layouts and splits).
        split: ``"train"``, ``"val470"``, ``"val294"`` or ``"all"``.
        crop: random crop size (int or ``(h, w)``) applied identically to input, target and
            disparity; pairs smaller than the crop are first enlarged (and their ``blur``
            scaled with them). ``None`` returns whole images.
        flip: random horizontal flip (same for all three maps).
        seed: crops/flips depend only on ``(seed, epoch, index)``, so runs are repeatable
            with any number of loader workers; call :meth:`set_epoch` once per epoch.

    Items are dicts: ``image`` and ``target`` (3, H, W) float32 in [0, 1]; ``disparity``
    (1, H, W) in [0, 1] (zeros when absent) and ``has_disparity`` (bool); ``focus`` and
    ``blur`` (float32 scalars, NaN when the pair has no params file; ``blur`` in px at the
    returned resolution); ``id`` (str).
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        crop: int | Sequence[int] | None = None,
        flip: bool = False,
        seed: int = 0,
    ) -> None:
        self.root = Path(root)
        self.split = split
        self.pairs = split_pairs(find_pairs(self.root), split)
        self.crop = _parse_crop(crop)
        self.flip = bool(flip)
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation stream of ``epoch``."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, Any]:
        pair = self.pairs[index]
        image = _to_chw(d2f_io.load_image(pair.input))  # [3,H,W]
        target = _to_chw(d2f_io.load_image(pair.target))  # [3,H,W]
        size = tuple(image.shape[-2:])
        if tuple(target.shape[-2:]) != size:
            logger.warning(
                "%s: target %s resized to input %s", pair.id, tuple(target.shape[-2:]), size
            )
            target = _resize(target, size)
        if pair.disparity is not None:
            raw = d2f_io.read_depth_array(pair.disparity) / 65535.0
            disparity = torch.from_numpy(np.clip(raw, 0, 1).astype(np.float32))[None]
            if tuple(disparity.shape[-2:]) != size:
                disparity = _resize(disparity, size)
        else:
            disparity = torch.zeros(1, *size)
        focus, blur = _read_params(pair.params) if pair.params is not None else (math.nan,) * 2

        rng = np.random.default_rng([self.seed, self.epoch, index])
        if self.crop is not None:
            ch, cw = self.crop
            h, w = size
            if h < ch or w < cw:
                scale = max(ch / h, cw / w)
                new = (max(ch, math.ceil(h * scale)), max(cw, math.ceil(w * scale)))
                image, target, disparity = (_resize(x, new) for x in (image, target, disparity))
                blur = blur * scale
                h, w = new
            y0 = int(rng.integers(0, h - ch + 1))
            x0 = int(rng.integers(0, w - cw + 1))
            image, target, disparity = (
                x[:, y0 : y0 + ch, x0 : x0 + cw] for x in (image, target, disparity)
            )
        if self.flip and rng.random() < 0.5:
            image, target, disparity = (x.flip(-1) for x in (image, target, disparity))
        return {
            "id": pair.id,
            "image": image.contiguous(),
            "target": target.contiguous(),
            "disparity": disparity.clamp(0, 1).contiguous(),
            "has_disparity": pair.disparity is not None,
            "focus": torch.tensor(focus, dtype=torch.float32),
            "blur": torch.tensor(blur, dtype=torch.float32),
        }


def _resize(x: Tensor, size: tuple[int, int]) -> Tensor:
    shrink = size[0] < x.shape[-2] or size[1] < x.shape[-1]
    out = F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=shrink)
    return out[0]
