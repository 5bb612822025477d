"""A photo's depth from its scene parse: sky at the back, a ground plane, things standing.

The scene teachers' maps (:mod:`d2f_core.teachers`: ADE20K classes, U^2-Net-p silhouettes, the
VOC foreground, the indoor depth) are turned into one relative disparity per photo (0 =
farthest, 1 = nearest). The ``scene`` depth source (:mod:`d2f_core.depth.scene_source`) builds
it at inference; stage 0 (:mod:`d2f_core.train.scene_targets`) trained the defocus network
towards the same map.

1. **Ground** (floor, road, grass, sidewalk, earth, water, sand, field...) is a plane seen by a
   level camera: its disparity grows linearly from the horizon row to the bottom of the frame
   (for a flat ground at camera height ``h``, depth ``Z = f h / (y - y_h)``).
2. **Sky** is the farthest thing in the frame.
3. **Everything else stands** on the ground where it touches it: each pixel takes the
   ground's disparity at the first ground pixel below it in its column (a building, a tree, a
   wall), or the frame's bottom when none is below (it reaches out of the frame towards the
   camera). Pixels that are none of these keep the older layout (:func:`scene_layout`).
4. Where the photo shows no scene (a close-up: little sky and ground) the layout is the
   "bottom is near" ramp blended with the indoor teacher, and indoors, where walls, floor and
   ceiling cover most of the frame, the indoor teacher keeps its weight.
5. **Subjects** (a human mask, else U^2-Net-p's silhouette where it is a clear, compact
   subject, and the VOC teacher's foreground), and **near occluders** that cross the frame
   (poles, columns, street lights, narrow trunks spanning its height), stand at the ground
   where they touch it and nearer than what surrounds them (:func:`subject_target`).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "FURNITURE_VOC",
    "GROUND",
    "OCCLUDERS",
    "ROOM",
    "ROOM_SHARE",
    "SKY",
    "feather",
    "ground_plane",
    "horizon_row",
    "in_classes",
    "is_room",
    "normalise",
    "occluder_alpha",
    "open_ground",
    "ramp",
    "scene_layout",
    "scene_strength",
    "scene_subjects",
    "scene_target",
    "silhouette_alpha",
    "stand_on_scene",
    "subject_target",
    "teacher_disparity",
    "teacher_layout",
    "teacher_subject",
    "teacher_weight",
]

#: ADE20K class indices (``ade20k_labels_151.txt``; 0 is "other")
SKY = (3,)
GROUND = (4, 7, 10, 12, 14, 22, 27, 29, 30, 47, 53, 55, 61, 92, 95, 110, 129)
ROOM = (1, 4, 6, 9, 15, 19, 23, 25, 36, 63, 64)
#: things that may cross the frame in front of a scene: pole, column, streetlight,
#: traffic light, signboard, tree (only a narrow part spanning the height counts)
OCCLUDERS = (94, 43, 88, 137, 44, 5)


# ------------------------------------------------------------------- the ramp, the older layout


#: PASCAL VOC classes that are a room's furniture (chair, dining table, sofa, tv monitor): in a
#: room they stand where the room does, and are not made subjects (:func:`is_room`)
FURNITURE_VOC = (9, 11, 18, 20)
#: share of the frame that walls, floor, ceiling and the like cover in a room
ROOM_SHARE = 0.4


def is_room(ade: np.ndarray) -> bool:
    """Whether the scene parse ``ade`` shows a room: :data:`ROOM` classes over
    :data:`ROOM_SHARE` of the frame."""
    return float(in_classes(ade, ROOM).mean()) >= ROOM_SHARE


def ramp(height: int, width: int) -> np.ndarray:
    """``H x W`` float32: 0 at the top row, 1 at the bottom row ("the bottom is near")."""
    col = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    return np.broadcast_to(col, (height, width)).copy()


def teacher_weight(teacher: np.ndarray, cap: float = 0.8) -> float:
    """Weight of the depth teacher in a photo's layout: its correlation with the ramp,
    clipped to ``[0, cap]``.

    The indoor teacher is right on rooms, streets and ground planes, where its map falls
    off towards the top like the ramp, and wrong on close-ups and dark scenes, where it
    does not. On the 12 measured-depth photos of ``d2f-bench depth`` (teacher and VOC subject
    run on each), the targets built with a fixed 0.4 blend score 0.689 mean Spearman, with
    this weight 0.722 (the teacher alone 0.548, the ramp 0.607). A teacher that disagrees
    with the ramp is not trusted.
    """
    h, w = teacher.shape
    r = np.broadcast_to(np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None], (h, w))
    t = teacher - teacher.mean()
    rr = r - r.mean()
    denom = float(np.sqrt((t * t).sum() * (rr * rr).sum()))
    c = float((t * rr).sum()) / denom if denom > 0 else 0.0
    return float(np.clip(c, 0.0, cap))


def teacher_subject(
    fg: np.ndarray, min_area: float = 0.01, max_area: float = 0.8
) -> np.ndarray | None:
    """The subject alpha of a photo without a mask: the VOC teacher's foreground ``fg``,
    ramped from 0.3 to 0.7 and feathered by a pixel, where it covers ``min_area`` to
    ``max_area`` of the frame; ``None`` elsewhere (no subject, or the whole frame)."""
    area = float((fg >= 0.5).mean())
    if not min_area <= area <= max_area:
        return None
    return feather(np.clip((fg - 0.3) / 0.4, 0, 1), 1.0)


def teacher_layout(teacher: np.ndarray, weight: float = -1.0) -> np.ndarray:
    """A photo's layout: the ramp blended with the depth teacher's ranked disparity, at
    ``weight`` of the teacher, or per photo by :func:`teacher_weight` when negative."""
    h, w = teacher.shape
    wt = teacher_weight(teacher) if weight < 0 else weight
    return ((1 - wt) * ramp(h, w) + wt * teacher).astype(np.float32)


def normalise(t: np.ndarray) -> np.ndarray:
    lo, hi = float(t.min()), float(t.max())
    return ((t - lo) / max(hi - lo, 1e-6)).astype(np.float32)


def in_classes(ade: np.ndarray, classes: tuple[int, ...]) -> np.ndarray:
    """Where ``ade``'s class is one of ``classes``, ``H x W`` bool."""
    return np.isin(ade, np.asarray(classes, dtype=ade.dtype))


