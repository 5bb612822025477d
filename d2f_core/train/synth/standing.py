"""Generated scenes where "the bottom of the frame is near" is wrong, with exact ground truth.

Three kinds, each a stack of planar layers like :func:`d2f_core.train.synth.make_scene`'s, so the
thin-lens ground truth of :func:`d2f_core.train.synth.render_thin_lens` stays exact:

- ``"post"``: a tall near cut-out (a post, a pole, a trunk) that crosses the frame from top to
  bottom in front of a far scene;
- ``"over"``: a subject over water or a floor seen from above, whose bottom rows are *far*
  (the plane's disparity falls towards the bottom of the frame, or stays far all over);
- ``"night"``: a dark far scene with small bright lights far behind a near subject.

Every scene's subject is its nearest layer: :func:`subject_mask` gives its coverage.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .lens import Layer, Scene
from .scene import blob, builtin_textures, coverage, lights, texture, trim

__all__ = ["STANDING_KINDS", "make_standing_scene", "subject_mask"]

STANDING_KINDS = ("post", "over", "night")


def _background(rng, textures, size, margin, disparity, dark: bool) -> Layer:
    h, w = size
    bg = texture(rng, textures, h + 2 * margin, w + 2 * margin, scale=(1.0, 2.5))
    bg *= rng.uniform(0.03, 0.15) if dark else 1.0
    alpha = np.ones(bg.shape[1:], np.float32)
    return Layer(bg, alpha, -margin, -margin, disparity, kind="background")


def _post(rng, textures, size, margin, disparity) -> Layer:
    """A vertical bar from above the frame to below it, slightly tilted, with a rounded
    silhouette (a post or trunk), width 4-25 % of the frame's."""
    h, w = size
    width = rng.uniform(0.04, 0.25) * w
    cx = rng.uniform(0.15, 0.85) * w
    tilt = rng.uniform(-0.08, 0.08)
    top, left = -margin, -margin
    hh, ww = h + 2 * margin, w + 2 * margin
    yy, xx = np.mgrid[top : top + hh, left : left + ww].astype(np.float32)
    centre = cx + tilt * (yy - h / 2)
    alpha = coverage(np.abs(xx - centre) - width / 2)
    rgb = texture(rng, textures, hh, ww, scale=(0.3, 1.0))
    # a round post is lit from one side
    across = np.clip((xx - centre) / max(width / 2, 1.0), -1, 1)
    shade = 0.65 + 0.35 * np.sqrt(np.clip(1 - across**2, 0, 1)) * (1 + 0.3 * across)
    layer = Layer((rgb * shade * alpha).astype(np.float32), alpha, top, left, disparity)
    layer.kind, layer.info = "post", {"subject": True, "width_px": round(float(width), 1)}
    return trim(layer)


def _plane(rng, textures, size, margin, d_top, d_bottom) -> Layer:
    """A plane filling the frame's lower part, disparity linear in the row from ``d_top``
    at its first row to ``d_bottom`` at the frame's last (water or a floor from above)."""
    h, w = size
    start = int(rng.uniform(0.2, 0.5) * h)
    top, left = start, -margin
    hh, ww = h + margin - start, w + 2 * margin
    rgb = texture(rng, textures, hh, ww, scale=(0.5, 1.5))
    if rng.random() < 0.5:  # water: bluish, with bright ripples
        ripple = 0.5 + 0.5 * np.sin(np.arange(hh, dtype=np.float32) * rng.uniform(0.3, 1.0))
        rgb = (
            rgb
            * np.array([0.5, 0.7, 1.0], np.float32)[:, None, None]
            * (0.7 + 0.3 * ripple)[None, :, None]
        )
    alpha = np.ones((hh, ww), np.float32)
    slope = (d_bottom - d_top) / max(h - 1 - start, 1)
    centre = d_top + slope * ((h - 1) / 2 - start)
    layer = Layer(rgb.astype(np.float32), alpha, top, left, float(centre), (float(slope), 0.0))
    layer.kind, layer.order = "plane", float(max(d_top, d_bottom))
    return layer


