"""Uploads and depth sources: a photo (and a depth map, the phone's depth or a model) loaded
into a session, with the file paths a client names checked first.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import logging
import shutil
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from app import imaging, sources
from app.cache import content_key
from app.reporting import user_error
from app.sessions import Session, SessionClosed, no_scene, reported
from app.settings import (
    FOCAL_RANGE_MAX,
    PANEL_PREFIX,
    VIEWS,
    RenderParams,
    disparity_of,
    position_of,
)
from app.uploads import NOT_AN_UPLOAD

# the app's events log under one name, whichever module holds them
log = logging.getLogger("app.handlers")


def _payload_path(value: Any) -> str | None:
    """File path of an upload, whether given as a path or as Gradio's raw FileData dict."""
    if value is None:
        return None
    if isinstance(value, (str, Path)):
        return str(value)
    if isinstance(value, dict):
        path = value.get("path")
        return str(path) if path else None
    path = getattr(value, "path", None)
    return str(path) if path else None


def _safe_stem(name: str, most: int) -> str:
    """The stem of the user's file ``name`` as part of a file name that is safe here: its
    letters, digits, ``-`` and ``_`` kept, anything else ``_``, at most ``most`` characters
    ("photo" when nothing is left)."""
    stem = Path(str(name)).stem
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in stem)[:most] or "photo"


def _payload_name(value: Any, default: str = "photo", *, ext: bool = False) -> str:
    """The user's file name (``ext``) or a file-system-safe stem of it, for names and messages."""
    name = None
    if isinstance(value, dict):
        name = value.get("orig_name") or value.get("path")
    elif value is not None:
        name = getattr(value, "orig_name", None) or _payload_path(value)
    if not name:
        return default
    if ext:
        return Path(str(name)).name
    stem = Path(str(name)).stem
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in stem)[:60]
    return safe or default


def _remember_load_error(fn: Callable) -> Callable:
    """Keep a failed upload's message for the tab (``request``) that sent it, so that the
    chained :meth:`RefocusApp.after_failed_load` can show it in the status line."""
    signature = inspect.signature(fn)

    def note(self, args: tuple, kwargs: dict, err: gr.Error) -> None:
        request = signature.bind_partial(self, *args, **kwargs).arguments.get("request")
        self.note_load_error(getattr(request, "session_hash", None), str(err.message))

    if inspect.isgeneratorfunction(fn):

        @functools.wraps(fn)
        def steps(self, *args, **kwargs):
            try:
                yield from fn(self, *args, **kwargs)
            except gr.Error as err:
                note(self, args, kwargs, err)
                raise

        return steps

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        try:
            return fn(self, *args, **kwargs)
        except gr.Error as err:
            note(self, args, kwargs, err)
            raise

    return wrapper


@dataclasses.dataclass
class _Upload:
    """An upload decoded (:meth:`LoadEvents._decoded_upload`): the photo, the map it renders
    from (``None``: the chosen source predicts one), its description and source, the
    render's parameters at the photo's size, the focus slider's new position (or a skip),
    whether to search for the subject, and the files' paths and names."""

    photo: Any
    disparity: Any
    source: str
    chosen: str
    params: RenderParams
    new_focus: Any
    search: bool
    path: str
    photo_name: str
    depth_path: str | None
    depth_name: str


def _check_texts(view: Any, depth_kind: Any, hub_model: Any, depth_source: Any) -> None:
    """The load event takes raw payloads (Gradio does not check them): its texts checked.

    Raises:
        gr.Error: naming the bad value.
    """
    if view not in VIEWS:
        raise user_error(f"Unknown view {view!r}; expected one of {', '.join(VIEWS)}.")
    for what, value in (("depth map kind", depth_kind), ("Hugging Face model", hub_model)):
        if value is not None and not isinstance(value, str):
            raise user_error(f"The {what} must be text, got {type(value).__name__}.")
    sources.check_choice(depth_source, hub_model)  # a hub model: offered, cached (ms)


