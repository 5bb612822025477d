"""Synthetic layered scenes with exact thin-lens ground truth (accumulation buffer).

A scene is a back-to-front stack of RGBA layers. Each layer is a plane in disparity,
``d(y, x) = disparity + slope_y * (y - cy) + slope_x * (x - cx)`` (view pixel coordinates,
``(cy, cx)`` the view centre; fronto-parallel layers have zero slope), and keeps its full
content, including what nearer layers hide. Disparity is in [0, 1], 1 = nearest.

Working space: layer colours are *linear radiance*. Texture photos are sRGB-encoded, so they
are decoded to linear first; HDR lights carry linear radiance 3-30 (above 1). Compositing and
the aperture average happen in linear radiance, the result is clipped to [0, 1] only at the
end and then encoded (``encoding="srgb"``, the default, stores sRGB like a camera JPEG;
``encoding="linear"`` stores the clipped linear values).

Ground truth (accumulation buffer, exact for layered scenes under a thin lens): for each point
``u`` of a disk aperture of radius ``a = K / 2`` px, a layer point ``p`` is seen at
``p + a * (d(p) - focus) * u``; every layer is warped so (bilinear sampling) and composited
back to front with premultiplied alpha; the views are averaged. A fronto-parallel layer at
disparity ``d`` then becomes a disk blur of diameter ``K * |d - focus|``. A sloped plane is an
affine warp per aperture point, inverted in closed form, so it is exact too.

Modules: ``lens`` (scene model, pinhole and thin-lens renderers), ``scene`` (random
scenes), ``dataset`` (pairs, EBB!-format writer, ``d2f-synth`` CLI).
"""

__all__ = [
    "Layer",
    "Scene",
    "SynthPair",
    "aperture_samples",
    "builtin_textures",
    "generate_dataset",
    "linear_to_srgb",
    "load_textures",
    "main",
    "make_pair",
    "make_scene",
    "render_pinhole",
    "render_thin_lens",
    "srgb_to_linear",
]

from .dataset import SynthPair, generate_dataset, main, make_pair
from .lens import (
    Layer,
    Scene,
    aperture_samples,
    linear_to_srgb,
    render_pinhole,
    render_thin_lens,
    srgb_to_linear,
)
from .scene import builtin_textures, load_textures, make_scene
