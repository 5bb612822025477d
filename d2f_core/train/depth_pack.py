"""Stage 0's photos and targets packed small, for training on another machine.

Building a photo's stage-0 target reads its teacher labels and runs the scene model
(:meth:`~d2f_core.train.depth_data.RealDepthData.photo_target`, about 70 ms a photo on one
core); the photos and labels together are several hundred megabytes. A pack holds what
training draws from instead: every labelled training photo whole at a long side of ``side``
px (WebP), its target at ``target_side`` px (8-bit PNG, relative: 0 farthest, 255 nearest)
and, where the photo has a human-drawn mask, that mask (1-bit PNG) for the pasted cut-outs.
About 20 kB a photo at the defaults, so the 2,801 training photos fit in about 60 MB.

:class:`PackedDepthData` draws stage-0 samples from a pack as
:class:`~d2f_core.train.depth_data.RealDepthData` draws them from the photos (the same
crops, pasted cut-outs, mirrors, jitter and generated scenes); ``d2f-train depth --pack``
trains on it. Two things differ: the target is built once for the whole photo at ``side`` px
and resized with the crop, rather than built at the crop's scale; and a crop is cut from the
photo as packed, so a batch side over ``side`` px is an upscaled (softer) photo, where the
original photo (up to 640 px) may have held the detail. The targets' options
(``--layout-teacher``, the scene targets) are fixed when the pack is written and recorded in
it.

``d2f-train depth-pack ROOT --labels DIR --out DIR [--shard I/N]`` writes ``pack_I.npz``;
shards written by several processes are read together.
"""

from __future__ import annotations

import argparse
import io
import logging
import random
import sys
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..sizing import scaled_size
from .depth_data import RealDepthData, check_jitter, check_share, resize_array
from .heldout import is_heldout_key
from .teachers import mask_box, read_mask, shard_arg

__all__ = ["Pack", "PackedDepthData", "PackedPhoto", "read_pack", "write_pack"]

logger = logging.getLogger(__name__)


@dataclass
class PackedPhoto:
    """One photo of a pack, decoded: ``image`` H x W x 3 uint8, ``target`` h x w uint8
    (255 nearest), ``mask`` H x W bool or ``None``."""

    key: str
    source: str
    image: np.ndarray
    target: np.ndarray
    mask: np.ndarray | None


@dataclass
class Pack:
    """A pack read back: its photos in key order, the long side they were packed at, and how
    their targets were built (``layout_teacher`` and ``scene`` as ``RealDepthData`` took
    them; ``None`` where a shard does not record it)."""

    photos: list[PackedPhoto]
    side: int
    layout_teacher: float | None
    scene: bool | None


def _encode(array: np.ndarray, fmt: str, **kw) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array).save(buf, fmt, **kw)
    return buf.getvalue()


def _decode(data: bytes) -> np.ndarray:
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im)