class LoadEvents:
    """The upload events of a :class:`~app.handlers.RefocusApp`: a photo and its depth
    source loaded into a session."""

    def load(self, *args: Any, **kwargs: Any) -> tuple:
        """:meth:`load_steps` without a first look: the outputs of the full-resolution
        render (the same arguments)."""
        *_, last = self.load_steps(*args, first_look=False, **kwargs)
        return last

    @_remember_load_error
    @reported
    def load_steps(
        self,
        image: Any,
        depth: Any,
        depth_kind: str,
        session: Session | None,
        focus: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
        depth_source: Any = sources.AUTO,
        hub_model: Any = "",
        blur_on: Any = True,
        request: gr.Request | None = None,
        *,
        first_look: bool = True,
    ) -> Iterator[tuple]:
        """Decode an upload (and optional depth map), prepare it (cached), render it.

        A generator of the outputs: with ``first_look``, a photo over
        :data:`~app.settings.FIRST_LOOK_PIXELS` is shown first at the size of the render
        pass (:meth:`_render_first_look`, a fifth of the full render's time at 12 MP), then at
        full resolution; else the full render only.

        ``focus`` is the focus slider's position (0 = nearest, 1 = farthest), ``f_number``
        the aperture (K follows from the photo's long side, :func:`blur_px`), ``blur_on``
        False renders no blur. The new session replaces ``session``; past
        :attr:`max_sessions` other live sessions the upload is refused with a message.
        ``request`` (given by Gradio) names the browser tab, whose sessions are closed when
        it is closed.

        Returns:
            ``(session, focus, result, compare, legend, info)``; ``focus`` is the slider
            position of the focal plane the photo's camera used when it carries one, else of
            the subject found in the depth (:meth:`D2F.subject_focus`: the network's, or the
            phone's depth recorded without a focal plane), and skipped for a depth map of
            the user's own (the slider's focus is kept).
        """
        path = _payload_path(image)
        if path is None:  # the input was cleared
            if session is not None:
                session.close()
            cleared = (gr.update(value=None), gr.update(value=None), gr.update(visible=False))
            yield (None, gr.skip(), *cleared, "")
            return
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            size=None,
        )  # fmt: skip
        _check_texts(view, depth_kind, hub_model, depth_source)
        t0 = time.perf_counter()
        upload = self._decoded_upload(session, image, path, depth, depth_kind, depth_source,
                                      hub_model, params)  # fmt: skip
        photo, chosen, params = upload.photo, upload.chosen, upload.params
        t_decode = time.perf_counter()
        self._admit(session)
        key = sources.scene_key(content_key(photo.image, upload.disparity), chosen)
        scene, cached = self.cache.get_or_prepare(
            self.model,
            key,
            lambda: sources.prepare(self.model, photo.image, upload.disparity, chosen),
        )
        source = sources.describe(scene, upload.source)
        t_prepare = time.perf_counter()
        params, found, subject = self._loaded_focus(scene, params, upload.search)
        new_focus = upload.new_focus if found is None else found
        new = Session(
            key=key,
            get_scene=no_scene,  # set below, once the upload is kept
            name=_payload_name(upload.photo_name),
            shown_size=photo.shown_size,
            size=photo.size,
            before=imaging.fit_display(imaging.to_uint8(photo.image)),
            icc_profile=photo.icc_profile,
            exif=photo.exif,
            owner=getattr(request, "session_hash", None),
            auto_range=params.focal_range,
        )
        new.get_scene = self._scene_source(new, key, upload.path, upload.photo_name,
                                           upload.depth_path, depth_kind, upload.depth_name,
                                           chosen)  # fmt: skip
        # closed once the new session has its own copy of the upload (which may be the old
        # session's copy, when the panel showed the app's picture)
        if session is not None:
            session.close()
        if photo.from_original or not photo.browser_shows:
            self._write_panel(new)
        self._register(new)
        session = new
        prep = "cached scene" if cached else f"prepare {1000 * (t_prepare - t_decode):.0f} ms"
        log.info(
            "loaded %s (%dx%d), depth: %s, %s %r", session.name, *session.size, source, prep, image
        )
        loaded = f" | decode {1000 * (t_decode - t0):.0f} ms | {prep} | depth: {source}{subject}"
        steps = self._render_shown(session, params, view, scene, loaded, first_look)
        del scene
        try:
            for outputs in steps:
                yield (session, new_focus, *outputs)
                new_focus = gr.skip()  # set by the first picture (the user may move it since)
        except Exception:
            session.close()
            raise

    def _decoded_upload(
        self,
        session: Session | None,
        image: Any,
        path: str,
        depth: Any,
        depth_kind: str,
        depth_source: Any,
        hub_model: Any,
        params: RenderParams,
    ) -> _Upload:
        """The upload's files checked and decoded, the depth source chosen (the "Depth
        source" control, :mod:`app.sources`), the notes said (a resized map, the depth used),
        and the focus the photo brings: the camera's focal plane, or a search for the
        subject where there is none (a map of one's own keeps the slider's focus)."""
        photo_name = _payload_name(image, ext=True)
        behind = self._upload_behind_panel(session, path)
        if behind is not None:  # the panel shows the app's picture: load what it stands for
            path, photo_name = behind
        else:
            self._check_file(path)
        depth_path = _payload_path(depth)
        if depth_path is not None:
            self._check_file(depth_path)
        depth_name = _payload_name(depth, "depth map", ext=True)
        notes: list[str] = []
        photo, disparity, source, depth_size = self._decode(
            path, photo_name, depth_path, depth_kind, depth_name, notes
        )
        for note in notes:
            gr.Warning(note)
        # the "Depth source" control (app/sources.py): the scene cache keys on the source
        chosen, note = sources.resolve(
            depth_source,
            hub_model,
            depth_path is not None,
            photo.disparity is not None,
            getattr(self.model.config, "depth_source", "d2f"),
        )
        if note:
            gr.Warning(note)
        disparity, own_map = sources.pick(chosen, disparity, photo)
        if not own_map:
            depth_size = None
            if chosen == "embedded":
                source = f"depth embedded in the photo ({photo.depth_source})"
        new_focus = gr.skip()
        if photo.notice:
            gr.Warning(photo.notice)
        if depth_size is not None:
            w, h = photo.size
            dw, dh = depth_size
            if (dw, dh) != (w, h):
                gr.Info(f"The depth map ({dw}x{dh}) was resized to the photo ({w}x{h}).")
        elif disparity is not None:
            gr.Info(f"Using the {source}.")
            if photo.focus is not None:
                new_focus = position_of(photo.focus)
                params = dataclasses.replace(params, focus=disparity_of(new_focus))
        # no focal plane from the camera (none recorded with the phone's depth, or no depth):
        # focus on the subject; a map of the user's own keeps the slider's focus
        search = not own_map and (disparity is None or photo.focus is None)
        return _Upload(
            photo=photo,
            disparity=disparity,
            source=source,
            chosen=chosen,
            params=params.sized(photo.size),
            new_focus=new_focus,
            search=search,
            path=path,
            photo_name=photo_name,
            depth_path=depth_path,
            depth_name=depth_name,
        )

    def _loaded_focus(self, scene: Any, params: RenderParams, search: bool) -> tuple:
        """``(params, position, note)``: the focus and focal range a load sets. With
        ``search``, the automatic focus (``D2F.default_focus``: the subject, with the range
        that keeps it sharp), its focus slider position and a note for the status line;
        else the thin lens at ``params``' focus (the camera's focal plane, or the slider's on
        a map of one's own), ``None`` and no note."""
        params = dataclasses.replace(params, focal_range=0.0)
        if not search:
            return params, None, ""
        t0 = time.perf_counter()
        focus, auto_range, (sx, sy), _ = self.model.default_focus(scene)
        ms = 1000 * (time.perf_counter() - t0)
        position = position_of(focus)
        params = dataclasses.replace(
            params,
            focus=disparity_of(position),
            focal_range=round(min(auto_range, FOCAL_RANGE_MAX), 3),
        )
        note = f" | focus on the subject at ({sx:.0f}, {sy:.0f}) in {ms:.0f} ms"
        return params, position, note

    def _decode(
        self,
        path: str,
        name: str,
        depth_path: str | None,
        depth_kind: Any,
        depth_name: str,
        notes: list[str] | None = None,
    ) -> tuple[imaging.Photo, np.ndarray | None, str, tuple[int, int] | None]:
        """``(photo, disparity or None, where the disparity comes from, the depth file's
        size or None)`` of an upload; what the user should know of the map is added to
        ``notes`` (:func:`app.imaging.depth_notes`)."""
        photo = imaging.load_photo(path, name)
        if depth_path is not None:
            kind = "depth" if str(depth_kind).startswith("depth") else "disparity"
            disparity, size = imaging.load_depth_map(
                depth_path, photo.size, kind, depth_name, notes
            )
            return photo, disparity, f"your {kind} map", size
        if photo.disparity is not None:
            source = f"depth embedded in the photo ({photo.depth_source})"
            return photo, photo.disparity, source, None
        return photo, None, "network", None

    def _scene_source(
        self,
        session: Session,
        key: str,
        path: str,
        name: str,
        depth_path: str | None,
        depth_kind: Any,
        depth_name: str,
        chosen: str,
    ) -> Callable[[], Any]:
        """``() -> Scene``: the cached scene of ``key``, else the session's copy of the
        upload decoded and prepared again (the cache may have dropped it for other photos)."""
        folder = self._session_dir(session, "upload")
        # the copy carries the user's file name: the photo panel may show it again (after a
        # failed upload) and send it back (a depth source switched), and its name is the one
        # the download and the command give
        kept = folder / (_safe_stem(name, 80) + Path(path).suffix.lower())
        shutil.copyfile(path, kept)
        session.upload, session.source_path, session.upload_name = kept, path, name
        kept_depth = None
        if depth_path is not None:
            kept_depth = folder / f"depth{Path(depth_path).suffix.lower()}"
            shutil.copyfile(depth_path, kept_depth)
        model, cache = self.model, self.cache

        def prepare() -> Any:
            photo, disparity, _, _ = self._decode(
                str(kept), name, None if kept_depth is None else str(kept_depth), depth_kind,
                depth_name,
            )  # fmt: skip
            log.info("preparing %s again (dropped from the scene cache)", name)
            disparity, _ = sources.pick(chosen, disparity, photo)
            return sources.prepare(model, photo.image, disparity, chosen)

        def get_scene() -> Any:
            scene = cache.get(model, key)
            if scene is None:
                scene, _ = cache.get_or_prepare(model, key, prepare)
            return scene

        return get_scene

    def _write_panel(self, session: Session) -> None:
        """Put the picture the app renders from in the photo panel (:meth:`photo_panel`).

        A Lens Blur file's main picture is the phone's blurred rendering; the app renders
        from the all-in-focus original embedded in it (``d2f_core.io.load_photo``), which
        can differ in size. A file the browser cannot show (HEIC, TIFF) would be a broken
        image that cannot be clicked. The panel gets the decoded photo at display size, and
        clicks on it are mapped from its size (:attr:`Session.shown_size`).
        """
        folder = self._session_dir(session, "panel")
        safe = _safe_stem(session.upload_name or session.name, 60)
        path = folder / f"{PANEL_PREFIX}{uuid.uuid4().hex[:12]}-{safe}.jpg"
        imaging.write_display(session.before, path)
        session.panel = path
        session.shown_size = (session.before.shape[1], session.before.shape[0])

    @staticmethod
    def loaded_range(session: Session | None) -> Any:
        """The focal range slider after a load: the subject's range with the automatic
        focus, 0 (thin lens) otherwise; ``gr.skip()`` without a photo."""
        if isinstance(session, Session) and not session.closed:
            return session.auto_range
        return gr.skip()

    @staticmethod
    def photo_panel(session: Session | None) -> Any:
        """The photo panel after a successful load: the picture the app renders from when
        it is not the uploaded file's main picture (a Lens Blur file's embedded original) or
        the browser cannot show the file (HEIC), else ``gr.skip()`` (the panel already shows
        the upload).

        Setting the panel fires the input's ``.change`` only; the app loads on ``.upload``.
        """
        if isinstance(session, Session) and session.panel is not None and not session.closed:
            return gr.update(value=str(session.panel))
        return gr.skip()

    def _check_file(self, path: str) -> None:
        """Refuse a path that the client may not make the server open, with one message
        that says nothing of the path (:class:`app.uploads.UploadGate`)."""
        if self.files is not None and not self.files.allows(path):
            raise user_error(NOT_AN_UPLOAD)

    @staticmethod
    def _upload_behind_panel(session: Session | None, path: str) -> tuple[str, str] | None:
        """``(path, name)`` of the upload behind the picture in the photo panel when the
        photo input sends that picture back (a depth map or depth source was changed after
        a Lens Blur upload), else None.

        Raises:
            SessionClosed: the panel's picture belongs to no live session (closed when idle):
                it holds neither the depth nor the full-size photo, so it is not loaded.
        """
        name = Path(path).name
        if not name.startswith(PANEL_PREFIX):
            return None
        live = (
            isinstance(session, Session)
            and not session.closed
            and session.panel is not None
            and session.upload is not None
            and session.panel.name == name
        )
        if not live:
            raise SessionClosed
        return str(session.upload), session.upload_name or session.upload.name

    def note_load_error(self, owner: str | None, message: str) -> None:
        """Keep the message of a failed upload for :meth:`after_failed_load` (per tab)."""
        if owner is None:
            return
        with self._sessions_lock:
            self._load_errors[owner] = message
            while len(self._load_errors) > 1000:
                self._load_errors.popitem(last=False)

    def after_failed_load(
        self, session: Session | None, image: Any, request: gr.Request | None = None
    ) -> tuple:
        """Bring the page back to one state after an upload failed (chained on failure).

        The photo panel showed the file that could not be read while the result and status
        showed the previous photo. It shows the photo that is loaded again (or nothing when
        none is), and the status keeps the error, where it stays after the toast is gone.

        Returns:
            ``(photo, result, compare, legend, info, download)`` updates.
        """
        owner = getattr(request, "session_hash", None)
        with self._sessions_lock:
            message = self._load_errors.pop(owner, None) if owner else None
        message = message or "The upload could not be read."
        live = isinstance(session, Session) and not session.closed and session.upload
        if live:
            # the photo input failed (not the depth map): show the loaded photo again
            path = _payload_path(image)
            panel = session.panel
            same = path == session.source_path or (
                panel is not None and path is not None and Path(path).name == panel.name
            )
            shown = panel if panel is not None else session.upload
            photo = gr.skip() if same else gr.update(value=str(shown))
            info = f"Error: {message} Still showing {session.name}."
            return (photo, gr.skip(), gr.skip(), gr.skip(), info, gr.skip())
        return (
            gr.update(value=None),
            gr.update(value=None, visible=True),
            gr.update(value=None, visible=False),
            gr.update(visible=False),
            f"Error: {message}",
            gr.update(value=None, label="Download", interactive=False),
        )
