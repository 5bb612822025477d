"""Stage 0's samples: real photos with the targets their labels make, pasted cut-outs and
generated scenes (:class:`RealDepthData`; ``d2f_core.train.depth_train`` describes what each
teaches), and :func:`resize_array`, the array resize they and the benchmarks share."""

from __future__ import annotations

import itertools
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..io import load_image
from ..io.formats import exif_orientation
from ..networks import SCENE_MAPS
from ..sizing import scaled_size
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
from .teachers import Photo, iter_photos, read_label, read_mask, subject_cutout

__all__ = ["SCENE_SOURCES", "DepthSample", "RealDepthData", "resize_array"]

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


#: the photometric jitters of :func:`photometric_jitter`
JITTERS = ("mild", "strong")


def check_jitter(kind: str) -> str:
    """``kind`` if it names one of :data:`JITTERS`; else a ``ValueError`` that lists them."""
    if kind not in JITTERS:
        raise ValueError(f"jitter must be one of {', '.join(JITTERS)}, got {kind!r}")
    return kind


def check_share(value: float, name: str) -> float:
    """``value`` if it is a share in [0, 1], else a ValueError naming ``name``."""
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must be a share in [0, 1], got {value}")
    return float(value)


def photometric_jitter(img: np.ndarray, rng: random.Random, kind: str = "mild") -> np.ndarray:
    """A training photo (``H x W x 3`` in 0..1) with a random exposure: ``"mild"``, a gain of
    0.8-1.2 and a gamma of 0.8-1.25; ``"strong"`` adds, each at random, a white balance
    (channel gains 0.9-1.1), a saturation of 0.5-1.5 (or grey, one time in ten), a
    Gaussian blur (sigma 0.5-1.5 px) and sensor noise (sigma up to 0.03), so that depth
    cannot be read off one camera's colours and sharpness. The depth target is unchanged.
    """
    gain = rng.uniform(0.8, 1.2)
    gamma = rng.uniform(0.8, 1.25)
    img = np.clip(img * gain, 0, 1) ** gamma
    if check_jitter(kind) == "mild":
        return img
    img = img * np.array([rng.uniform(0.9, 1.1) for _ in range(3)], np.float32)
    grey = img @ np.array([0.299, 0.587, 0.114], np.float32)
    saturation = 0.0 if rng.random() < 0.1 else rng.uniform(0.5, 1.5)
    img = grey[..., None] + saturation * (img - grey[..., None])
    if rng.random() < 0.2:
        from scipy.ndimage import gaussian_filter

        img = gaussian_filter(img, sigma=(rng.uniform(0.5, 1.5),) * 2 + (0,))
    if rng.random() < 0.2:
        noise = np.random.default_rng(rng.randrange(1 << 30)).normal(size=img.shape)
        img = img + rng.uniform(0.0, 0.03) * noise.astype(np.float32)
    return np.clip(img, 0, 1).astype(np.float32)


_FRAME_TRIES = 8  # draws of a photo whose orientation matches the frame, at most


def _same_orientation(aspect: float, frame: float) -> bool:
    """Whether a photo of width/height ``aspect`` fills a frame of width/height ``frame``
    without losing much of either side: both landscape, both portrait, or either of them
    (nearly) square, within 10 %."""
    if 0.9 <= frame <= 1.1 or 0.9 <= aspect <= 1.1:
        return True
    return (aspect > 1.0) == (frame > 1.0)


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
        jitter: the photometric jitter of a photo's sample (:func:`photometric_jitter`).
        frame_match: share of the photo samples whose photo is drawn again (up to
            :data:`_FRAME_TRIES` times) until it is landscape in a landscape frame and portrait
            in a portrait one, as the network reads a whole photo; otherwise a portrait photo
            in a landscape frame loses nearly half its height, its sky or its ground.
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
        jitter: str = "mild",
        frame_match: float = 0.0,
    ) -> None:
        self.jitter = check_jitter(jitter)
        self.frame_match = check_share(frame_match, "frame_match")
        self._aspects: dict[str, float] = {}
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
        img = self._load(photo)
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
        img = self._load(photo)
        size = scaled_size(img.shape[:2], long_side / max(img.shape[:2]), None)
        img, alpha, layout, keep, _ = self._whole(photo, img, size)
        return np.clip(img, 0.0, 1.0), _target(layout, alpha), keep

    def _load(self, photo: Photo) -> np.ndarray:
        """The photo, H x W x 3 float32 in [0, 1]."""
        return load_image(photo.path)

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

    def _subject(self, rng: random.Random) -> tuple[np.ndarray, np.ndarray] | None:
        """A random masked photo's subject cut to its bounding box: (rgb h x w x 3 in [0, 1],
        mask h x w in {0, 1}), or None for an empty mask."""
        cut = subject_cutout(rng.choice(self.masked))
        return None if cut is None else (cut[0], cut[1])

    def _cutout(
        self, rng: random.Random, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """A subject cut out of a random masked photo (:meth:`_subject`), scaled to a quarter
        to four fifths of ``size``'s short side and mirrored half the time: (rgb h x w x 3,
        feathered alpha h x w)."""
        cut = self._subject(rng)
        if cut is None or cut[1].sum() < 64:
            return None
        crop, mask = cut
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

    def _draw(self, rng: random.Random) -> Photo:
        """One training photo, drawn by :attr:`scene_weight`."""
        if self.scene_weight == 1.0:
            return rng.choice(self.photos)
        return rng.choices(self.photos, cum_weights=self._cum_weights)[0]

    def _aspect(self, photo: Photo) -> float:
        """The photo's width over its height, read from its header once."""
        aspect = self._aspects.get(photo.key)
        if aspect is None:
            from PIL import Image

            with Image.open(photo.path) as im:
                w, h = im.size
                if exif_orientation(im) >= 5:  # shown turned a quarter, as load_image turns it
                    w, h = h, w
            aspect = self._aspects[photo.key] = w / h
        return aspect

    def sample(self, rng: random.Random, size: tuple[int, int] | None = None) -> DepthSample:
        """One sample of ``size`` (``(H, W)``; default :attr:`size`)."""
        size = self.size if size is None else size
        self._drawn += 1
        if self.rescan_every and self._drawn % self.rescan_every == 0:
            self._scan()
            self._weigh()
        if rng.random() < self.synth:
            return self._synth(rng, size)
        photo = self._draw(rng)
        if self.frame_match and rng.random() < self.frame_match:
            for _ in range(_FRAME_TRIES):
                if _same_orientation(self._aspect(photo), size[1] / size[0]):
                    break
                photo = self._draw(rng)
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
        img = photometric_jitter(img, rng, self.jitter)
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