def make_standing_scene(
    size: tuple[int, int] = (256, 256),
    *,
    seed: int,
    kind: str | None = None,
    margin: int | None = None,
    textures: Sequence[np.ndarray] | None = None,
) -> Scene:
    """One scene of ``kind`` (one of :data:`STANDING_KINDS`; drawn from ``seed`` when None).

    Same arguments -> the same scene. The subject is the nearest layer (disparity 0.75-1) and
    ``Scene.subject`` is its disparity.
    """
    if len(size) != 2 or min(size) < 16:
        raise ValueError(f"size must be (H, W) with both >= 16, got {size!r}")
    size = (int(size[0]), int(size[1]))
    h, w = size
    margin = math.ceil(0.06 * max(size)) + 2 if margin is None else int(margin)
    textures = builtin_textures() if textures is None else tuple(textures)
    rng = np.random.default_rng(seed)
    if kind is None:
        kind = STANDING_KINDS[int(rng.integers(len(STANDING_KINDS)))]
    if kind not in STANDING_KINDS:
        raise ValueError(f"kind must be one of {STANDING_KINDS}, got {kind!r}")
    d_bg = float(rng.uniform(0.0, 0.1))
    d_subject = float(rng.uniform(0.75, 1.0))
    night = kind == "night" or rng.random() < 0.2
    layers = [_background(rng, textures, size, margin, d_bg, night)]
    others: list[Layer] = []
    if kind == "over" or rng.random() < 0.3:
        # far at the bottom: the plane recedes downwards, or stays far all over
        d_top = float(rng.uniform(d_bg + 0.05, 0.35))
        d_bottom = float(rng.uniform(d_bg, d_top)) if rng.random() < 0.6 else d_top
        others.append(_plane(rng, textures, size, margin, d_top, d_bottom))
    if night or rng.random() < 0.3:
        for group in range(int(rng.integers(1, 4))):
            others += lights(rng, float(rng.uniform(d_bg, d_bg + 0.15)), size, margin, group)
    for _ in range(int(rng.integers(0, 3))):  # things between, never nearer than the subject
        d = float(rng.uniform(d_bg + 0.05, min(0.5, d_subject - 0.2)))
        r = rng.uniform(0.05, 0.15) * min(size)
        cy, cx = rng.uniform(0.1, 0.9) * h, rng.uniform(0, 1) * w
        others.append(blob(rng, textures, cy, cx, r, d, size, margin))
    if kind == "post":
        subject = _post(rng, textures, size, margin, d_subject)
    else:
        r = rng.uniform(0.12, 0.3) * min(size)
        # anywhere in the frame, the bottom half included (over a far floor)
        cy, cx = rng.uniform(0.3, 0.75) * h, rng.uniform(0.25, 0.75) * w
        subject = blob(rng, textures, cy, cx, r, d_subject, size, margin)
        subject.info["subject"] = True
    layers += sorted((trim(lay) for lay in others), key=lambda lay: lay.order)
    layers.append(trim(subject))
    return Scene(layers, size, margin, d_subject, seed)


def subject_mask(scene: Scene) -> np.ndarray:
    """The coverage of the scene's subject (its last layer) in the view, ``H x W`` float32."""
    h, w = scene.size
    out = np.zeros((h, w), np.float32)
    lay = scene.layers[-1]
    y0, x0 = max(lay.top, 0), max(lay.left, 0)
    y1, x1 = min(lay.top + lay.alpha.shape[0], h), min(lay.left + lay.alpha.shape[1], w)
    if y1 > y0 and x1 > x0:
        out[y0:y1, x0:x1] = lay.alpha[y0 - lay.top : y1 - lay.top, x0 - lay.left : x1 - lay.left]
    return out