def horizon_row(ade: np.ndarray) -> float:
    """The horizon as a fraction of the height (0 = top row): just above the highest ground
    seen, but not below the lowest sky; 0 when the photo shows no ground."""
    h = ade.shape[0]
    ground = in_classes(ade, GROUND)
    if ground.mean() < 0.01:
        return 0.0
    rows = np.nonzero(ground)[0]
    top = float(np.percentile(rows, 5)) / max(h - 1, 1)
    sky = in_classes(ade, SKY)
    if sky.mean() >= 0.01:
        sky_low = float(np.percentile(np.nonzero(sky)[0], 95)) / max(h - 1, 1)
        top = min(top, max(sky_low, 0.0))
    return float(np.clip(top - 0.03, 0.0, 0.95))


def ground_plane(height: int, width: int, horizon: float) -> np.ndarray:
    """``H x W`` disparity of a flat ground below ``horizon`` (a fraction of the height):
    0 at the horizon, 1 at the bottom row, linear in the row between."""
    y = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None]
    plane = np.clip((y - horizon) / max(1.0 - horizon, 1e-3), 0.0, 1.0)
    return np.broadcast_to(plane, (height, width)).astype(np.float32)


def open_ground(ade: np.ndarray) -> np.ndarray:
    """The ground a scene stands on, ``H x W`` bool: the ground classes where they reach
    the frame's edge. A patch of "ground" that something surrounds (the coffee in a cup seen
    from above, read as floor) is part of that thing, not a floor in the distance."""
    from scipy.ndimage import label

    ground = in_classes(ade, GROUND)
    parts, _ = label(ground)
    edge = np.concatenate([parts[0], parts[-1], parts[:, 0], parts[:, -1]])
    return np.isin(parts, edge[edge > 0])


