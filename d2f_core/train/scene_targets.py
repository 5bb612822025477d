"""Stage-0 depth targets from a scene model: sky at the back, a ground plane, things standing.

The rules live in :mod:`d2f_core.depth.layout`, where the ``scene`` depth source applies them at
inference; this module adds what only training needs (:func:`taught_mask`, the label files).

The labels of :mod:`d2f_core.train.scene_teachers` (ADE20K classes, U^2-Net-p silhouettes) and of
:mod:`d2f_core.train.teachers` (VOC foreground, indoor depth) are turned into one relative disparity
per photo (0 = farthest, 1 = nearest), the target the defocus network learns in stage 0:

1. **Ground** (floor, road, grass, sidewalk, earth, water, sand, field...) is a plane seen by a
   level camera: its disparity grows linearly from the horizon row to the bottom of the frame
   (for a flat ground at camera height ``h``, depth ``Z = f h / (y - y_h)``). Only ground that
   reaches the frame's edge counts (:func:`~d2f_core.depth.layout.open_ground`): a patch that
   something surrounds (the coffee in a cup seen from above, read as floor) is part of it.
2. **Sky** is the farthest thing in the frame.
3. **Everything else stands** on the ground where it touches it: each pixel takes the
   ground's disparity at the first ground pixel below it in its column (a building, a tree, a
   wall), or the frame's bottom when none is below (it reaches out of the frame towards the
   camera). Pixels that are none of these keep the older layout (:func:`scene_layout`).
4. Where the photo shows no scene (a close-up: little sky and ground) the layout is today's
   (the "bottom is near" ramp blended with the indoor teacher), and indoors, where walls,
   floor and ceiling cover most of the frame, the indoor teacher keeps its weight.
5. **Subjects** (a human mask, else U^2-Net-p's silhouette where it is a clear, compact
   subject, and the VOC teacher's foreground), and **near occluders** that cross the frame
   (poles, columns, street lights, narrow trunks spanning its height), stand at the ground
   where they touch it and nearer than what surrounds them
   (:func:`subject_target`).
"""

from __future__ import annotations

import numpy as np

from ..depth.layout import (  # noqa: F401  (the targets' rules live with the scene source)
    GROUND,
    OCCLUDERS,
    ROOM,
    SKY,
    ground_plane,
    horizon_row,
    in_classes,
    normalise,
    occluder_alpha,
    ramp,
    scene_layout,
    scene_strength,
    scene_subjects,
    scene_target,
    silhouette_alpha,
    stand_on_scene,
    subject_target,
    teacher_layout,
    teacher_subject,
    teacher_weight,
)

__all__ = [
    "normalise",
    "ramp",
    "teacher_layout",
    "teacher_subject",
    "teacher_weight",
    "GROUND",
    "OCCLUDERS",
    "ROOM",
    "SKY",
    "ground_plane",
    "horizon_row",
    "occluder_alpha",
    "scene_layout",
    "scene_strength",
    "scene_subjects",
    "scene_target",
    "silhouette_alpha",
    "taught_mask",
    "subject_target",
]


def taught_mask(
    alpha: np.ndarray | None, ade: np.ndarray | None = None, margin: float = 0.02
) -> np.ndarray:
    """Where a photo's target says something the scene model knows, ``H x W`` bool: its
    subjects (``alpha >= 0.5``) grown by ``margin`` of the frame's long side (their edges and
    what stands just behind them), and its sky.

    Stage 0's keep term (``d2f-train depth --keep``) leaves these pixels to the target and
    holds the rest to an earlier network's relative depth.
    """
    from scipy.ndimage import distance_transform_edt

    shape = alpha.shape if alpha is not None else ade.shape
    out = np.zeros(shape, bool)
    if alpha is not None and (alpha >= 0.5).any():
        r = max(1, round(margin * max(shape)))
        # within r of a subject pixel: a dilation by a disc of radius r, in one pass
        out = distance_transform_edt(alpha < 0.5) <= r
    if ade is not None:
        out |= in_classes(ade, SKY)
    return out


def read_scene_label(path, size: tuple[int, int]) -> dict | None:
    """The scene labels of a label file (:func:`d2f_core.train.scene_teachers.label_scene_photos`)
    at ``size`` (``(H, W)``): ``{"ade": uint8 classes, "sal": float32 [0, 1] or None}``;
    ``None`` for a file written without them."""
    from PIL import Image

    h, w = size
    with np.load(path) as z:
        if "ade" not in z.files:
            return None
        ade = np.asarray(Image.fromarray(z["ade"]).resize((w, h), Image.NEAREST))
        sal = None
        if "sal" in z.files:
            sal_img = Image.fromarray(z["sal"]).resize((w, h), Image.BILINEAR)
            sal = np.asarray(sal_img, dtype=np.float32) / 255.0
    return {"ade": ade, "sal": sal}
