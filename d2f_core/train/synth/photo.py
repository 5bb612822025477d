"""Layered scenes made of real photos: a real subject cut out with its mask, standing on a
real background photo that slopes away in depth, with exact thin-lens ground truth.

The scene is still a stack of planar layers (:class:`~d2f_core.train.synth.lens.Layer`), so
:func:`~d2f_core.train.synth.lens.render_thin_lens` gives its exact bokeh; but the textures,
silhouettes and edges are real: hair, fur, petals and thin limbs keep their soft alpha.

- The background photo is a plane whose disparity grows from the top of the view to the
  bottom (a ground or a wall seen at an angle), or a fronto-parallel plane.
- Each subject stands on that plane: its disparity is the plane's at its lowest row, lifted
  a little so that it stands out, fronto-parallel.
- Sometimes a near occluder, another cut-out, covers a corner of the view at a disparity
  nearer than every subject.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ...depth.layout import feather
from .lens import Layer, Scene, srgb_to_linear
from .scene import resize_image

__all__ = ["Cutout", "PhotoScenes", "feather", "make_photo_scene"]

#: photo folders of landscapes, streets, interiors and buildings (backgrounds)
SCENE_SOURCES = ("photos/sun_hays80", "photos/urban100", "photos/bsds500")
#: a cut-out: sRGB float ``(h, w, 3)`` in [0, 1] and its alpha ``(h, w)`` in [0, 1]
Cutout = tuple[np.ndarray, np.ndarray]


def _cut_layer(
    cut: Cutout, height_px: float, bottom: float, cx: float, disparity: float, kind: str
) -> Layer:
    rgb, alpha = cut
    h0, w0 = alpha.shape
    scale = height_px / h0
    h, w = max(4, round(h0 * scale)), max(4, round(w0 * scale))
    rgb_s = np.clip(resize_image(rgb.astype(np.float32), h, w), 0, 1)
    a = np.clip(resize_image(alpha[..., None].astype(np.float32), h, w)[..., 0], 0, 1)
    a = feather(a >= 0.5, 0.7) if a.max() > 0 else a
    lin = srgb_to_linear(rgb_s).transpose(2, 0, 1) * a[None]
    top, left = round(bottom - h), round(cx - w / 2)
    return Layer(lin.astype(np.float32), a, top, left, float(disparity), kind=kind)


def make_photo_scene(
    size: tuple[int, int],
    *,
    seed: int,
    background: np.ndarray,
    subjects: Sequence[Cutout],
    occluder: Cutout | None = None,
    margin: int | None = None,
) -> Scene:
    """A layered scene of real photos (see the module docstring).

    Args:
        size: view ``(H, W)``.
        seed: RNG seed of the layout.
        background: sRGB float ``(h, w, 3)`` photo, resized to cover the view and margin.
        subjects: one or more cut-outs; the first is the main subject.
        occluder: an optional cut-out placed nearest, over a corner of the view.
        margin: content beyond the view on each side; default ``ceil(0.06 * max(size)) + 2``.

    Returns:
        :class:`Scene` with ``subject`` = the main subject's disparity.
    """
    if not subjects:
        raise ValueError("subjects must hold at least one cut-out")
    height, width = int(size[0]), int(size[1])
    margin = int(np.ceil(0.06 * max(height, width))) + 2 if margin is None else int(margin)
    rng = np.random.default_rng(seed)
    bh, bw = height + 2 * margin, width + 2 * margin
    bg = np.clip(resize_image(background.astype(np.float32), bh, bw), 0, 1)
    d_top = rng.uniform(0.0, 0.15)
    d_bottom = d_top + (rng.uniform(0.15, 0.45) if rng.random() < 0.75 else 0.0)
    slope_y = (d_bottom - d_top) / max(1, height - 1)
    # the plane's disparity at the view centre; it stays in [0, 1] over the margin too
    d_centre = 0.5 * (d_top + d_bottom)
    layers = [
        Layer(
            srgb_to_linear(bg).transpose(2, 0, 1).astype(np.float32),
            np.ones((bh, bw), np.float32),
            -margin,
            -margin,
            d_centre,
            slope=(float(slope_y), 0.0),
            kind="background",
            order=d_top,
        )
    ]
    cy = (height - 1) / 2.0

    def plane_at(row: float) -> float:
        return float(np.clip(d_centre + slope_y * (row - cy), 0.0, 1.0))

    objects = []
    main_d = 0.0
    for i, cut in enumerate(subjects):
        tall = rng.uniform(0.45, 0.85) * height if i == 0 else rng.uniform(0.2, 0.5) * height
        bottom = rng.uniform(0.75, 1.05) * height
        cx = rng.uniform(0.3, 0.7) * width if i == 0 else rng.uniform(0.05, 0.95) * width
        d = min(1.0, plane_at(min(bottom, height - 1)) + rng.uniform(0.1, 0.3))
        if i == 0:
            d = max(d, rng.uniform(0.45, 0.8))
            main_d = d
        lay = _cut_layer(cut, tall, bottom, cx, d, "subject" if i == 0 else "cutout")
        if i == 0:
            lay.info["subject"] = True
        objects.append(lay)
    if occluder is not None:
        d = min(1.0, max(o.disparity for o in objects) + rng.uniform(0.1, 0.3))
        tall = rng.uniform(0.4, 0.9) * height
        side = rng.choice([-0.05, 1.05]) * width
        lay = _cut_layer(occluder, tall, rng.uniform(1.0, 1.3) * height, side, d, "occluder")
        objects.append(lay)
    layers += sorted(objects, key=lambda lay: lay.order)
    return Scene(layers, (height, width), margin, float(main_d), seed)


class PhotoScenes:
    """``scene_fn`` for :func:`~d2f_core.train.synth.dataset.make_pair`: photo scenes from a
    datasets folder (``../shared/datasets``), subjects from its masked photos and
    backgrounds from its scene collections (:data:`SCENE_SOURCES`), limited to one side of
    the depth-training split.

    Args:
        root: the datasets folder.
        split: ``"heldout"`` (photos stage 0 never sees) or ``"train"``.
        occluder_share: share of scenes with a near occluder.
    """

    def __init__(self, root, split: str = "heldout", occluder_share: float = 0.3) -> None:
        from ..heldout import is_heldout
        from ..teachers import iter_photos

        if split not in ("heldout", "train"):
            raise ValueError(f"split must be 'heldout' or 'train', got {split!r}")
        photos = [p for p in iter_photos(root) if is_heldout(p) == (split == "heldout")]
        # backgrounds from the scene collections: object photos would put a subject into
        # the background plane
        self.backgrounds = [p for p in photos if p.source in SCENE_SOURCES]
        self.subjects = [p for p in photos if p.mask is not None]
        if not self.backgrounds:
            raise ValueError(f"no scene photos ({', '.join(SCENE_SOURCES)}) in {root}")
        if not self.subjects:
            raise ValueError(f"no masked photos in the {split} split of {root}")
        self.occluder_share = occluder_share

    def _pick_cutout(self, rng: np.random.Generator) -> Cutout:
        from ..teachers import subject_cutout

        for _ in range(20):
            cut = subject_cutout(self.subjects[int(rng.integers(len(self.subjects)))])
            if cut is not None and 0.02 <= cut[2] <= 0.8:
                return cut[0], cut[1]
        raise ValueError("no usable subject mask (2-80 % of its photo) found in 20 draws")

    def __call__(self, size: tuple[int, int], seed: int, margin: int) -> Scene:
        from ...io import load_image

        rng = np.random.default_rng([int(seed), 0xC0FFEE])
        bg_photo = self.backgrounds[int(rng.integers(len(self.backgrounds)))]
        background = load_image(bg_photo.path)
        subjects = [self._pick_cutout(rng) for _ in range(1 + int(rng.random() < 0.4))]
        occluder = self._pick_cutout(rng) if rng.random() < self.occluder_share else None
        return make_photo_scene(
            size,
            seed=int(rng.integers(1 << 31)),
            background=background,
            subjects=subjects,
            occluder=occluder,
            margin=margin,
        )
