"""The focus and blur brushes of the page: paint over the photo what must stay sharp (green)
or be blurred (red), whatever the depth map says (``D2F.paint``).

The paint is the session's: every later render applies it for its own focus, so it stays
when the focus or the aperture changes, until it is cleared or another photo is loaded. The
masks as painted are kept as PNG files (:func:`masks_folder`, kept after the tab is closed),
and the status line's ``d2f render`` command names them (``--sharp-mask``, ``--blur-mask``).
"""

from __future__ import annotations

import hashlib
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np
from PIL import Image

from app.imaging import DISPLAY_MAX_SIDE, fit_display
from app.reporting import NO_PHOTO, SKIP4, user_error
from app.sessions import Session, reported
from d2f_core.depth.brushes import Brushes
from d2f_core.io.depth import check_aspect
from d2f_core.io.masks import DECODE_ERRORS
from d2f_core.io.save import atomic_write

log = logging.getLogger("app.handlers")

#: What Apply says when the canvas holds no paint and the photo had none.
NOTHING_PAINTED = (
    "Nothing is painted: choose a brush, paint over the photo in the brushes' panel, then "
    "Apply paint."
)

#: The brushes' colours on the canvas, with their opacity: keep sharp, blur.
SHARP_COLOUR = "#22c55e"
BLUR_COLOUR = "#ef4444"
BRUSH_OPACITY = 0.6


#: The long side of the brushes' canvas (px): the editor shows it at about 400-600 px, and
#: exports its background, its paint and their composite at this size on Apply (in the
#: browser, a second at 1600 px in software). The strokes' edges follow the photo's at this
#: size too (``d2f_core.depth.brushes.EDGE_SIDE``).
CANVAS_SIDE = 1024
#: The largest side a canvas image (background, paint layer, composite) may have: the canvas
#: is the photo at display size (:data:`app.imaging.DISPLAY_MAX_SIDE`), and a request's
#: memory stays bounded by it whatever a client sends.
CANVAS_MAX_SIDE = DISPLAY_MAX_SIDE


def masks_folder() -> Path:
    """Where the painted masks are written for the status line's ``d2f render`` command:
    ``$D2F_APP_MASKS``, else ``$XDG_CACHE_HOME/d2f/masks`` (``~/.cache/d2f/masks``). They
    stay when the tab and the server are gone, so the command still runs; each is named by
    its paint's content and is a few KB (a 1-bit picture at the canvas's size)."""
    env = os.environ.get("D2F_APP_MASKS")
    if env:
        folder = Path(env)
    else:
        cache = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        folder = Path(cache) / "d2f" / "masks"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def check_canvas_image(file: Any) -> None:
    """Refuse a canvas image larger than the canvas from its header, before any pixel is
    decoded (Gradio decodes every layer of the editor's value to a full-size array)."""
    from io import BytesIO

    path = getattr(file, "path", None)
    source = path if path is not None else BytesIO(bytes(file))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(source) as im:
                w, h = im.size
    except (*DECODE_ERRORS, Image.DecompressionBombError) as exc:
        raise gr.Error(f"The paint layer is not an image: {exc}", print_exception=False) from None
    if max(w, h) > CANVAS_MAX_SIDE:
        raise gr.Error(
            f"The paint layer is {w}x{h}: the canvas is at most {CANVAS_MAX_SIDE} px on a side.",
            print_exception=False,
        )


def bound_canvas(editor: gr.ImageEditor) -> gr.ImageEditor:
    """``editor`` with its images checked from their headers (:func:`check_canvas_image`)
    before Gradio decodes them; returns it. (An instance's method is wrapped: a subclass of
    a Gradio component makes Gradio write a stub file beside this module.)"""
    convert = editor.convert_and_format_image

    def checked(file: Any, flatten_on_white: bool = False) -> Any:
        if file is None:
            return convert(file, flatten_on_white)
        check_canvas_image(file)
        try:
            return convert(file, flatten_on_white)
        except DECODE_ERRORS as exc:
            raise gr.Error(
                f"The paint layer is truncated or corrupt: {exc}", print_exception=False
            ) from None

    editor.convert_and_format_image = checked
    return editor


