"""Weighted layered rendering (D2F's ``f_l``), radiance virtualisation boost and refocusing.

Pure tensor code: no file I/O, no learned parameters.

Two compositing orders are provided:

* ``order="depth"`` (default): a signed, depth-ordered refocus. For a disparity map ``d``
  (1 = nearest), a focal disparity ``focus`` and a blur amount ``K`` (px), a pixel's
  circle-of-confusion (CoC) diameter is ``K * |d - focus|``. Pixels behind and in front of the
  focal plane go to separate layers, and layers are composited far to near, so a blurred
  foreground spills over a sharp subject as it does through a real lens. With
  ``placement="nearest"`` (default) each pixel is drawn with the kernel nearest its CoC on
  both sides of focus; ``placement="paper"`` reads the kernel sizes as CoCs, which draws CoCs
  behind the focal plane with the next smaller kernel (see :func:`layer_plan`).
* ``order="paper"``: the authors' ordering by unsigned defocus ``D = |d - focus|`` (most blurred
  layer first, the sharp layer always on top), with layer ``l`` covering ``D = l / (L - 1)`` and
  the kernel schedule stretched so that ``D = 1`` gets a kernel of ``K`` px. With ``K = 69`` and
  ``focus = 0`` this is exactly the paper's ``f_l(X, D)``.

Both use the paper's soft layer masks ``0.5 + 0.5 tanh(gamma (1/(L-1) - |D - l/(L-1)|))`` and
the compositing ``acc = acc (1 - K*M) + K*(M X)``. The radiance normalisation
``f_l(R I, D) / f_l(R, D)`` is done in one pass: both share the alpha ``K*M``.

Speed (see ``d2f-bench render``): layers holding no pixels are skipped, each
layer is blurred only inside its support box, kernels are applied by FFT with cached spectra
(direct convolution for small kernels), and large kernels are applied at reduced resolution
when ``quality`` allows it.

The stages, one module each, in the order a render runs:

* :mod:`.inputs`: input checks and tensors (image, disparity, focus, blur);
* :mod:`.threads`: the torch threads a render uses on a busy machine;
* :mod:`.radiance`: the HDR boost of saturated pixels (``R``);
* :mod:`.plan`: the layer plan and masks, with the CoC schedule (:mod:`.schedule`), the
  kernel sizes (:mod:`.kernels`) and the adaptive settings chooser (:mod:`.adaptive`);
* :mod:`.hidden`: what lies behind a blurred near edge;
* :mod:`.blur`: kernels and the direct, FFT and coarse-grid convolutions;
* :mod:`.composite`: far-to-near compositing and normalisation;
* :mod:`.tiled`: large frames by tiles and bands;
* :mod:`.api`: the public :func:`render`, :func:`render_bokeh` and :class:`LayeredRenderer`,
  re-exported here.
"""

from __future__ import annotations

from .api import LayeredRenderer, render, render_bokeh
from .blur import LANES, QUALITY_PRESETS, KernelSpec, QualityPreset, grid_factor
from .hidden import HiddenSurface, hidden_surface
from .inputs import (
    MAX_BLUR,
    PLACEMENTS,
    check_focus_blur,
    disparity_tensor,
    image_tensor,
)
from .plan import GAMMA, LayerPlan, layer_plan
from .radiance import HDR_ALPHA, HDR_BETA, HDR_THRESHOLD, hdr_boost, highlight_mask

__all__ = [
    "GAMMA",
    "HDR_ALPHA",
    "HDR_BETA",
    "HDR_THRESHOLD",
    "LANES",
    "MAX_BLUR",
    "PLACEMENTS",
    "QUALITY_PRESETS",
    "HiddenSurface",
    "KernelSpec",
    "LayerPlan",
    "LayeredRenderer",
    "QualityPreset",
    "check_focus_blur",
    "disparity_tensor",
    "grid_factor",
    "hdr_boost",
    "hidden_surface",
    "highlight_mask",
    "image_tensor",
    "layer_plan",
    "render",
    "render_bokeh",
]
