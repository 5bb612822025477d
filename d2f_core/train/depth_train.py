"""Stage 0: the defocus network learns depth from real photos before any bokeh loss.

``d2f-train depth`` trains :class:`~d2f_core.networks.DefocusNet` with direct supervision:

- **Real photos with a subject** (human-drawn masks, or the VOC teacher's foreground where a
  photo has no mask). The target is a layout plus the subject in front of it: the layout is
  a "bottom of the frame is near" ramp blended with the indoor depth teacher's ranked
  disparity (``layout_teacher`` of it); every connected part of the subject stands on that
  layout where its lowest row touches it (a person standing on a floor has the floor's
  disparity at their feet), and is lifted to at least what surrounds it. The mask is
  feathered by a pixel so hair and fur edges stay soft.
- **Pasted subjects**: a subject cut out of another masked photo with its feathered alpha is
  placed over the photo, in front of everything it covers. Its disparity is exact, and it
  teaches that what looks like a subject is near wherever it lies in the frame.
- **Generated layered scenes** (:mod:`d2f_core.train.synth`) with their exact disparity, so the
  network stays calibrated on the scenes the bokeh stages and the held-out set use.

- **The keep term** (``--keep``): where a photo's target knows nothing new (outside its
  subjects, a margin around them and the sky; :func:`~d2f_core.train.scene_targets.taught_mask`),
  the network is also held to an earlier network's relative depth
  (:func:`~d2f_core.train.depth_losses.keep_loss`), so that what it learnt of whole scenes is
  not traded for the scene targets' coarser layout while those teach it subjects in front.
  Measured (``TRAINING.md``): it keeps the measured photos' scores and, with them, holds back
  the subjects' gain; the shipped weights were trained without it.

Real targets are relative (0 = farthest, 1 = nearest in each photo), so their loss is a
scale- and shift-invariant L1 plus multi-scale gradient matching (MiDaS), plus a plain L1 with
weight ``absolute_weight`` that keeps outputs in [0, 1]; generated scenes have absolute
targets and take a plain L1 plus gradient matching.

A photo is held out of training when :func:`is_heldout` says so (a hash of its name: about
one photo in ten); ``d2f-bench depth`` evaluates on exactly those.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import math
import random
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..io import load_image
from ..networks import SCENE_MAPS, build_defocus_net, count_parameters
from ..sizing import scaled_size
from .depth_losses import (
    depth_loss,
    gradient_matching_loss,
    keep_loss,
    scene_map_loss,
    ssi_align,
)
from .distill import Distiller, teacher_grid
from .heldout import is_heldout
from .scene_targets import (
    SKY,
    normalise,
    read_scene_label,
    scene_strength,
    scene_subjects,
    stand_on_scene,
    subject_target,
    taught_mask,
    teacher_layout,
    teacher_subject,
    teacher_weight,
)
from .synth.photo import feather
from .teachers import FeatureTeacher, Photo, iter_photos, read_label, read_mask, subject_cutout

__all__ = [
    "DepthSample",
    "RealDepthData",
    "gradient_matching_loss",
    "is_heldout",
    "resize_array",
    "ssi_align",
    "subject_target",
    "train_depth",
]

logger = logging.getLogger(__name__)

#: folders of whole scenes (streets, rooms, landscapes): the layouts that the depth teacher
#: knows; ``scene_weight`` draws them more often
SCENE_SOURCES = ("photos/sun_hays80", "photos/urban100", "photos/bsds500")


# ------------------------------------------------------------------------------ data


@dataclass
class DepthSample:
    image: np.ndarray  # H x W x 3 float32 [0, 1]
    target: np.ndarray  # H x W float32 [0, 1]
    relative: bool  # True: scale/shift-free target (real photos)
    #: H x W float32 in [0, 1]: where the keep term holds the network to an earlier one's
    #: relative depth (the photo's pixels that its target knows nothing new about)
    keep: np.ndarray | None = None
    #: 2 x H x W float32: what the scene head learns (:data:`~d2f_core.networks.SCENE_MAPS`:
    #: the subjects' alpha and the sky), -1 where the photo's labels do not say
    maps: np.ndarray | None = None


def resize_array(x: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """An ``H x W`` or ``H x W x C`` float array at ``size`` = ``(h, w)``: bilinear,
    antialiased when shrinking, or nearest."""
    h, w = size
    t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))
    t = t.permute(2, 0, 1)[None] if t.ndim == 3 else t[None, None]
    mode = "nearest" if nearest else "bilinear"
    shrink = h < t.shape[-2] or w < t.shape[-1]
    kw = {} if nearest else {"align_corners": False, "antialias": shrink}
    out = F.interpolate(t, size=(h, w), mode=mode, **kw)[0]
    return out.permute(1, 2, 0).numpy() if x.ndim == 3 else out[0].numpy()


def _target(layout: np.ndarray, alpha: np.ndarray | None) -> np.ndarray:
    """A photo's stage-0 target: its layout with the subject ``alpha`` (if any) stood on it,
    normalised to [0, 1]."""
    return normalise(subject_target(layout, alpha) if alpha is not None else layout)


class RealDepthData:
    """Samples for stage 0 (see the module docstring); ``sample(rng)`` draws one.

    Args:
        root: the datasets folder (``../shared/datasets``).
        labels: the teachers' ``.npz`` folder written by ``d2f-train label``.
        size: ``(H, W)`` of every sample.
        paste: probability of pasting another photo's subject.
        synth: probability of a generated layered scene instead of a photo.
        layout_teacher: weight of the depth teacher in the background layout (the rest is
            the ramp); negative: per photo, :func:`teacher_weight`.
        scene_weight: how much more often than another photo a photo of
            :data:`SCENE_SOURCES` is drawn.
        scene: build the targets of photos whose labels hold the scene teachers' maps with
            :func:`d2f_core.train.scene_targets.scene_target`.
        rescan_every: look for label files written since every this many samples (0: never).
        standing: share of the generated scenes drawn from :mod:`d2f_core.train.synth.standing`.
        keep_on: where a sample's keep map (:attr:`DepthSample.keep`) is on: ``"background"``,
            every photo outside its taught pixels; ``"plain"``, only photos with no subject
            (no mask, silhouette, VOC subject or occluder), outside their sky and weighted by
            how little of a scene they show (1 - :func:`scene_strength`): close-ups and rooms;
            ``None`` (training without the keep term): no keep maps are made.
        scene_maps: also make each sample's :attr:`DepthSample.maps`, the scene head's
            targets: the subjects its depth target stands in front (human masks, clear
            silhouettes, the VOC subject, near occluders and pasted cut-outs) and the scene
            teacher's sky.
    """

    def __init__(
        self,
        root: str | Path,
        labels: str | Path,
        size: tuple[int, int] = (256, 256),
        paste: float = 0.4,
        synth: float = 0.15,
        layout_teacher: float = 0.4,
        fg_min_area: float = 0.01,
        fg_max_area: float = 0.8,
        scene_weight: float = 1.0,
        scene: bool = False,
        rescan_every: int = 0,
        standing: float = 0.0,
        keep_on: str | None = None,
        scene_maps: bool = False,
    ) -> None:
        if keep_on not in (None, "background", "plain"):
            raise ValueError(f"keep_on must be 'background', 'plain' or None, got {keep_on!r}")
        self.keep_on = keep_on
        self.scene_maps = scene_maps
        self.labels = Path(labels)
        self._all = [p for p in iter_photos(root) if not is_heldout(p)]
        self.scene = scene
        self.rescan_every = rescan_every
        self.standing = standing
        self._drawn = 0
        self._scan()
        if not self.photos:
            raise ValueError(f"no labelled training photos under {root} with labels {labels}")
        self.size = size
        self.paste = paste
        self.synth = synth
        self.layout_teacher = layout_teacher
        self.fg_min_area, self.fg_max_area = fg_min_area, fg_max_area
        if scene_weight <= 0:
            raise ValueError(f"scene_weight must be positive, got {scene_weight}")
        self.scene_weight = scene_weight
        self._weigh()

    def _scan(self) -> None:
        """The photos whose labels exist now (labels may still be being written)."""
        have = {f.name for f in self.labels.iterdir()} if self.labels.is_dir() else set()
        self.photos = [p for p in self._all if f"{p.key}.npz" in have]
        self.masked = [p for p in self.photos if p.mask is not None]

    def _weigh(self) -> None:
        weights = [self.scene_weight if p.source in SCENE_SOURCES else 1.0 for p in self.photos]
        self._cum_weights = list(itertools.accumulate(weights))

    # -- pieces
    def _photo(
        self, photo: Photo, rng: random.Random, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Image, subject alpha (or None), layout, keep map (:meth:`_keep_map`) and scene
        maps (:attr:`DepthSample.maps`, or None), at ``size`` after a random crop."""
        img = load_image(photo.path)
        h0, w0 = img.shape[:2]
        th, tw = size
        scale = max(th / h0, tw / w0) * rng.uniform(1.0, 1.3)
        rh, rw = max(th, round(h0 * scale)), max(tw, round(w0 * scale))
        img, alpha, layout, keep, maps = self._whole(photo, img, (rh, rw))
        y = rng.randint(0, rh - th)
        x = rng.randint(0, rw - tw)
        sl = (slice(y, y + th), slice(x, x + tw))
        return (img[sl], None if alpha is None else alpha[sl], layout[sl],
                None if keep is None else keep[sl],
                None if maps is None else maps[(slice(None), *sl)])  # fmt: skip

    def photo_target(
        self, photo: Photo, long_side: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """A training photo whole, scaled to a long side of ``long_side`` px, and what stage 0
        teaches there: ``(image H x W x 3, target H x W in [0, 1], keep map or None)``, before
        any crop, pasted cut-out, mirror or jitter. How close a network comes to these targets
        on the photos it was trained on (``d2f-bench depth --fit``) tells a network too small
        for its targets from one that does not carry them over to new photos."""
        img = load_image(photo.path)
        size = scaled_size(img.shape[:2], long_side / max(img.shape[:2]), None)
        img, alpha, layout, keep, _ = self._whole(photo, img, size)
        return np.clip(img, 0.0, 1.0), _target(layout, alpha), keep

    def _whole(
        self, photo: Photo, img: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """:meth:`_photo` before its crop: the photo ``img`` resized to ``size``."""
        h0, w0 = img.shape[:2]
        rh, rw = size
        img = resize_array(img, (rh, rw))
        mask = read_mask(photo, (h0, w0))
        label = self.labels / f"{photo.key}.npz"
        fg, teacher = read_label(label, (rh, rw))
        if mask is not None:
            alpha = feather(resize_array(mask, (rh, rw)) >= 0.5, 1.0)
        else:
            alpha = teacher_subject(fg, self.fg_min_area, self.fg_max_area)
        wt = teacher_weight(teacher) if self.layout_teacher < 0 else self.layout_teacher
        layout = teacher_layout(teacher, wt)
        scene = read_scene_label(label, (rh, rw)) if self.scene else None
        subjects, ade = alpha, None
        if scene is not None:  # the scene model's target, subjects and occluders stood on it
            ade = scene["ade"]
            voc = None if mask is not None else alpha
            subjects = scene_subjects(ade, alpha if mask is not None else None, scene["sal"], voc)
            layout = stand_on_scene(ade, layout, wt, subjects)
            alpha = None
        maps = None
        if self.scene_maps:
            maps = np.full((len(SCENE_MAPS), rh, rw), -1.0, np.float32)
            if subjects is not None:  # else no mask, no scene labels, no VOC subject: unknown
                maps[0] = subjects
            if ade is not None:
                maps[1] = np.isin(ade, SKY)
        return img, alpha, layout, self._keep_map(subjects, ade, wt, (rh, rw)), maps

    def _keep_map(
        self,
        subjects: np.ndarray | None,
        ade: np.ndarray | None,
        teacher_weight: float,
        shape: tuple[int, int],
    ) -> np.ndarray | None:
        """A photo's keep map (see ``keep_on``), ``H x W`` float32, zero on the target's
        taught pixels (:func:`~d2f_core.train.scene_targets.taught_mask`); ``None`` when
        ``keep_on`` is ``None``."""
        if self.keep_on is None:
            return None
        if subjects is None and ade is None:
            keep = np.ones(shape, np.float32)
        else:
            keep = (~taught_mask(subjects, ade)).astype(np.float32)
        if self.keep_on == "plain":
            plain = subjects is None or not (subjects >= 0.5).any()
            strength = 0.0 if ade is None else scene_strength(ade, teacher_weight)
            keep *= (1.0 - strength) * float(plain)
        return keep

    def _cutout(
        self, rng: random.Random, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """A subject cut out of a random masked photo: (rgb h x w x 3, alpha h x w)."""
        cut = subject_cutout(rng.choice(self.masked))
        if cut is None or cut[1].sum() < 64:
            return None
        crop, mask, _ = cut
        th, tw = size
        scale = rng.uniform(0.25, 0.8) * min(th, tw) / max(mask.shape)
        ch, cw = max(4, round(mask.shape[0] * scale)), max(4, round(mask.shape[1] * scale))
        rgb = resize_array(crop, (ch, cw))
        alpha = feather(resize_array(mask, (ch, cw)) >= 0.5, 0.8)
        if rng.random() < 0.5:
            rgb, alpha = rgb[:, ::-1], alpha[:, ::-1]
        return rgb, alpha

    def _paste(
        self,
        img: np.ndarray,
        target: np.ndarray,
        rgb: np.ndarray,
        a: np.ndarray,
        rng: random.Random,
        keep: np.ndarray | None = None,
        maps: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Composite a cut-out over ``img`` at a random place (up to a quarter of it may
        leave the frame), nearer than everything it covers and at least at the target's
        disparity where its lowest row stands; returns the new image, target and keep map
        (zero under the cut-out) and scene maps (the cut-out is a subject and hides the
        sky)."""
        th, tw = target.shape
        ch, cw = a.shape
        y = rng.randint(-ch // 4, th - 3 * ch // 4)
        x = rng.randint(-cw // 4, tw - 3 * cw // 4)
        ya, yb, xa, xb = max(0, y), min(th, y + ch), max(0, x), min(tw, x + cw)
        if yb <= ya or xb <= xa:
            return img, target, keep, maps
        a_c = a[ya - y : yb - y, xa - x : xb - x]
        rgb_c = rgb[ya - y : yb - y, xa - x : xb - x]
        inside = a_c >= 0.5
        if not inside.any():
            return img, target, keep, maps
        rows = np.nonzero(inside.any(axis=1))[0]
        contact = float(np.median(target[ya + rows[-1], xa:xb][inside[rows[-1]]]))
        value = min(1.0, max(contact, float(target[ya:yb, xa:xb][inside].max()) + 0.05))
        img, target = img.copy(), target.copy()
        img[ya:yb, xa:xb] = a_c[..., None] * rgb_c + (1 - a_c[..., None]) * img[ya:yb, xa:xb]
        target[ya:yb, xa:xb] = a_c * value + (1 - a_c) * target[ya:yb, xa:xb]
        if keep is not None:
            keep = keep.copy()
            keep[ya:yb, xa:xb] *= 1 - a_c
        if maps is not None:
            maps = maps.copy()
            region = maps[:, ya:yb, xa:xb]
            known = region >= 0
            region[0] = np.where(known[0], a_c + (1 - a_c) * region[0], region[0])
            region[1] = np.where(known[1], (1 - a_c) * region[1], region[1])
        return img, normalise(target), keep, maps

    def _synth(self, rng: random.Random, size: tuple[int, int]) -> DepthSample:
        from .synth import linear_to_srgb, make_scene, render_pinhole
        from .synth.standing import STANDING_KINDS, make_standing_scene

        seed = rng.randrange(1 << 30)
        if rng.random() < self.standing:
            kind = rng.choice(STANDING_KINDS)
            scene = make_standing_scene(size, seed=seed, kind=kind, margin=0)
        else:
            scene = make_scene(size, seed=seed, margin=0)
        radiance, disp = render_pinhole(scene)
        image = linear_to_srgb(np.clip(radiance, 0.0, 1.0)).astype(np.float32)
        return DepthSample(image, disp.astype(np.float32), relative=False)

    def sample(self, rng: random.Random, size: tuple[int, int] | None = None) -> DepthSample:
        """One sample of ``size`` (``(H, W)``; default :attr:`size`)."""
        size = self.size if size is None else size
        self._drawn += 1
        if self.rescan_every and self._drawn % self.rescan_every == 0:
            self._scan()
            self._weigh()
        if rng.random() < self.synth:
            return self._synth(rng, size)
        if self.scene_weight == 1.0:
            photo = rng.choice(self.photos)
        else:
            photo = rng.choices(self.photos, cum_weights=self._cum_weights)[0]
        img, alpha, layout, keep, maps = self._photo(photo, rng, size)
        target = _target(layout, alpha)
        if rng.random() < self.paste:
            cut = self._cutout(rng, size)
            if cut is not None:
                img, target, keep, maps = self._paste(img, target, *cut, rng, keep, maps)
        if rng.random() < 0.5:
            img, target = img[:, ::-1], target[:, ::-1]
            keep = None if keep is None else keep[:, ::-1]
            maps = None if maps is None else maps[:, :, ::-1]
        # mild photometric jitter
        gain = rng.uniform(0.8, 1.2)
        gamma = rng.uniform(0.8, 1.25)
        img = np.clip(img * gain, 0, 1) ** gamma
        return DepthSample(
            img.astype(np.float32), target.astype(np.float32), relative=True,
            keep=None if keep is None else np.ascontiguousarray(keep, dtype=np.float32),
            maps=None if maps is None else np.ascontiguousarray(maps, dtype=np.float32),
        )  # fmt: skip

    def batch(
        self, rng: random.Random, n: int, size: tuple[int, int] | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(images, targets, relative, keep, maps)``: B x 3 x H x W, B x 1 x H x W, B,
        B x 1 x H x W (zero for generated scenes) and B x 2 x H x W (the scene maps, -1
        where unknown: everywhere in generated scenes and without ``scene_maps``)."""
        samples = [self.sample(rng, size) for _ in range(n)]
        images = torch.stack(
            [torch.from_numpy(np.ascontiguousarray(s.image)).permute(2, 0, 1) for s in samples]
        )
        targets = torch.stack([torch.from_numpy(np.ascontiguousarray(s.target)) for s in samples])
        relative = torch.tensor([s.relative for s in samples])
        keep = torch.stack(
            [torch.zeros(s.target.shape) if s.keep is None else torch.from_numpy(s.keep)
             for s in samples]
        )  # fmt: skip
        maps = torch.stack(
            [torch.full((len(SCENE_MAPS), *s.target.shape), -1.0) if s.maps is None
             else torch.from_numpy(s.maps) for s in samples]
        )  # fmt: skip
        return images, targets[:, None], relative, keep[:, None], maps


def batch_shapes(sides: Sequence[int]) -> list[tuple[int, int]]:
    """Sample shapes for multi-scale training: for every long side in ``sides``, a square,
    a 4:3 landscape and a 3:4 portrait frame, both sides rounded to multiples of 32."""
    shapes = []
    for side in sides:
        short = max(32, round(side * 0.75 / 32) * 32)
        side = max(32, round(side / 32) * 32)
        shapes += [(side, side), (short, side), (side, short)]
    return shapes


class _Batches(torch.utils.data.IterableDataset):
    """Endless batches of :class:`RealDepthData` from a seeded stream (one per worker).

    With ``shapes``, every batch takes one shape drawn from them and as many samples as
    fit ``batch_size`` samples of :attr:`RealDepthData.size` in pixels (at least 2), so a
    step costs about the same at every scale.
    """

    def __init__(
        self,
        data: RealDepthData,
        batch_size: int,
        seed: int,
        shapes: Sequence[tuple[int, int]] = (),
        teacher: str | Path | None = None,
    ) -> None:
        self.data, self.batch_size, self.seed = data, batch_size, seed
        self.shapes = list(shapes)
        self.teacher = teacher

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        rng = random.Random(self.seed + (0 if info is None else 7919 * info.id))
        torch.set_num_threads(1)
        teacher = FeatureTeacher(self.teacher) if self.teacher is not None else None
        budget = self.batch_size * self.data.size[0] * self.data.size[1]
        while True:
            if not self.shapes:
                batch = self.data.batch(rng, self.batch_size)
            else:
                h, w = rng.choice(self.shapes)
                batch = self.data.batch(rng, max(2, round(budget / (h * w))), (h, w))
            if teacher is not None:
                batch = (*batch, teacher_grid(teacher, batch[0]))
            yield batch


# ------------------------------------------------------------------------------ training


def _load_defocus(net: torch.nn.Module, checkpoint: str | Path) -> torch.nn.Module:
    """``net`` with the defocus network of the D2F ``checkpoint`` loaded into it (a smaller
    lite variant grows into it, :meth:`~d2f_core.networks.DefocusNet.load_lite`)."""
    from ..pipeline import D2F

    net.load_lite(D2F.from_checkpoint(checkpoint).defocus_net.state_dict())
    return net


def _on_cpu(state: dict[str, Tensor]) -> dict[str, Tensor]:
    """A state dict with every tensor on the CPU (checkpoints load on any machine)."""
    return {k: v.detach().cpu() for k, v in state.items()}


def _real_data(args: argparse.Namespace) -> RealDepthData:
    """The photos of ``--data`` with the labels of ``--labels``, as the options ask."""
    return RealDepthData(
        args.data,
        args.labels,
        size=(args.crop, args.crop),
        paste=args.paste,
        synth=args.synth,
        layout_teacher=args.layout_teacher,
        scene_weight=args.scene_weight,
        scene=args.scene_targets,
        rescan_every=args.rescan_every,
        standing=args.standing,
        keep_on=args.keep_on if args.keep is not None else None,
        scene_maps=build_defocus_net(args.variant).scene_head is not None,
    )


def train_depth(args: argparse.Namespace) -> Path:
    """Run (or resume) stage 0; returns the path of the last checkpoint."""
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    last = out / "depth_last.pt"
    resuming = last.is_file() and not args.restart
    # the options alone, before the photos are scanned
    if args.head_only and args.init is None and not resuming:
        raise ValueError("--head-only needs --init: the network whose disparity stays as it is")
    if args.head_only and (args.keep is not None or args.distill is not None):
        raise ValueError("--head-only trains the scene head alone: --keep and --distill train "
                         "the rest of the network")  # fmt: skip
    if args.scene_map_weight < 0:
        raise ValueError(f"--scene-map-weight must be >= 0, got {args.scene_map_weight}")
    if args.ema and not 0.0 < args.ema < 1.0:
        raise ValueError(f"--ema must lie in (0, 1), got {args.ema}")
    if args.pack is None and (args.data is None or args.labels is None):
        raise ValueError("give --data and --labels, or --pack")
    if args.pack is not None and (args.data is not None or args.labels is not None):
        raise ValueError("--pack holds the photos and their targets: no --data or --labels")
    if args.pack is not None and (args.keep is not None or args.distill is not None):
        raise ValueError("--keep and --distill need the photos' labels: --data and --labels")
    if args.minutes is not None and args.minutes <= 0:
        raise ValueError(f"--minutes must be positive, got {args.minutes}")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device here")
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # a few batch shapes, each seen many times
    if args.pack is not None:
        from .depth_pack import PackedDepthData

        if "scene" in args.variant:
            raise ValueError("a pack holds no scene maps: a '-scene' --variant needs --data")
        data: RealDepthData = PackedDepthData(
            args.pack, size=(args.crop, args.crop), paste=args.paste, synth=args.synth,
            scene_weight=args.scene_weight, standing=args.standing,
        )  # fmt: skip
    else:
        data = _real_data(args)
    net = build_defocus_net(args.variant)
    if args.init is not None:
        _load_defocus(net, args.init)
        logger.info("defocus network initialised from %s", args.init)
    distiller = None
    head = [] if net.scene_head is None else list(net.scene_head.parameters())
    if args.head_only and not head:
        raise ValueError(f"--head-only needs a '-scene' --variant, got {args.variant!r}")
    ids = {id(q) for q in head}
    trunk = [q for q in net.parameters() if id(q) not in ids]
    groups = [] if args.head_only else [{"params": trunk, "lr_scale": 1.0}]
    if args.head_only:  # the disparity stays exactly the initial network's
        for q in trunk:
            q.requires_grad_(False)
    if head:
        # the scene head starts untrained on a trained decoder: it learns ten times faster
        groups.append({"params": head, "lr_scale": 10.0})
    if args.distill is not None:
        distiller = Distiller(net.encoder.channels, args.distill_channels)
        # the projection starts at zero and must catch up with a trained encoder before
        # its gradient says anything to it: it learns ten times faster
        groups.append({"params": list(distiller.parameters()), "lr_scale": 10.0})
        encoder_feats: list[Tensor] = []
        net.encoder.register_forward_hook(lambda _m, _i, out: encoder_feats.append(out))
    keeper = None
    if args.keep is not None:
        keeper = _load_defocus(build_defocus_net(args.variant), args.keep)
        keeper.eval().requires_grad_(False)
        logger.info("keep term: weight %g towards %s", args.keep_weight, args.keep)
    net.to(device)
    if keeper is not None:
        keeper.to(device)
    if distiller is not None:
        distiller.to(device)
    opt = torch.optim.AdamW(groups, lr=args.lr, weight_decay=1e-4)
    spent = 0.0  # seconds of training before this run (resumed), for --minutes
    step = 0
    ema = None
    if resuming:
        state = torch.load(last, map_location="cpu", weights_only=True)
        net.load_state_dict(state["state_dict"])
        opt.load_state_dict(state["optimizer"])
        ema = state.get("ema")
        if ema is not None:
            ema = {k: v.to(device) for k, v in ema.items()}
        if distiller is not None:
            if "distiller" not in state:
                raise ValueError(f"{last} was trained without --distill; use --restart")
            distiller.load_state_dict(state["distiller"])
        step = int(state["step"])
        spent = float(state.get("elapsed_s", 0.0))
        logger.info("resumed from %s at step %d", last, step)
    if not args.ema:
        ema = None
    elif ema is None:  # the average starts at the weights training starts from
        ema = {k: v.detach().clone() for k, v in net.state_dict().items()}
    torch.manual_seed(args.seed + step)
    logger.info(
        "stage 0: %s, %d params, %d photos (%d masked), crop %d, batch %d",
        args.variant,
        count_parameters(net),
        len(data.photos),
        len(data.masked),
        args.crop,
        args.batch_size,
    )
    net.train()
    if args.head_only:
        net.eval()  # the trunk's batch norms keep their statistics
    loader = iter(
        torch.utils.data.DataLoader(
            _Batches(
                data,
                args.batch_size,
                args.seed * 1_000_003 + step,
                batch_shapes(args.sides) if args.sides else (),
                teacher=args.distill,
            ),
            batch_size=None,
            num_workers=args.workers,
            pin_memory=device.type == "cuda",
            prefetch_factor=4 if args.workers else None,
        )
    )
    t0 = time.perf_counter()
    log = open(out / "depth_log.jsonl", "a")  # noqa: SIM115
    budget = None if args.minutes is None else 60.0 * args.minutes

    def progress() -> float:
        """How far along the schedule: steps done, or the time budget spent if sooner."""
        done = step / args.steps
        if budget is not None:
            done = max(done, (spent + time.perf_counter() - t0) / budget)
        return min(1.0, done)

    done = progress() >= 1.0
    while not done:
        lr = args.lr * 0.5 * (1 + math.cos(math.pi * progress()))
        warm = min(1.0, (step + 1) / 200)
        for g in opt.param_groups:
            g["lr"] = lr * warm * g.get("lr_scale", 1.0)
        images, targets, relative, keep, maps, *teacher = (
            t.to(device, non_blocking=True) for t in next(loader)
        )
        if net.scene_head is None:
            pred = net(images)
        else:
            pred, logits = net.forward_scene(images)
        loss, parts = depth_loss(pred, targets, relative, args.absolute_weight)
        if net.scene_head is not None:
            scene = scene_map_loss(logits, maps)
            loss = loss + args.scene_map_weight * scene
            parts["maps"] = scene.item()
        if keeper is not None:
            with torch.no_grad():
                reference = keeper(images)
            kept = keep_loss(pred, reference, keep)
            loss = loss + args.keep_weight * kept
            parts["keep"] = kept.item()
        if distiller is not None:
            if not bool(distiller.ready):
                distiller.fix_statistics(teacher[0])
            distill = distiller(encoder_feats.pop(), teacher[0])
            encoder_feats.clear()
            loss = loss + args.distill_weight * distill
            parts["distill"] = distill.item()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        step += 1
        if ema is not None:
            with torch.no_grad():
                for k, v in net.state_dict().items():
                    if v.is_floating_point():
                        ema[k].lerp_(v, 1.0 - args.ema)
                    else:
                        ema[k].copy_(v)
        if step % args.log_every == 0:
            rec = {
                "step": step,
                "loss": loss.item(),
                **parts,
                "lr": lr,
                "elapsed_s": round(time.perf_counter() - t0, 1),
            }
            log.write(json.dumps(rec) + "\n")
            log.flush()
            logger.info("step %d loss %.4f %s", step, loss.item(), parts)
        final = done = progress() >= 1.0
        if step % args.save_every == 0 or final:
            state = {
                "state_dict": _on_cpu(net.state_dict()),
                "elapsed_s": spent + time.perf_counter() - t0,
                "optimizer": opt.state_dict(),
                "step": step,
                "variant": args.variant,
            }
            if distiller is not None:
                state["distiller"] = distiller.state_dict()
            if ema is not None:
                state["ema"] = _on_cpu(ema)
            tmp = last.with_suffix(".tmp")
            torch.save(state, tmp)
            tmp.replace(last)
            if step % args.keep_every == 0 or final:
                torch.save(
                    {
                        "state_dict": _on_cpu(net.state_dict()),
                        "step": step,
                        "variant": args.variant,
                    },  # fmt: skip
                    out / f"depth_{step:06d}.pt",
                )
                if ema is not None:
                    torch.save(
                        {
                            "state_dict": _on_cpu(ema),
                            "step": step,
                            "variant": args.variant,
                            "ema": args.ema,
                        },  # fmt: skip
                        out / f"depth_{step:06d}_ema.pt",
                    )
    log.close()
    return last


def export_checkpoint(
    depth: str | Path, base: str | Path, out: str | Path, overrides: Sequence[str] = ()
) -> Path:
    """A D2F checkpoint: ``base`` with its defocus network replaced by the stage-0 weights
    in ``depth`` (a ``depth_*.pt`` file) and ``KEY=VALUE`` config overrides applied."""
    from ..pipeline import D2F
    from .overrides import apply_overrides

    model = D2F.from_checkpoint(base)
    config = apply_overrides(model.config.to_dict(), overrides)
    state = torch.load(depth, map_location="cpu", weights_only=True)
    variant = state.get("variant", config["defocus"])
    config["defocus"] = variant
    fresh = D2F(config)
    fresh.radiance_net.load_state_dict(model.radiance_net.state_dict())
    fresh.fusion_net.load_state_dict(model.fusion_net.state_dict())
    fresh.defocus_net.load_state_dict(state["state_dict"])
    fresh.save(out)
    return Path(out)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="d2f-train depth",
        description="stage 0: train the defocus network on real photos with depth targets",
    )
    p.add_argument("--data", type=Path, default=None, help="datasets folder")
    p.add_argument("--labels", type=Path, default=None, help="teacher labels (d2f-train label)")
    p.add_argument(
        "--pack",
        type=Path,
        default=None,
        help="train on a pack of the photos and their targets (d2f-train depth-pack) instead "
        "of --data and --labels",
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="a time budget: the learning-rate schedule follows the time spent or the steps "
        "done, whichever is further along, and training ends at either",
    )
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--variant", default="lite")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--crop", type=int, default=256)
    p.add_argument(
        "--sides",
        type=lambda v: [int(x) for x in v.split(",")],
        default=None,
        metavar="A,B,...",
        help="multi-scale: long sides of the batches (square, 4:3 and 3:4 frames; "
        "each batch holds --batch-size crops of --crop in pixels)",
    )
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--paste", type=float, default=0.4)
    p.add_argument("--synth", type=float, default=0.15)
    p.add_argument(
        "--layout-teacher",
        type=float,
        default=0.4,
        help="weight of the depth teacher in the layout; -1: per photo, by its agreement "
        "with the ramp (teacher_weight)",
    )
    p.add_argument("--absolute-weight", type=float, default=0.25)
    p.add_argument(
        "--scene-weight",
        type=float,
        default=1.0,
        help="draw the photos of whole scenes (SUN, Urban100, BSDS) this many times as often",
    )
    p.add_argument(
        "--scene-targets",
        action="store_true",
        help="targets from the scene model (d2f_core.train.scene_targets) on photos whose labels "
        "hold the scene teachers' maps (d2f-train label-scene)",
    )
    p.add_argument(
        "--standing",
        type=float,
        default=0.0,
        help="share of the generated scenes drawn from d2f_core.train.synth.standing (a near post "
        "across the frame, a subject over a far floor, far lights at night)",
    )
    p.add_argument(
        "--rescan-every",
        type=int,
        default=0,
        metavar="N",
        help="look for new label files every N samples (labelling still running)",
    )
    p.add_argument(
        "--distill",
        type=Path,
        default=None,
        metavar="ONNX",
        help="feature distillation from this teacher (the VOC teacher's ASPP features)",
    )
    p.add_argument("--distill-weight", type=float, default=0.2)
    p.add_argument(
        "--keep",
        type=Path,
        default=None,
        metavar="D2F_CHECKPOINT",
        help="hold the network to this checkpoint's relative depth where a photo's target "
        "knows nothing new (outside its subjects, their margins and the sky)",
    )
    p.add_argument("--keep-weight", type=float, default=1.0)
    p.add_argument(
        "--head-only",
        action="store_true",
        help="train the scene head alone; the rest of the network, and its disparity, stay "
        "as --init has them",
    )
    p.add_argument(
        "--scene-map-weight",
        type=float,
        default=0.5,
        help="weight of the scene head's cross-entropy (a '-scene' --variant: subjects, sky)",
    )
    p.add_argument(
        "--keep-on",
        choices=("background", "plain"),
        default="background",
        help="background: every photo outside its subjects, their margins and the sky; "
        "plain: only photos with no subject, weighted by how little sky and ground they show",
    )
    p.add_argument(
        "--ema",
        type=float,
        default=0.0,
        metavar="DECAY",
        help="also keep an exponential moving average of the weights (e.g. 0.99), saved "
        "beside every kept checkpoint as depth_<step>_ema.pt",
    )
    p.add_argument("--distill-channels", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--save-every", type=int, default=100)
    p.add_argument("--keep-every", type=int, default=1000)
    p.add_argument("--workers", type=int, default=1, help="data-loading processes")
    p.add_argument("--init", type=Path, default=None, help="D2F checkpoint to start from")
    p.add_argument("--restart", action="store_true", help="ignore an existing depth_last.pt")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["export"]:
        e = argparse.ArgumentParser(
            prog="d2f-train depth export",
            description="a D2F checkpoint from a base checkpoint and stage-0 weights",
        )
        e.add_argument("depth", type=Path)
        e.add_argument("base", type=Path)
        e.add_argument("out", type=Path)
        e.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
        a = e.parse_args(argv[1:])
        try:
            print(export_checkpoint(a.depth, a.base, a.out, a.set))
        except (ValueError, FileNotFoundError, KeyError) as exc:
            print(f"d2f-train depth export: error: {exc}", file=sys.stderr)
            return 2
        return 0
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    path = train_depth(args)
    print(f"stage 0 checkpoint: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
