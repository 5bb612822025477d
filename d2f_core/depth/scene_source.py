"""The ``scene`` depth source: the scene teachers run at inference, the network's subjects on top.

For a photo with no depth of its own, the map is built in four steps, at a working size of
:data:`WORK_SIDE` px on the long side:

1. **Parse** the scene (ADE20K classes, :mod:`d2f_core.teachers.deeplab`).
2. **The other teachers, where the parse needs them**: the indoor depth model
   (:mod:`~d2f_core.teachers.fastdepth`) gives the layout of a photo that shows little sky and
   ground, or a room; the silhouette model (:mod:`~d2f_core.teachers.u2net`) finds the subject
   of a photo that is not a room; the VOC model (:mod:`~d2f_core.teachers.deeplab`) the
   objects. A teacher whose output cannot change the map is not run
   (:func:`needed_teachers`), and :attr:`SceneMaps.ran` says which ran.
3. **The scene layout** (:mod:`d2f_core.depth.layout`): sky farthest, a ground plane, things
   standing on it, subjects and near occluders in front of what surrounds them. In a room
   (:func:`~d2f_core.depth.layout.is_room`) furniture (VOC's chair, dining table, sofa and
   tv) stays where the room puts it: it is no subject.
4. **The network's subjects and map**: the defocus network's scene head stands its subjects
   on that map, as it stands them on its own (:meth:`d2f_core.pipeline.D2F.stand`; in a room
   not on furniture), and the network's own map is blended in by :data:`NETWORK_SHARE`
   (the network reads close-ups the teachers cannot: a flower, a face, an object on a
   table).

The teachers are given as an object with four methods (:class:`Teachers`), so the same map
can be built from the torch ports (:class:`PortedTeachers`, what ships) or from the original
files run by their own runtimes (``d2f-bench depth --teachers``).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from PIL import Image

from ..io.save import to_uint8
from ..rendering.inputs import image_tensor
from ..sizing import resize
from . import layout as L

__all__ = [
    "LABEL_SIDE",
    "NETWORK_SHARE",
    "PARSE_SIDE",
    "READ_SIDE",
    "SUBJECT_BLEND",
    "WORK_SIDE",
    "PortedTeachers",
    "SceneMaps",
    "Teachers",
    "foreground_label",
    "label_size",
    "needed_teachers",
    "reading_copy",
    "scene_maps",
    "shared_teachers",
    "work_size",
]

#: long side (px) of the map the scene source builds (the size stage 0's targets were made at)
WORK_SIDE = 384
#: long side (px) of the scene parse and the silhouette before they are brought to the map's
#: size (the size the training labels were stored at)
LABEL_SIDE = 256
#: share of the defocus network's own map in the ``scene`` map (12 measured photos, with the
#: subjects stood at 0.4: 0 gives 0.760 mean Spearman and 11 over the ramp, 0.15 gives 0.761
#: and 12, 0.35 gives 0.752). The network reads the generated scenes it was trained on
#: better: on 24 held-out generated pairs at their focus, 0.15 renders 26.46 dB, 0.5 26.62
#: and the network alone 26.92
NETWORK_SHARE = 0.15
#: long side (px) of the copy of a large photo that the teachers and the network read
#: (:func:`reading_copy`)
READ_SIDE = 1024
#: side (px) of the square the ADE20K parse reads (the original graph reads 513; the network
#: is fully convolutional). The scene map on the 12 measured photos / the held-out subject
#: AUC (within 8 px), the maps straight from :func:`scene_maps`: 513 px 0.757 / 0.883
#: (0.818), 385 px 0.761 / 0.884 (0.819), 321 px 0.755 / 0.882 (0.817), 257 px 0.754 /
#: 0.880 (0.814); the parse takes about (side / 513)^2 of its 0.67 s at 513 on one thread
PARSE_SIDE = 321
#: how far the network's subjects are stood on the scene map (every pixel moved nearer by
#: this much times the square of its subject probability, :meth:`D2F.stand`), in place of
#: the network's own ``config.subject_blend`` (0.4 for the shipped weights). On the 127
#: held-out masked photos a subject pixel is nearer than a background pixel 0.871 of the
#: time at 0.4, 0.883 at 0.6 and 0.890 at 0.8; the 12 measured photos' mean Spearman is
#: 0.761, 0.757 and 0.751 (12, 12 and 11 over the ramp)
SUBJECT_BLEND = 0.6


def work_size(h: int, w: int, side: int = WORK_SIDE) -> tuple[int, int]:
    """``(h, w)`` of the map for a photo of ``h x w``: its aspect, long side ``side`` (the
    photo's own size when that is smaller)."""
    s = min(side, max(h, w)) / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


def label_size(width: int, height: int, side: int = LABEL_SIDE) -> tuple[int, int]:
    """``(w, h)`` of a teacher's label: the photo's aspect with its long side at ``side``."""
    scale = side / max(width, height)
    return max(1, round(width * scale)), max(1, round(height * scale))


class Teachers(Protocol):
    """What the scene source asks of the teachers, each for a PIL RGB photo."""

    def parse(self, rgb: Image.Image) -> np.ndarray:
        """ADE20K class per pixel, uint8 at :func:`label_size`."""

    def silhouette(self, rgb: Image.Image) -> np.ndarray:
        """Salient-object probability, uint8 (0-255) at :func:`label_size`."""

    def objects(self, rgb: Image.Image) -> np.ndarray:
        """PASCAL VOC class probabilities, float32 257x257x21 (0 is the background)."""

    def depth(self, rgb: Image.Image) -> np.ndarray:
        """The indoor depth model's raw output, uint8 at 224x224 (metres = 0.0717 x value)."""


@dataclass
class SceneMaps:
    """What the scene source found in a photo, at the working size :func:`work_size`.

    Attributes:
        disparity: the map, ``h x w`` float32 in [0, 1] (1 = nearest).
        ade: the ADE20K class per pixel.
        ran: the teachers that ran, in order (``"parse"``, ``"depth"``, ``"silhouette"``,
            ``"objects"``), then ``"network"`` when the defocus network's subjects and map
            were used.
        strength: how much of a scene the photo shows (:func:`~.layout.scene_strength`).
    """

    disparity: np.ndarray
    ade: np.ndarray
    ran: list[str] = field(default_factory=list)
    strength: float = 0.0


def needed_teachers(ade: np.ndarray) -> tuple[bool, bool]:
    """``(depth, silhouette)``: whether the indoor depth model and the silhouette model can
    change the map of a photo with scene parse ``ade``.

    - The indoor model's layout is weighed by ``1 - strength`` of the scene
      (:func:`~.layout.scene_layout`); where sky and ground cover a quarter of the frame and
      more and the photo is not a room, the strength is 1 whatever its weight, so it is not run.
    - The silhouette is never used in a room (:func:`~.layout.silhouette_alpha`).
    """
    room = L.is_room(ade)
    scene = float(L.in_classes(ade, L.SKY).mean() + L.in_classes(ade, L.GROUND).mean())
    full_scene = float(np.clip((scene - 0.05) / 0.2, 0.0, 1.0)) >= 1.0
    return room or not full_scene, not room


def _rgb(image: np.ndarray) -> Image.Image:
    return Image.fromarray(to_uint8(image, "photo"))


def _resized(label: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    h, w = size
    mode = Image.NEAREST if nearest else Image.BILINEAR
    return np.asarray(Image.fromarray(label).resize((w, h), mode))


def scene_maps(
    image: np.ndarray, teachers: Teachers, model: Any = None, size: tuple[int, int] | None = None
) -> SceneMaps:
    """The ``scene`` source's map of ``image`` (``H x W x 3`` float in [0, 1]).

    Args:
        image: the photo.
        teachers: the scene teachers (:class:`PortedTeachers`, or the originals).
        model: a :class:`~d2f_core.pipeline.D2F` whose scene head stands its subjects on the
            map (``None``, or a network without the head: the teachers' map alone).
        size: the map's ``(h, w)``; default :func:`work_size`.
    """
    size = work_size(*image.shape[:2]) if size is None else tuple(size)
    image = reading_copy(image)
    rgb = _rgb(image)
    ran = ["parse"]
    ade = _resized(teachers.parse(rgb), size, nearest=True)
    room = L.is_room(ade)
    need_depth, need_silhouette = needed_teachers(ade)
    if need_depth:
        ran.append("depth")
        disp = L.teacher_disparity(teachers.depth(rgb), size)
        weight = L.teacher_weight(disp)
        old_layout = L.teacher_layout(disp, weight)
    else:  # weighed by 0 in the layout
        weight, old_layout = 0.0, L.ramp(*size)
    sal = None
    if need_silhouette:
        ran.append("silhouette")
        sal = _resized(teachers.silhouette(rgb), size, nearest=False).astype(np.float32) / 255.0
    ran.append("objects")
    probs = np.asarray(teachers.objects(rgb), dtype=np.float32)
    furniture = probs[..., list(L.FURNITURE_VOC)].sum(-1) if room else None
    fg = _resized(foreground_label(probs, furniture), size, nearest=False)
    target = L.scene_target(
        ade, old_layout, weight, sal=sal, voc=L.teacher_subject(fg.astype(np.float32) / 255.0)
    )
    if model is not None:
        ran.append("network")
        if furniture is not None:
            furniture = np.clip(_resized_float(furniture, size), 0.0, 1.0)
        target = _with_network(model, image, target, furniture)
    strength = L.scene_strength(ade, weight)
    return SceneMaps(target.astype(np.float32), ade, ran, strength)


def reading_copy(image: np.ndarray | torch.Tensor, side: int = READ_SIDE) -> np.ndarray:
    """``image`` (``H x W x 3``, or a checked ``[1, 3, H, W]`` float tensor) as an ``H x W x
    3`` array with its long side brought down to ``side`` (antialiased) when it is larger:
    every teacher and the network read it at 513 px or less, and one resize of a 12 MP
    photo costs what each teacher's own would (about 0.2 s each on one thread)."""
    tensor = isinstance(image, torch.Tensor)
    h, w = image.shape[-2:] if tensor else image.shape[:2]
    if max(h, w) > side:
        x = image if tensor else image_tensor(image)
        image = resize(x, work_size(h, w, side)).clamp_(0, 1)
    elif not tensor:
        return image
    return image[0].permute(1, 2, 0).contiguous().cpu().numpy()


def foreground_label(probs: np.ndarray, furniture: np.ndarray | None = None) -> np.ndarray:
    """The VOC model's foreground as the training labels stored it, uint8 (0-255): ``1 -
    P(background)``, less ``furniture`` (its furniture's probability) in a room."""
    fg = 1.0 - probs[..., 0]
    if furniture is not None:
        fg = fg - furniture
    return np.round(np.clip(fg, 0.0, 1.0) * 255).astype(np.uint8)


def _resized_float(a: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None, None]
    return resize(t, size)[0, 0].numpy()


def _with_network(
    model: Any, image: np.ndarray, target: np.ndarray, furniture: np.ndarray | None
) -> np.ndarray:
    """``target`` with the subjects of ``model``'s scene head stood on it by
    :data:`SUBJECT_BLEND` (none on ``furniture``, its probability in a room) and the
    network's own map (its subjects stood alike) blended in by :data:`NETWORK_SHARE`."""
    x = image_tensor(image).to(model.device)
    work = resize(x, target.shape).clamp_(0, 1)
    with torch.no_grad():
        d, probs = model.disparity_and_scene_maps(work, refine=True, photo=x, blend=SUBJECT_BLEND)
    if probs is not None:
        maps = resize(probs.float().cpu(), target.shape)[0].clamp_(0, 1).numpy()
        subject = maps[0] if furniture is None else maps[0] * (1.0 - furniture)
        target = model.stand(target, subject, maps[1], SUBJECT_BLEND)
    d = d[0, 0].float().cpu().numpy()
    return (1.0 - NETWORK_SHARE) * target + NETWORK_SHARE * d


class PortedTeachers:
    """The scene teachers as the torch modules of :mod:`d2f_core.teachers`, with the shipped
    weights, each loaded the first time it is asked for (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._modules: dict[str, Any] = {}

    def _get(self, name: str, load: Any) -> Any:
        with self._lock:
            if name not in self._modules:
                self._modules[name] = load()
            return self._modules[name]

    def parse(self, rgb: Image.Image) -> np.ndarray:
        from ..teachers import deeplab

        net = self._get("ade20k", deeplab.load_ade20k)
        return deeplab.ade20k_labels(rgb, label_size(*rgb.size), net, side=PARSE_SIDE)

    def silhouette(self, rgb: Image.Image) -> np.ndarray:
        from ..teachers import u2net

        net = self._get("u2netp", u2net.load_u2netp)
        return u2net.silhouette_label(rgb, label_size(*rgb.size), net)

    def objects(self, rgb: Image.Image) -> np.ndarray:
        from ..teachers import deeplab

        net = self._get("voc", deeplab.load_voc)
        return deeplab.voc_probabilities(rgb, net)

    def depth(self, rgb: Image.Image) -> np.ndarray:
        from ..teachers import fastdepth

        net = self._get("fastdepth", fastdepth.load_fastdepth)
        return fastdepth.depth_uint8(rgb, net)


_SHARED: list[PortedTeachers] = []
_SHARED_LOCK = threading.Lock()


def shared_teachers() -> PortedTeachers:
    """One :class:`PortedTeachers` for the process (the modules load once, on first use)."""
    with _SHARED_LOCK:
        if not _SHARED:
            _SHARED.append(PortedTeachers())
        return _SHARED[0]
