"""d2f: single-image bokeh rendering and live refocusing (the D2F method).

Stages, each in its own module:

- :mod:`d2f_core.kernels`: soft/hard disk and polygonal aperture kernels, size schedules.
- :mod:`d2f_core.rendering`: weighted layered rendering ``f_l``, HDR boost, refocus.
- :mod:`d2f_core.networks`: defocus hallucination ``f_d``, radiance ``f_r``, fusion ``f_p``.
- :mod:`d2f_core.pipeline`: :class:`D2F` with ``prepare`` (networks, cached) and ``render``.
- :mod:`d2f_core.losses`, :mod:`d2f_core.data`, :mod:`d2f_core.train`,
  :mod:`d2f_core.evaluate`, :mod:`d2f_core.synth`: training and evaluation.
- :mod:`d2f_core.io`: the only module that reads and writes files.
"""

from __future__ import annotations

import importlib

from .kernels import hard_disk_kernel, kernel_sizes, polygon_kernel, soft_disk_kernel
from .rendering import LayeredRenderer, coc_to_defocus, hdr_boost, render, render_bokeh

__version__ = "0.1.0"

_LAZY = {"D2F": "pipeline", "Scene": "pipeline", "Result": "pipeline"}

__all__ = [
    "D2F",
    "LayeredRenderer",
    "Result",
    "Scene",
    "coc_to_defocus",
    "hard_disk_kernel",
    "hdr_boost",
    "kernel_sizes",
    "polygon_kernel",
    "render",
    "render_bokeh",
    "soft_disk_kernel",
]


def __getattr__(name: str):
    # the pipeline pulls in the networks; import it only when asked for
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
