"""The maps ``d2f-bench depth`` scores, as predictors (photo -> ``H x W`` disparity): the ramp,
the shipped network, and the labelling teachers run by their own runtimes with the stage-0
targets built from them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..train.depth_train import resize_array
from .depth_metrics import eval_size as _eval_size
from .depth_metrics import rankdata

__all__ = [
    "Predictor",
    "network_predictor",
    "network_predictors",
    "ramp_predictor",
    "rank_mix",
    "source_predictor",
    "subject_blend_predictor",
    "teacher_predictors",
    "weight_specs",
]


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


def source_predictor(source: str, weights: str | Path | None = None) -> Predictor:
    """The disparity :meth:`D2F.prepare` gives a photo from the depth source ``source``
    (``"scene"``, ``"d2f"``; :mod:`d2f_core.depth.sources`), with the network in ``weights``
    (the shipped one by default)."""
    from ..pipeline import D2F

    model = D2F.from_pretrained(weights)
    return _remember_last(lambda image: model.prepare(image, depth=source).disparity_full())


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