def write_pack(
    data: RealDepthData,
    out: str | Path,
    side: int = 352,
    target_side: int = 176,
    quality: int = 80,
    shard: tuple[int, int] = (0, 1),
) -> Path:
    """Pack the photos of ``data`` (every ``shard[1]``-th from ``shard[0]``) into
    ``out/pack_<shard[0]>.npz``; returns its path."""
    index, count = shard
    if not 0 <= index < count:
        raise ValueError(f"shard must be I/N with 0 <= I < N, got {index}/{count}")
    if side < 32 or not 16 <= target_side <= side:
        raise ValueError(
            f"need side >= 32 and 16 <= target_side <= side, got {side} and {target_side}"
        )
    if not 1 <= quality <= 100:
        raise ValueError(f"quality must lie in [1, 100], got {quality}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    keys, sources, spans, chunks = [], [], [], []
    offset = 0
    photos = data.photos[index::count]
    for i, photo in enumerate(photos):
        img, target, _ = data.photo_target(photo, side)
        h, w = target.shape
        small = resize_array(target, scaled_size((h, w), target_side / max(h, w), None))
        parts = [
            _encode((img * 255 + 0.5).astype(np.uint8), "WEBP", quality=quality, method=6),
            _encode((np.clip(small, 0, 1) * 255 + 0.5).astype(np.uint8), "PNG", optimize=True),
        ]
        if photo.mask is not None:
            mask = read_mask(photo, (h, w)) >= 0.5
            parts.append(_encode(mask, "PNG", optimize=True) if mask.any() else b"")
        else:
            parts.append(b"")
        row = []
        for part in parts:
            row.append((offset, len(part)))
            offset += len(part)
            chunks.append(part)
        keys.append(photo.key)
        sources.append(photo.source)
        spans.append(row)
        if (i + 1) % 200 == 0:
            logger.info("packed %d of %d photos (%.1f MB)", i + 1, len(photos), offset / 1e6)
    path = out / f"pack_{index}.npz"
    tmp = out / f"pack_{index}.tmp.npz"
    np.savez(
        tmp,
        keys=np.array(keys, dtype=str),
        sources=np.array(sources, dtype=str),
        spans=np.array(spans, dtype=np.int64).reshape(-1, 3, 2),
        blob=np.frombuffer(b"".join(chunks), dtype=np.uint8),
        side=np.int64(side),
        layout_teacher=np.float64(data.layout_teacher),
        scene=np.bool_(data.scene),
    )
    tmp.replace(path)
    return path


def read_pack(folder: str | Path) -> Pack:
    """Every photo of the ``pack_*.npz`` shards in ``folder``, decoded.

    Raises:
        ValueError: no shard, a shard that is not a pack (truncated, corrupt), shards packed
            at different sizes or with different targets, a photo in two shards, a held-out
            photo, or no photo at all.
    """
    files = sorted(Path(folder).glob("pack_*.npz"))
    files = [f for f in files if not f.name.endswith(".tmp.npz")]
    if not files:
        raise ValueError(f"no pack_*.npz in {folder} (d2f-train depth-pack writes them)")
    photos: list[PackedPhoto] = []
    built: set[tuple] = set()
    for file in files:
        try:
            with np.load(file) as z:
                keys, sources, spans, blob = z["keys"], z["sources"], z["spans"], z["blob"]
                side = int(z["side"])
                how = (
                    side,
                    float(z["layout_teacher"]) if "layout_teacher" in z else None,
                    bool(z["scene"]) if "scene" in z else None,
                )
            for key, source, row in zip(keys, sources, spans, strict=True):
                image, target, mask = (
                    None if n == 0 else _decode(blob[a : a + n].tobytes()) for a, n in row
                )
                if image is None or target is None or image.ndim != 3:
                    raise ValueError(f"photo {key} has no image or target")
                mask = None if mask is None else mask.astype(bool)
                photos.append(PackedPhoto(str(key), str(source), image, target, mask))
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{file} is not a stage-0 pack: {exc}") from exc
        built.add(how)
    if len(built) > 1:
        raise ValueError(f"the shards in {folder} were packed differently: {sorted(built)}")
    keys = [p.key for p in photos]
    if len(set(keys)) != len(keys):
        twice = sorted({k for k in keys if keys.count(k) > 1})
        raise ValueError(f"{folder}: photos in two shards (left from another pack?): {twice[:3]}")
    held = [k for k in keys if is_heldout_key(k)]
    if held:
        raise ValueError(f"{folder} holds held-out photos, which training never reads: {held[:3]}")
    if not photos:
        raise ValueError(f"the pack in {folder} holds no photos")
    photos.sort(key=lambda p: p.key)
    side, layout_teacher, scene = built.pop()
    return Pack(photos, side, layout_teacher, scene)


class PackedDepthData(RealDepthData):
    """:class:`~d2f_core.train.depth_data.RealDepthData`'s samples, drawn from a pack
    (:func:`write_pack`) instead of the photos and their labels.

    Args:
        pack: the folder of ``pack_*.npz`` shards.
        size, paste, synth, scene_weight, standing, jitter, frame_match: as for
            ``RealDepthData``.
    """

    def __init__(
        self,
        pack: str | Path,
        size: tuple[int, int] = (256, 256),
        paste: float = 0.4,
        synth: float = 0.15,
        scene_weight: float = 1.0,
        standing: float = 0.0,
        jitter: str = "mild",
        frame_match: float = 0.0,
    ) -> None:
        self.jitter = check_jitter(jitter)
        self.frame_match = check_share(frame_match, "frame_match")
        read = read_pack(pack)
        self.photos, self.side = read.photos, read.side
        self.masked = [p for p in self.photos if p.mask is not None]
        self.size, self.paste, self.synth, self.standing = size, paste, synth, standing
        self.keep_on, self.scene_maps = None, False
        self.rescan_every, self._drawn = 0, 0
        if scene_weight <= 0:
            raise ValueError(f"scene_weight must be positive, got {scene_weight}")
        self.scene_weight = scene_weight
        self._weigh()

    def _aspect(self, photo: PackedPhoto) -> float:  # type: ignore[override]
        h, w = photo.image.shape[:2]
        return w / h

    def _load(self, photo: PackedPhoto) -> np.ndarray:  # type: ignore[override]
        return photo.image.astype(np.float32) / 255.0

    def _whole(self, photo: PackedPhoto, img: np.ndarray, size: tuple[int, int]):  # type: ignore[override]
        """The packed photo and its target at ``size``: no subject alpha (its target holds
        it), keep map or scene maps."""
        target = resize_array(photo.target.astype(np.float32) / 255.0, size)
        return resize_array(img, size), None, target, None, None

    def _subject(self, rng: random.Random) -> tuple[np.ndarray, np.ndarray] | None:
        if not self.masked:
            return None
        photo = rng.choice(self.masked)
        if photo.mask is None or not photo.mask.any():
            return None
        box = mask_box(photo.mask)
        return photo.image[box].astype(np.float32) / 255.0, photo.mask[box].astype(np.float32)


def main(argv: Sequence[str] | None = None) -> int:
    """``d2f-train depth-pack``: :func:`write_pack` over a datasets folder and its labels."""
    p = argparse.ArgumentParser(
        prog="d2f-train depth-pack",
        description="pack stage 0's training photos and their targets (d2f-train depth --pack)",
    )
    p.add_argument("data", type=Path, help="datasets folder")
    p.add_argument("--labels", type=Path, required=True, help="teacher labels (label-scene)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--layout-teacher", type=float, default=-1.0,
                   help="as d2f-train depth (default -1: per photo)")  # fmt: skip
    p.add_argument("--no-scene-targets", action="store_true",
                   help="the older targets (ramp, depth teacher, VOC subject)")  # fmt: skip
    p.add_argument("--side", type=int, default=352)
    p.add_argument("--target-side", type=int, default=176)
    p.add_argument("--quality", type=int, default=80, help="WebP quality of the photos")
    p.add_argument("--shard", type=shard_arg, default=(0, 1), metavar="I/N")
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    import torch

    torch.set_num_threads(a.threads)
    try:
        data = RealDepthData(a.data, a.labels, layout_teacher=a.layout_teacher,
                             scene=not a.no_scene_targets)  # fmt: skip
        path = write_pack(data, a.out, a.side, a.target_side, a.quality, a.shard)
    except (ValueError, FileNotFoundError) as exc:
        print(f"d2f-train depth-pack: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0