def _standing(ground: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Every pixel's disparity where its column next meets the ``ground`` below it (the
    frame's bottom, 1, when it never does): things stand where they touch the ground."""
    h, w = ground.shape
    out = np.empty((h, w), np.float32)
    cur = np.ones(w, np.float32)
    for y in range(h - 1, -1, -1):
        cur = np.where(ground[y], plane[y], cur)
        out[y] = cur
    return out


def scene_strength(ade: np.ndarray, teacher_weight: float = 0.0) -> float:
    """How much of a scene the photo shows, in [0, 1]: 1 when sky and ground cover a quarter
    of the frame or more, 0 on a close-up; indoors (walls, floor, ceiling over 40 % of the
    frame) reduced by the indoor teacher's weight ``teacher_weight``
    (:func:`scene_layout` blends its model in by this much)."""
    scene = float(in_classes(ade, SKY).mean() + in_classes(ade, GROUND).mean())
    strength = float(np.clip((scene - 0.05) / 0.2, 0.0, 1.0))
    if is_room(ade):
        strength *= 1.0 - float(teacher_weight)
    return strength


def scene_layout(
    ade: np.ndarray, old_layout: np.ndarray, teacher_weight: float = 0.0
) -> tuple[np.ndarray, float]:
    """``(layout, strength)``: the scene model's disparity blended with ``old_layout`` (the
    ramp and indoor teacher of :func:`teacher_layout`) by how much of a
    scene the photo shows.

    ``strength`` is 1 when sky and ground cover a quarter of the frame or more and 0 on a
    close-up; indoors (walls, floor, ceiling over 40 % of the frame) it is reduced by the
    indoor teacher's own weight ``teacher_weight``, which is right there.
    """
    h, w = ade.shape
    sky = in_classes(ade, SKY)
    ground = open_ground(ade)
    strength = scene_strength(ade, teacher_weight)
    if strength <= 0.0:
        return old_layout.astype(np.float32), 0.0
    plane = ground_plane(h, w, horizon_row(ade))
    model = _standing(ground, plane)
    model = np.where(ground, plane, model)
    model = np.where(sky, 0.0, np.maximum(model, 0.05))
    # columns meet the ground at different rows behind clutter: smooth across, keep the sky
    from scipy.ndimage import uniform_filter1d

    model = np.where(sky, 0.0, uniform_filter1d(model, size=max(3, w // 24), axis=1))
    layout = strength * model + (1.0 - strength) * old_layout
    return layout.astype(np.float32), strength


def silhouette_alpha(
    sal: np.ndarray,
    ade: np.ndarray | None = None,
    min_area: float = 0.01,
    max_area: float = 0.6,
    min_clarity: float = 0.6,
) -> np.ndarray | None:
    """U^2-Net-p's silhouette as a subject alpha where it is a clear, compact subject, else
    ``None``.

    ``sal`` is the silhouette in [0, 1]. It is used when its confident part covers
    ``min_area`` to ``max_area`` of the frame, when it is clear (of the pixels above 0.1, the
    share that are above 0.5 or below... : mean distance from 0.5, doubled, at least
    ``min_clarity``), and not in a room (walls, floor, ceiling over 40 % of the frame, where a
    silhouette is a shelf or a doorway). Parts under a tenth of the largest are dropped.
    """
    from skimage.measure import label

    hard = sal >= 0.5
    area = float(hard.mean())
    if not min_area <= area <= max_area:
        return None
    soft = sal[sal > 0.1]
    clarity = float(np.mean(np.abs(soft - 0.5)) * 2) if soft.size else 0.0
    if clarity < min_clarity:
        return None
    if ade is not None and is_room(ade):
        return None
    parts = label(hard, connectivity=2)
    sizes = np.bincount(parts.ravel())[1:]
    keep = np.zeros_like(hard)
    for idx, n in enumerate(sizes, start=1):
        if n >= 0.1 * sizes.max():
            keep |= parts == idx
    from skimage.morphology import dilation, disk

    near = dilation(keep, disk(2))
    return np.where(near, np.clip((sal - 0.3) / 0.4, 0.0, 1.0), 0.0).astype(np.float32)


def occluder_alpha(ade: np.ndarray, min_height: float = 0.8, max_width: float = 0.3) -> np.ndarray:
    """Parts of the classes :data:`OCCLUDERS` that span ``min_height`` of the frame's height
    and at most ``max_width`` of its width (a post, a pole, a trunk in front of a scene), as a
    {0, 1} alpha."""
    from skimage.measure import label, regionprops

    h, w = ade.shape
    out = np.zeros((h, w), np.float32)
    cand = in_classes(ade, OCCLUDERS)
    if not cand.any():
        return out
    parts = label(cand, connectivity=2)
    for region in regionprops(parts):
        y0, x0, y1, x1 = region.bbox
        if (y1 - y0) >= min_height * h and (x1 - x0) <= max_width * w:
            out[parts == region.label] = 1.0
    return out


def subject_target(
    layout: np.ndarray, mask: np.ndarray, lift: float = 0.05, min_pixels: int = 16
) -> np.ndarray:
    """Disparity target: ``layout`` with every connected part of ``mask`` stood on it.

    Args:
        layout: ``H x W`` disparity of the scene without the subject (1 = nearest).
        mask: ``H x W`` soft subject alpha in [0, 1].
        lift: each part is at least this much nearer than the layout's 90th percentile
            around it (a ring a tenth of the frame wide), so it stands out from what
            surrounds it even where the layout there is flat.
        min_pixels: parts smaller than this keep the layout.

    Returns:
        ``H x W`` float32 in [0, 1], ``alpha * subject + (1 - alpha) * layout``.
    """
    from scipy.ndimage import binary_dilation
    from skimage.measure import label
    from skimage.morphology import dilation, disk

    h, w = layout.shape
    hard = mask >= 0.5
    parts = label(hard, connectivity=2)
    subject = layout.copy()
    ring_radius = max(2, int(0.1 * max(h, w)))
    for idx in range(1, int(parts.max()) + 1):
        part = parts == idx
        n = int(part.sum())
        if n < min_pixels:
            continue
        rows = np.nonzero(part.any(axis=1))[0]
        bottom = rows[-1]
        contact = float(np.median(layout[bottom][part[bottom]]))
        # the ring around the part, at quarter resolution for speed
        small = part[::4, ::4]
        grown = dilation(small, disk(max(1, ring_radius // 4)))
        ring = grown & ~small
        # what lies below the part's lowest row is the ground in front of it, not behind
        ring[bottom // 4 + 1 :] = False
        around = layout[::4, ::4][ring]
        floor = float(np.percentile(around, 90)) + lift if around.size else contact
        value = min(1.0, max(contact, floor))
        grow = binary_dilation(part, disk(2))  # cover the soft rim of the part
        subject[grow] = value
    return (mask * subject + (1.0 - mask) * layout).astype(np.float32)


def scene_target(
    ade: np.ndarray,
    old_layout: np.ndarray,
    teacher_weight: float = 0.0,
    mask: np.ndarray | None = None,
    sal: np.ndarray | None = None,
    voc: np.ndarray | None = None,
) -> np.ndarray:
    """The stage-0 target of one photo (see the module docstring), ``H x W`` float32 in
    [0, 1], 1 = nearest.

    Args:
        ade: ADE20K class per pixel, ``H x W`` (any integer type).
        old_layout: the ramp-and-teacher layout at the same size.
        teacher_weight: the indoor teacher's weight in ``old_layout``.
        mask: the human subject mask in [0, 1], when the photo has one (it wins).
        sal: U^2-Net-p's silhouette in [0, 1] (:func:`silhouette_alpha` decides).
        voc: the VOC teacher's subject alpha (:func:`teacher_subject`).
    """
    return stand_on_scene(ade, old_layout, teacher_weight, scene_subjects(ade, mask, sal, voc))


def stand_on_scene(
    ade: np.ndarray, old_layout: np.ndarray, teacher_weight: float, subjects: np.ndarray
) -> np.ndarray:
    """:func:`scene_target` of a photo whose subjects' alpha (:func:`scene_subjects`) is
    already known: they stand on :func:`scene_layout`'s layout."""
    layout, _ = scene_layout(ade, old_layout, teacher_weight)
    target = subject_target(layout, subjects) if subjects.max() >= 0.5 else layout
    return normalise(target)


def scene_subjects(
    ade: np.ndarray,
    mask: np.ndarray | None = None,
    sal: np.ndarray | None = None,
    voc: np.ndarray | None = None,
) -> np.ndarray:
    """The alpha, ``H x W`` float32 in [0, 1], of everything :func:`scene_target` stands in
    front: the human mask when there is one, else the clear silhouette and the VOC
    subject; and the near occluders in either case."""
    if mask is not None:
        alpha = mask.astype(np.float32)
    else:
        alpha = np.zeros(ade.shape, np.float32)
        if sal is not None:
            s = silhouette_alpha(sal, ade)
            if s is not None:
                alpha = np.maximum(alpha, s)
        if voc is not None:
            alpha = np.maximum(alpha, voc)
    return np.maximum(alpha, occluder_alpha(ade)).astype(np.float32)


def feather(alpha: np.ndarray, sigma: float) -> np.ndarray:
    """``alpha`` softened by a Gaussian of ``sigma`` px, float32 in [0, 1] (as is for
    ``sigma <= 0``): a hard mask's edge becomes a soft rim, as hair and fur have."""
    if sigma <= 0:
        return alpha.astype(np.float32)
    from skimage.filters import gaussian

    return np.clip(gaussian(alpha.astype(np.float32), sigma=sigma), 0, 1).astype(np.float32)


def teacher_disparity(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """The indoor depth teacher's raw output (uint8, metres = 0.0717 x value) as a ranked
    disparity at ``size`` (``(H, W)``), float32 in [0, 1] (1 = nearest): ``1 / depth``
    smoothed by a Gaussian of 4 px at its 224-px output, rank-normalised, resized bilinearly.
    """
    from PIL import Image
    from skimage.filters import gaussian

    h, w = size
    # the teacher's fine structure is texture noise on close-ups: keep its coarse layout
    depth_m = gaussian(np.maximum(depth.astype(np.float32), 1.0), sigma=4.0, preserve_range=True)
    disp = 1.0 / depth_m
    order = np.argsort(np.argsort(disp.ravel(), kind="stable"), kind="stable")
    ranked = (order / max(1, order.size - 1)).reshape(disp.shape).astype(np.float32)
    return np.array(Image.fromarray(ranked).resize((w, h), Image.BILINEAR), dtype=np.float32)
