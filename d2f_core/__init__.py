"""d2f: shallow depth of field from one photo (the D2F method, "Defocus to Focus").

The public API, importable from ``d2f_core``:

The model
    :class:`D2F` (``D2F.from_pretrained()`` loads the shipped weights), its settings
    :class:`D2FConfig`, a prepared photo :class:`Scene` (``model.prepare(image)``) and a
    refocused render :class:`Result` (``model.render(scene, focus, blur)``).

Depth sources (:mod:`d2f_core.depth.sources`)
    :func:`depth_map` turns a source (``"embedded"`` phone depth, ``"file:PATH"``, ``"d2f"``,
    ``"transformers:MODEL"``) into a :class:`DepthMap`; :data:`SOURCES` lists them,
    :func:`parse_source` reads one as a :class:`DepthSource`. ``D2F.prepare(image,
    depth=...)`` takes any of them.

The renderer alone (:mod:`d2f_core.rendering`), for a photo and a disparity map you have
    :func:`render_bokeh` (numpy in, numpy out), :class:`LayeredRenderer` (a module with fixed
    options for repeated renders), :func:`render` (tensors), :func:`hdr_boost`, and the
    kernels :func:`soft_disk_kernel`, :func:`hard_disk_kernel`, :func:`polygon_kernel`,
    :func:`kernel_sizes`; :func:`coc_to_defocus` maps a blur diameter to the paper's
    normalised defocus (:mod:`d2f_core.rendering.schedule`).

Files (:mod:`d2f_core.io`, the only module that reads and writes them)
    :func:`load_image`, :func:`load_photo` (with its embedded depth), :func:`load_depth`,
    :func:`load_mask` (a brush's mask), :func:`save_image`.

Errors
    Bad input raises ``ValueError`` naming the problem; :class:`InputTypeError` (a
    ``ValueError`` and a ``TypeError``) is input of the wrong type. Missing weights raise
    ``FileNotFoundError``.

Example::

    from d2f_core import D2F, load_image, save_image

    model = D2F.from_pretrained()
    scene = model.prepare(load_image("photo.jpg"))
    result = model.render(scene, blur=40)  # the phone's focus, else the subject: result.focus
    save_image("bokeh.jpg", result.bokeh)
    save_image("refocused.jpg", model.render(scene, model.focus_at(scene, 120, 80), 40).bokeh)

Other modules: :mod:`d2f_core.pipeline` (the model's stages), :mod:`d2f_core.networks`,
:mod:`d2f_core.rendering` (the renderer's stages; :mod:`d2f_core.rendering.adaptive`, renderer
settings per error budget), :mod:`d2f_core.depth` (depth sources and refinement),
:mod:`d2f_core.bundled` (the shipped weights and sample photos); for training
:mod:`d2f_core.train` (losses, data, synth, the two stages, stage 0), for evaluation
:mod:`d2f_core.evaluate` and for benchmarks :mod:`d2f_core.bench`.

Names are imported on first use, so ``import d2f_core`` (and ``d2f --help``) stays fast.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    # the model
    "D2F": "pipeline",
    "D2FConfig": "pipeline",
    "Scene": "pipeline",
    "Result": "pipeline",
    # depth sources
    "DepthMap": "depth.sources",
    "DepthSource": "depth.sources",
    "SOURCES": "depth.sources",
    "depth_map": "depth.sources",
    "parse_source": "depth.sources",
    # the renderer
    "LayeredRenderer": "rendering",
    "hdr_boost": "rendering",
    "render": "rendering",
    "render_bokeh": "rendering",
    "coc_to_defocus": "rendering.schedule",
    "hard_disk_kernel": "rendering.kernels",
    "kernel_sizes": "rendering.kernels",
    "polygon_kernel": "rendering.kernels",
    "soft_disk_kernel": "rendering.kernels",
    # files
    "load_depth": "io",
    "load_image": "io",
    "load_mask": "io",
    "load_photo": "io",
    "save_image": "io",
    # errors
    "InputTypeError": "errors",
}

__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
