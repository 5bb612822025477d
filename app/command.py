"""The ``d2f render`` command that reproduces the picture the app shows, in the CLI's words
for the app's controls: the focus position and the f-number as the sliders say them, the
focal range, the aperture, the quality and the depth source.
"""

from __future__ import annotations

import shlex
from typing import Any

from app.imaging import MAX_PIXELS
from app.settings import RenderParams

__all__ = ["render_command"]


def _depth_args(source: str) -> list[str]:
    """The CLI's depth options for a scene's ``disparity_source``."""
    if source in ("embedded", "d2f", "scene") or source.startswith("transformers:"):
        return ["--depth-model", source]
    # the user's own map: the CLI reads it from its file, which the app only saw uploaded
    return ["--depth", "YOUR_DEPTH_MAP.png"]


def render_command(
    params: RenderParams,
    photo: str,
    depth_source: str,
    output: str | None = None,
    masks: dict[str, Any] | None = None,
) -> str:
    """``d2f render PHOTO -o OUTPUT ...`` giving the picture of ``params`` (a PNG output is
    the app's PNG download, pixel for pixel).

    Args:
        params: the render's parameters, as the app checked them.
        photo: the photo's file name.
        depth_source: the scene's ``disparity_source`` (``embedded``, ``d2f``,
            ``transformers:MODEL``, or ``file`` / ``given`` for the user's map).
        output: the output file (default ``STEM_bokeh.png``).
        masks: the brushes' masks as painted, ``{"sharp": PATH, "blur": PATH}`` (either
            may be absent): ``--sharp-mask`` / ``--blur-mask``.
    """
    stem = photo.rsplit(".", 1)[0] if "." in photo else photo
    args = ["d2f", "render", photo, "-o", output or f"{stem}_bokeh.png"]
    args += ["--focus-position", f"{params.position:g}"]
    if params.f_number is None:
        args += ["--blur", "0"]
    else:
        args += ["--f-number", f"{params.f_number:g}"]
    args += ["--focal-range", f"{params.focal_range:g}"]
    if params.blades:
        args += ["--aperture-blades", str(params.blades)]
    if params.rotation:
        args += ["--rotation", f"{params.rotation:g}"]
    args += ["--quality", params.quality]
    if not params.highlight_boost:
        args.append("--no-highlight-boost")
    elif params.highlight_boost != 1.0:
        args += ["--highlight-boost", f"{params.highlight_boost:g}"]
    if not params.fusion:
        args.append("--no-fusion")
    for key, path in sorted((masks or {}).items(), reverse=True):  # sharp, then blur
        args += [f"--{key}-mask", str(path)]
    args += _depth_args(depth_source)
    # the app downscales larger uploads to this many pixels, as --max-pixels does
    args += ["--max-pixels", str(MAX_PIXELS)]
    return shlex.join(args)