def masks_from_layers(layers: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The keep-sharp and blur masks (``H x W`` float32, 1 = painted, ``None`` where nothing
    is) of the editor's paint layers (``H x W x 4`` RGBA): a painted pixel (alpha > 0) is
    "keep sharp" where the green brush left more green than red, "blur" otherwise."""
    sharp = blur = None
    for layer in layers or []:
        a = np.asarray(layer)
        if a.ndim != 3 or a.shape[2] != 4 or a.size == 0:
            raise user_error(f"The paint layer must be an RGBA picture, got shape {a.shape}.")
        if sharp is not None and a.shape[:2] != sharp.shape:
            (h, w), (h0, w0) = a.shape[:2], sharp.shape
            raise user_error(
                f"The paint layers differ in size ({w0}x{h0} and {w}x{h}): paint them all "
                "on the photo shown in the brushes' panel."
            )
        painted = a[..., 3] > 0
        green = a[..., 1].astype(np.int16) > a[..., 0].astype(np.int16)
        here_sharp, here_blur = painted & green, painted & ~green
        sharp = here_sharp if sharp is None else sharp | here_sharp
        blur = here_blur if blur is None else blur | here_blur
    return tuple(m.astype(np.float32) if m is not None and m.any() else None for m in (sharp, blur))


def paint_id(sharp: np.ndarray | None, blur: np.ndarray | None, edges: bool) -> str:
    """A short name of the paint's content ("" for none)."""
    if sharp is None and blur is None:
        return ""
    h = hashlib.sha1(str(bool(edges)).encode())
    for m in (sharp, blur):
        h.update(b"-" if m is None else str(m.shape).encode() + np.packbits(m > 0).tobytes())
    return h.hexdigest()[:12]


class PaintEvents:
    """The brushes' events as methods of :class:`~app.handlers.RefocusApp`."""

    @reported
    def paint_canvas(self, session: Session | None) -> Any:
        """The paint editor's value for ``session``'s photo: the photo at
        :data:`CANVAS_SIDE` as the canvas's background, no paint (``None`` without a photo).
        """
        if session is None:
            return None
        background = fit_display(session.before, CANVAS_SIDE)
        return {"background": background, "layers": [], "composite": None}

    def _keep_paint(
        self, session: Session, sharp: np.ndarray | None, blur: np.ndarray | None, edges: bool
    ) -> None:
        """Make the paint the session's: its brushes (edges following the photo's) and the
        masks' files; no paint clears both."""
        name = paint_id(sharp, blur, edges)
        if name == session.paint_id:
            return
        brushes, files = None, {}
        if name:
            w, h = session.size
            for what, m in (("painted keep-sharp", sharp), ("painted blur", blur)):
                try:
                    if m is not None:
                        check_aspect(m.shape, (h, w), "paint")
                except ValueError:
                    raise user_error(
                        f"The {what} mask is {m.shape[1]}x{m.shape[0]}, not the photo's shape "
                        f"({w}x{h}): paint on the photo shown in the brushes' panel."
                    ) from None
            image = session.get_scene().image
            brushes = Brushes.painted(image, sharp, blur, edges=edges)
            folder = masks_folder()
            for key, m in (("sharp", sharp), ("blur", blur)):
                if m is not None:
                    path = folder / f"{key}_mask_{name}.png"
                    if not path.exists():  # named by its content: written once
                        picture = Image.fromarray((m > 0).astype(np.uint8) * 255)
                        atomic_write(path, lambda fh, p=picture: p.save(fh, format="PNG"))
                    files[key] = path
        with session.lock:
            session.brushes = brushes
            session.paint_id = name if brushes is not None else ""
            session.paint_files = files if brushes is not None else {}
        log.info("paint %s: %s", session.name, session.paint_id or "cleared")

    @reported(dropped=SKIP4)
    def apply_paint(
        self,
        session: Session | None,
        editor: Any,
        edges: Any,
        *controls: Any,
    ) -> tuple:
        """Take the paint of the brushes' editor (its layers) and render with it.

        ``editor``: the ``gr.ImageEditor`` value (``{"background", "layers", "composite"}``,
        numpy RGBA); ``edges``: strokes' rims follow the photo's edges; ``controls``: the
        render's inputs after the session, as :meth:`render_full` takes them.

        Returns:
            ``(result, compare, legend, info)`` of the full render with the paint.
        """
        if session is None:
            raise user_error(NO_PHOTO)
        if controls and not session.shown_by(controls[-1]):
            return SKIP4
        layers = editor.get("layers") if isinstance(editor, dict) else None
        sharp, blur = masks_from_layers(layers)
        if sharp is None and blur is None and not session.paint_id:
            gr.Warning(NOTHING_PAINTED)
            return SKIP4
        self._keep_paint(session, sharp, blur, bool(edges))
        return self.render_full(session, *controls)

    @reported(dropped=SKIP4)
    def clear_paint(self, session: Session | None, *controls: Any) -> tuple:
        """Clear the session's paint and render without it (nothing to do without a photo).

        Returns:
            ``(result, compare, legend, info)``.
        """
        if session is None:
            return SKIP4
        if controls and not session.shown_by(controls[-1]):
            return SKIP4
        self._keep_paint(session, None, None, True)
        return self.render_full(session, *controls)
