"""d2f: single-image bokeh rendering and live refocusing (the D2F method).

Stages, each in its own module:

- :mod:`d2f_core.kernels`: soft/hard disk and polygonal aperture kernels, size schedules.
- :mod:`d2f_core.rendering`: weighted layered rendering ``f_l``, HDR boost, refocus.
- :mod:`d2f_core.networks`: defocus hallucination ``f_d``, radiance ``f_r``, fusion ``f_p``.
- :mod:`d2f_core.pipeline`: :class:`D2F` with ``prepare`` (networks, cached) and ``render``.
- :mod:`d2f_core.losses`, :mod:`d2f_core.data`, :mod:`d2f_core.train`,
  :mod:`d2f_core.evaluate`, :mod:`d2f_core.synth`: training and evaluation.
- :mod:`d2f_core.io`: the only module that reads and writes files.

Names are imported on first use, so ``import d2f_core`` (and ``d2f --help``) stays fast.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "D2F": "pipeline",
    "InputTypeError": "errors",
    "Scene": "pipeline",
    "Result": "pipeline",
    "LayeredRenderer": "rendering",
    "coc_to_defocus": "rendering",
    "hdr_boost": "rendering",
    "render": "rendering",
    "render_bokeh": "rendering",
    "hard_disk_kernel": "kernels",
    "kernel_sizes": "kernels",
    "polygon_kernel": "kernels",
    "soft_disk_kernel": "kernels",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
