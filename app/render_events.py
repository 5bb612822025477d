"""Render events: the views of a result, the preview while a slider moves, the full render and
the click that sets the focus.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np
from PIL import Image

from app import imaging
from app.command import render_command
from app.reporting import DOWNLOAD_WAIT, NO_PHOTO, SKIP4, user_error
from app.sessions import DISPLAY_FILES_KEPT, Session, SessionClosed, prune_files, reported
from app.settings import (
    FIRST_LOOK_MAX_SIDE,
    FOCAL_RANGE_MAX,
    PREVIEW_MAX_SIDE,
    REFERENCE_SIZE,
    SCREEN_SIDE,
    VIEWS,
    RenderParams,
    position_of,
    wants_first_look,
)
from d2f_core.lens import LENS_FOCAL_MM, MAX_BLUR_PX, NEAREST_M, SENSOR_WIDTH_MM, blur_px
from d2f_core.rendering.kernels import PAPER_GROWING_SIZES

MAX_DEFOCUS_COC = max(PAPER_GROWING_SIZES)
#: The outputs of a preview or of :meth:`RenderEvents.settle` that leave the page as it is.
SKIP5 = (*SKIP4, gr.skip())
#: The outputs of a click that leave the page as it is (the sliders and the picture).
SKIP6 = (gr.skip(), gr.skip(), *SKIP4)

_LEGENDS = {
    "Disparity": ("viridis", "0 far", "1 near", "Disparity ({source})"),
    "Defocus": (
        "magma",
        "0 in focus",
        "1 = a blur of {px} px or more across",
        "Defocus: how blurred each pixel is (size of its blur disc in the full image)",
    ),
    "Fusion mask": (
        "gray",
        "0 bokeh (upsampled)",
        "1 sharp input",
        "Fusion mask: where the full-resolution input is kept",
    ),
}


#: what the disparity view's legend calls each depth source
_MAP_SOURCES = {
    "embedded": "the photo's own phone depth",
    "file": "your depth map",
    "scene": "scene teachers and network",
    "d2f": "network map",
}


def _map_source(key: str) -> str:
    """The disparity legend's words for the source that made the map of the scene cache key
    ``key`` (:func:`app.sources.scene_key`: the pixels, then ``|SOURCE``)."""
    source = key.rsplit("|", 1)[-1] if "|" in key else ""
    if source.startswith("transformers:"):
        return f"Hugging Face model {source.split(':', 1)[1]}"
    return _MAP_SOURCES.get(source, "depth map")


class RenderEvents:
    """The render events of a :class:`~app.handlers.RefocusApp`: the views, the preview
    while a slider moves, the full render and the click to focus.

    Each render event gets the page's ``photo_id`` (its hidden box, set by the load to
    :attr:`Session.token`) as its last input, and is dropped (every output skipped) when the
    page sent it for another photo than the session's: Gradio hands an event the session
    its tab holds when the event runs, which is the next photo's once that one is loaded.
    """

    @staticmethod
    def photo_id(session: Session | None) -> str:
        """What the page's ``photo_id`` box holds once ``session`` is loaded ("" for none)."""
        return session.token if isinstance(session, Session) and not session.closed else ""

    def _session_dir(self, session: Session, name: str) -> Path:
        with session.lock:  # never made again for a session being closed
            if session.closed:
                raise SessionClosed
            if session.folder is None:
                session.folder = self.download_root / uuid.uuid4().hex
            folder = session.folder / name
            folder.mkdir(parents=True, exist_ok=True)
            return folder

    @staticmethod
    def _next_name(session: Session, suffix: str) -> str:
        # a per-session count, zero-padded, so that names sort by age (a clock's digits
        # can roll over: 999... sorted after 1000... made every new file the "oldest")
        with session.lock:
            session.files_written += 1
            return f"{session.files_written:09d}{suffix}"

    def _display_file(self, session: Session, image: np.ndarray, lossless: bool = False) -> str:
        """Write a picture for the browser as JPEG (:func:`app.imaging.write_display`), or as
        a PNG with ``lossless`` (the 100 % loupe's pixels are judged one by one), and return
        its path; the download is written apart, at full resolution.

        Gradio would encode arrays itself as PNG at level 6 (0.7 s for 1600x1200 here); it
        copies the file into its cache after the event returns, so a file is removed only
        once it is old (see :func:`prune_files`).
        """
        folder = self._session_dir(session, "display")
        path = folder / self._next_name(session, ".png" if lossless else ".jpg")
        if lossless:
            Image.fromarray(image).save(path, format="PNG", compress_level=1)
        else:
            imaging.write_display(image, path)
        prune_files(folder, DISPLAY_FILES_KEPT)
        return str(path)

    def _store_views(self, session: Session, result: Any, bokeh: np.ndarray) -> None:
        shown = imaging.fit_display(bokeh)
        # maps come at the render pass's size; shown at the bokeh's size they line up when
        # the user switches views. Kept grey (one byte a pixel), resized when first shown
        # and coloured when shown.
        session.pass_width = int(result.defocus.shape[-1])
        session.views = imaging.DisplayViews(
            shown,
            {
                "Disparity": result.disparity,
                "Defocus": result.defocus,
                "Fusion mask": result.fusion_mask,
            },
        )

    @staticmethod
    def _view_picture(session: Session, view: str) -> np.ndarray:
        picture = session.views.get(view, session.views["Bokeh"])
        if picture.ndim == 2:
            cmap = _LEGENDS[view][0]
            return imaging.colorize(picture.astype(np.float32) / 255.0, cmap)
        return picture

    @staticmethod
    def _legend(session: Session, view: str) -> tuple[str, str, str, str] | None:
        """The legend of ``view``; the defocus map's top end in full-resolution pixels."""
        legend = _LEGENDS.get(view)
        if legend is not None and view == "Disparity":
            cmap, low, high, title = legend
            return cmap, low, high, title.format(source=_map_source(session.key))
        if legend is None or view != "Defocus":
            return legend
        # the defocus map is the paper's D of the CoC at the render pass, 1 = 69 px there;
        # the pass (a preview's is its own size) is smaller than the photo by the width
        # ratio of the two
        px = round(MAX_DEFOCUS_COC * session.size[0] / max(session.pass_width, 1))
        cmap, low, high, title = legend
        return cmap, low, high.format(px=px), title

    def view_outputs(self, session: Session | None, view: str) -> tuple:
        """``(result, compare, legend)`` updates that show ``view`` of the last render."""
        if session is None or not session.views:
            return gr.update(value=None), gr.update(value=None), gr.update(visible=False)
        if view == "Before / after":
            after = session.views["Bokeh"]
            before = imaging.resize_to(session.before, (after.shape[1], after.shape[0]))
            return (
                gr.update(visible=False),
                gr.update(
                    value=(self._display_file(session, before), self._display_file(session, after)),
                    visible=True,
                ),
                gr.update(visible=False),
            )
        picture = self._view_picture(session, view)
        legend = self._legend(session, view)
        return (
            gr.update(value=self._display_file(session, picture), visible=True),
            gr.update(visible=False),
            gr.update(value=imaging.legend_html(*legend), visible=True)
            if legend
            else gr.update(visible=False),
        )

    @staticmethod
    def _settings_text(settings: Any, quality: str) -> str:
        """The quality the user chose and, briefly, what the adaptive picker did for it (the
        renderer's own preset names are not the user's words)."""
        if settings is None:
            return f"{quality} quality"
        if settings.identity:
            return f"{quality} quality: every blur under 1 px, photo shown as it is"
        done = f"{settings.num_layers} blur layers"
        if settings.quality != "exact":
            done += ", large blurs computed at reduced size"
        if not settings.fusion:
            done += ", no sharpening pass needed"
        return f"{quality} quality: {done}"

    @staticmethod
    def _info(session: Session, params: RenderParams, kind: str, ms: float, extra: str = "") -> str:
        w, h = session.size
        span = f", focal range {params.focal_range:g}" if params.focal_range else ""
        paint = ""
        if params.paint and session.brushes is not None:
            sharp, blurred = session.brushes.coverage()
            paint = f" | painted: {100 * sharp:.0f}% kept sharp, {100 * blurred:.0f}% blurred"
        text = (
            f"{w}x{h} px | focus {params.position:.3f} (0 = near, 1 = far; disparity "
            f"{params.focus:.3f}) | {params.blur_text()}{span}{paint} | {kind} render "
            f"{ms:.0f} ms"
        )
        return text + (f" | {extra}" if extra else "")

    @staticmethod
    def _file_params(params: RenderParams) -> str:
        """The settings part of a download's name: the focus slider's position, the
        f-number and K (``focus0.310_f2.8_K14.9``), or ``focus0.310_noblur``."""
        if params.f_number is None:
            return f"focus{params.position:.3f}_noblur"
        return f"focus{params.position:.3f}_f{params.f_number:g}_K{params.blur:g}"

    @staticmethod
    def blur_note(session: Session | None, f_number: Any, blur_on: Any = True) -> str:
        """The aperture slider's info line: the virtual lens, and the blur ``f_number``
        gives this photo (K, px at full resolution), or a 4000x3000 photo's before an upload.

        Never raises: it only describes the controls (a render refuses bad values).
        """
        lens = (
            f"{LENS_FOCAL_MM:g} mm lens on full frame ({SENSOR_WIDTH_MM:g} mm wide), nearest "
            f"thing {NEAREST_M:g} m away"
        )
        if blur_on in (False, None, 0, "false", "False"):
            return f"Blur is off: the photo as it is ({lens})"
        live = isinstance(session, Session) and not session.closed
        w, h = session.size if live else REFERENCE_SIZE
        try:
            n = round(float(f_number), 3)
            k = blur_px(n, max(w, h))  # refuses an f-number outside the lens's range
        except (TypeError, ValueError, OverflowError):
            return lens
        capped = " (the most the app renders)" if k >= MAX_BLUR_PX else ""
        where = f"this {w}x{h} photo" if live else f"a {w}x{h} photo"
        return f"f/{n:g}: blur K = {k:g} px{capped} on {where} ({lens})"

    def _render_full(
        self,
        session: Session,
        params: RenderParams,
        view: str,
        scene: Any = None,
        *,
        newest: bool = True,
        note: str = "",
    ) -> tuple:
        """Render ``params`` at full resolution and show it: ``(result, compare, legend,
        info)``, or skips when another value was set meanwhile. ``newest`` False: the render
        of values set earlier (an upload's, after its first look), skipped at once when the
        user has set others since. ``note`` ends the status line (kept with the render, for
        :meth:`settle`)."""
        session.touch()
        with session.lock:
            if not newest and not session.still_wanted(params):
                return SKIP4
            session.full_seq += 1
            seq = session.full_seq
            session.full_params = params
            session.ask(params)
        try:
            if scene is None:
                scene = session.scene
            photo = session.upload_name or f"{session.name}.jpg"
            source = getattr(scene, "disparity_source", "d2f")
            command = render_command(params, photo, source, masks=session.paint_files)
            # the picture at the screen's size: the full resolution waits for the download
            screen = SCREEN_SIDE if max(session.size) > SCREEN_SIDE else None
            t0 = time.perf_counter()
            result = self.model.render(
                scene, params.focus, params.blur, screen=screen, **params.render_options()
            )
            del scene
            ms = 1000 * (time.perf_counter() - t0)
        except BaseException:
            with session.lock:
                if session.full_seq == seq:
                    session.full_params = None
            raise
        bokeh = imaging.to_uint8(result.bokeh)
        extra = self._settings_text(result.settings, params.quality)
        if screen is not None:
            sh, sw = bokeh.shape[:2]
            extra += f" | shown at {sw}x{sh}, the download at full resolution"
        info = self._info(session, params, "full", ms, extra) + f" | reproduce: {command}" + note
        with session.lock:
            if session.full_seq != seq or session.closed:
                return SKIP4  # a newer full render is on its way
            if not session.still_wanted(params):
                # another value was set while this one rendered (its preview is shown, its
                # full render will follow): an older value's picture must not replace it
                session.full_params = None
                return SKIP4
            session.last_full_params = params
            session.last_full_info = info
            if screen is None:  # the photo's own size: the download's picture already
                self._keep_full_res(session, params, bokeh)
            self._store_views(session, result, bokeh)
        return (*self.view_outputs(session, view), info)

    def _render_small(
        self, scene: Any, params: RenderParams, max_side: int
    ) -> tuple[Any, np.ndarray, float]:
        """``(result, bokeh as uint8, ms)`` of ``params`` rendered at ``max_side`` (a preview's
        or a first look's size)."""
        t0 = time.perf_counter()
        result = self.model.render(
            scene, params.focus, params.blur, max_side=max_side, **params.render_options()
        )
        ms = 1000 * (time.perf_counter() - t0)
        return result, imaging.to_uint8(result.bokeh), ms

    def _render_shown(
        self,
        session: Session,
        params: RenderParams,
        view: str,
        scene: Any,
        note: str,
        first_look: bool = True,
    ) -> Iterator[tuple]:
        """The pictures of a render the user waits for (an upload, a click): with
        ``first_look``, a photo over :data:`~app.settings.FIRST_LOOK_PIXELS` is shown first
        at :data:`FIRST_LOOK_MAX_SIDE` (:meth:`_render_first_look`), then at full resolution,
        unless another value was set in between (then skips); else the full render only.

        Yields ``(result, compare, legend, info)``, ``note`` ending the status line.
        """
        looked = first_look and wants_first_look(session.size)
        if looked:
            outputs = self._render_first_look(session, params, view, scene)
            yield outputs if outputs is SKIP4 else (*outputs[:3], outputs[3] + note)
        yield self._render_full(session, params, view, scene, newest=not looked, note=note)

    def _render_first_look(
        self, session: Session, params: RenderParams, view: str, scene: Any
    ) -> tuple:
        """The first picture of an upload or a click, rendered at :data:`FIRST_LOOK_MAX_SIDE`
        while its full-resolution render follows (:meth:`_render_shown`).

        It holds ``params`` as the full render's (being rendered): a preview of the same
        values (the focus slider set by the load) is skipped. Returns ``(result, compare,
        legend, info)``, or skips when the photo was replaced or another value set meanwhile.
        """
        with session.lock:
            session.full_seq += 1
            session.full_params = params
            session.ask(params)
        result, bokeh, ms = self._render_small(scene, params, FIRST_LOOK_MAX_SIDE)
        with session.lock:
            if session.closed or not session.still_wanted(params):
                return SKIP4  # the photo was replaced, or another value was set meanwhile
            self._store_views(session, result, bokeh)
        w, h = bokeh.shape[1], bokeh.shape[0]
        info = self._info(session, params, "first look", ms, f"{w}x{h}, full resolution follows")
        return (*self.view_outputs(session, view), info)

    @reported(dropped=SKIP4)
    def render_full(
        self,
        session: Session | None,
        focus: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
        blur_on: Any = True,
        focal_range: Any = 0.0,
        photo_id: Any = None,
    ) -> tuple:
        """Full-resolution render (slider released, option changed).

        ``focus`` is the focus slider's position (0 = nearest, 1 = farthest), ``f_number``
        the aperture, ``blur_on`` False renders no blur, ``focal_range`` the span of
        disparity kept sharp (see :meth:`RenderParams.from_inputs`). The status line ends
        with the ``d2f render`` command that reproduces the picture.

        Without a photo loaded in the session (a slider released on an empty page, an API
        call before ``/load`` or from another session) the event is refused with a message;
        the previews of a drag before that stay silent. ``photo_id``: the page's (see
        :class:`RenderEvents`); an event sent for another photo, or whose photo the tab
        replaced while it ran, is dropped.

        Returns:
            ``(result, compare, legend, info)``, or skips.
        """
        if session is None:
            raise user_error(NO_PHOTO)
        if not session.shown_by(photo_id):
            return SKIP4
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            focal_range, size=session.size, paint=session.paint_id,
        )  # fmt: skip
        session.touch()
        with session.lock:
            session.ask(params)
            if params == session.full_params:
                return SKIP4  # already rendered (or being rendered) at full resolution
        return self._render_full(session, params, view)

    @reported(dropped=SKIP5)
    def render_preview(
        self,
        session: Session | None,
        focus: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
        blur_on: Any = True,
        focal_range: Any = 0.0,
        photo_id: Any = None,
    ) -> tuple:
        """Reduced-resolution render while a slider moves.

        Dropped (``gr.skip()``) when a full render of the same params was requested, or when
        a full render started while this preview ran: a preview must never replace the full
        result that the release of the slider asked for. While a preview is shown the
        download button is disabled (it would save another picture than the one on screen);
        the full render that follows enables it again. A preview sent for another photo
        than the session's (``photo_id``) is dropped too.

        Returns:
            ``(result, compare, legend, info, download)``.
        """
        if session is None or not session.shown_by(photo_id):
            return SKIP5
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            focal_range, size=session.size, paint=session.paint_id,
        )  # fmt: skip
        session.touch()
        with session.lock:
            session.ask(params)
            session.last_preview = params
            if params == session.full_params:
                return SKIP5
            seq = session.full_seq
        result, bokeh, ms = self._render_small(session.scene, params, PREVIEW_MAX_SIDE)
        with session.lock:
            stale = not session.still_wanted(params)
            if session.full_seq != seq or params == session.full_params or session.closed or stale:
                return SKIP5
            self._store_views(session, result, bokeh)
            # the views no longer hold the full render: releasing at its params renders again
            session.full_params = None
        extra = self._settings_text(result.settings, params.quality)
        info = self._info(session, params, "preview", ms, extra)
        return (*self.view_outputs(session, view), info, gr.update(**DOWNLOAD_WAIT))

    @reported(dropped=SKIP5)
    def settle(self, session: Session | None, *page: Any) -> tuple:
        """Bring the page's picture in line with its controls, after a preview or a full
        render has reached it. ``page``: the controls' values when this event starts, as
        :meth:`render_full` takes them after the session (focus, f-number, blades, rotation,
        highlight boost, fusion, view, quality, blur on, focal range, and optionally the
        page's photo id: a page that shows another photo is left alone), then the status
        line.

        Renders run side by side (the ``"model"`` group's concurrency) and reach the server
        and the page in their own time, so two orders go wrong without this step:

        - a preview stored just before the full render of its values started reaches the
          page after it: the preview stays on screen, with Download disabled. When the full
          render of the page's values is done and the views hold it, it is sent again (it is
          not rendered again);
        - a release sent before the last change of a value (a click into a number box, then
          a value typed; a slider let go, then an option chosen) reaches the server after
          that change's preview or full render: the page shows a full render of the old
          value under the new one. When the page shows the last full render, its values are
          not the page's, and the page's values are those of the last preview asked for or
          the ones asked for just before that full render, the page's values are rendered
          in full.

        Otherwise (a preview on screen whose release is to come, a full render on its way,
        values the render events refuse) it does nothing.

        Returns:
            ``(result, compare, legend, info, download)``: a picture sent again leaves the
            Download button as it is (the chained download event enables it with the file
            written for that render already), one rendered disables it until its file is
            written, as every full render does.
        """
        skip = SKIP5
        if session is None or session.closed:
            return skip
        if len(page) not in (11, 12):
            raise user_error(
                f"settle takes 10 control values, the photo id and the status line, got {page!r}"
            )
        controls, shown_info = list(page[:10]), page[-1]
        if len(page) == 12 and not session.shown_by(page[10]):
            return skip
        view = controls.pop(6)
        try:
            params = RenderParams.from_inputs(*controls, size=session.size, paint=session.paint_id)
        except gr.Error:
            return skip  # the render events have said what is wrong
        session.touch()
        with session.lock:
            done = session.last_full_params
            if done is None or session.full_params != done:
                return skip  # a preview is shown, or a full render is on its way
            shown = session.shows_last_full(shown_info)
            if done == params:
                if shown:
                    return skip
                return (*self.view_outputs(session, view), session.last_full_info, gr.skip())
            late = session.wanted == done and session.asked_before == params
            if not shown or not (late or session.last_preview == params):
                # a preview on screen, its release to come; or the page's values not yet
                # seen here (a drag started after a release): their preview is on its way
                return skip
        outputs = self._render_full(session, params, view)
        return (*outputs, gr.skip() if outputs is SKIP4 else gr.update(**DOWNLOAD_WAIT))

    def click(self, *args: Any, **kwargs: Any) -> tuple:
        """:meth:`click_steps` without a first look: the outputs of the full-resolution render
        (the same arguments)."""
        *_, last = self.click_steps(*args, first_look=False, **kwargs)
        return last

    @reported(dropped=SKIP6)
    def click_steps(
        self,
        session: Session | None,
        index: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
        blur_on: Any = True,
        photo_id: Any = None,
        *,
        first_look: bool = True,
    ) -> Iterator[tuple]:
        """Focus on the clicked point: ``index = [x, y]`` in the shown photo's pixels, with a
        focal range that keeps the clicked subject sharp (``D2F.focus_at(..., with_range=True)``:
        the extent in depth of the connected region around the point).

        A generator of the outputs: with ``first_look``, a photo over
        :data:`~app.settings.FIRST_LOOK_PIXELS` is shown refocused first at the render pass's
        size (:meth:`_render_first_look`), then at full resolution, unless another value was
        set in between; else the full render only.

        A click on another photo than the session's (``photo_id``: the page's; the tab has
        loaded a photo since) is dropped, and so is one whose photo the tab replaced while it
        ran, the sliders' new values with its pictures: the next photo's page is never set
        to values found on this one.

        Yields:
            ``(focus, focal_range, result, compare, legend, info)``; the focus slider moves to
            ``focus``, the position (0 = nearest, 1 = farthest) of the clicked point's
            disparity, and the focal range slider to the subject's range (set by the first
            picture only).
        """
        if session is None:
            gr.Warning("Upload a photo first.")
            yield SKIP6
            return
        if not session.shown_by(photo_id):
            yield SKIP6
            return
        session.touch()
        try:
            x, y = (float(v) for v in index)
        except (TypeError, ValueError):
            raise user_error(f"Click position must be [x, y], got {index!r}.") from None
        # the browser reports pixels of the upload as shown; the scene may be downscaled
        sw, sh = session.shown_size
        w, h = session.size
        xs = min(max((x + 0.5) * w / sw - 0.5, 0.0), w - 1.0)
        ys = min(max((y + 0.5) * h / sh - 0.5, 0.0), h - 1.0)
        t0 = time.perf_counter()
        disparity, span = self.model.focus_at(session.scene, xs, ys, with_range=True)
        focus, span = position_of(disparity), min(span, FOCAL_RANGE_MAX)
        ms_focus = 1000 * (time.perf_counter() - t0)
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            span, size=session.size, paint=session.paint_id,
        )  # fmt: skip
        clicked = f" | focused on the click at ({xs:.0f}, {ys:.0f}) in {ms_focus:.0f} ms"
        steps = self._render_shown(session, params, view, session.scene, clicked, first_look)
        for outputs in steps:
            if outputs is SKIP4 and session.closed:  # the photo was replaced meanwhile
                yield SKIP6
                return
            yield (focus, span, *outputs)
            focus, span = gr.skip(), gr.skip()  # set by the first picture

    @reported
    def show_view(self, session: Session | None, view: str) -> tuple:
        """Switch the result panel to ``view`` without rendering.

        Returns:
            ``(result, compare, legend)``.
        """
        if view not in VIEWS:
            raise user_error(f"Unknown view {view!r}; expected one of {', '.join(VIEWS)}.")
        if session is not None:
            session.touch()
        return self.view_outputs(session, view)
