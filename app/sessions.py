"""The per-session cache of the app: each user's :class:`Session` (the prepared photo, its
renders and files, in ``gr.State``), the live sessions of the server, memory given back
when a session closes, and :func:`reported`, which holds an event's session while it runs and
turns its failures into messages.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import inspect
import logging
import shutil
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from app.reporting import CLOSED_MESSAGE, MADE_ROOM_MESSAGE, one_line, user_error
from app.settings import RenderParams

# the app's events log under one name, whichever module holds them
log = logging.getLogger("app.handlers")


#: Display and download files kept per session: Gradio copies each one into its cache once
#: the event that made it returns, so only files at least :data:`FILE_MIN_AGE_S` old are
#: removed, and never the newest :data:`DISPLAY_FILES_KEPT` (an event may still be waiting
#: for its copy while others of the same session write theirs).
DISPLAY_FILES_KEPT = 8
FILE_MIN_AGE_S = 60.0
#: Live sessions (a photo loaded, not yet expired); an upload past it gets a message.
DEFAULT_MAX_SESSIONS = 16
#: A session unused this long (seconds) is closed: its pictures and files are freed.
DEFAULT_SESSION_IDLE_S = 1800.0
#: Long side of the live preview rendered while a slider is dragged.


class SessionClosed(Exception):
    """An event reached a session that was closed (expired, ended, or replaced)."""


@dataclass
class Session:
    """One user's work: where its prepared scene is found, and what was last shown.

    A session holds no scene: :attr:`scene` looks the photo up in the process-wide scene
    cache by :attr:`key` and prepares it again from the session's copy of the upload when
    the cache has dropped it. Its own memory is the display-size pictures (``before``,
    ``views``); the latest full render is kept on disk (:attr:`last_full`).

    Attributes:
        key: the photo's key in the scene cache (:func:`app.cache.content_key`).
        get_scene: ``() -> Scene`` for :attr:`key` (cache, else prepare again).
        name: file stem of the upload, used for the download's name.
        shown_size: ``(width, height)`` of the picture in the photo panel; clicks come in
            these coordinates (the upload as the browser shows it, or :attr:`panel`).
        size: ``(width, height)`` of the scene (the upload, possibly downscaled).
        before: ``(h, w, 3)`` uint8 input at display size.
        views: the last render at display size (:class:`app.imaging.DisplayViews`, empty
            before the first): ``"Bokeh"`` ``(h, w, 3)`` uint8, the maps ``(h, w)`` uint8
            (0..255 for 0..1), coloured when shown.
        pass_width: width in px of the rendering pass of :attr:`views` (a preview's pass is
            its own size): the defocus map's scale (its 1 is 69 px at that pass).
        full_params: params of the full-resolution render the views hold or will hold
            (None: none, or a preview has replaced it).
        full_seq: counts full-resolution renders; a preview that overlaps one is dropped.
        wanted: params of the latest render asked for (full or preview): a
            render of other params that finishes after it was asked for is dropped, so the
            picture always belongs to the last value the user set (:meth:`still_wanted`).
        last_full_params: params of the latest full render (the picture at the screen's
            size; its full resolution is rendered for the download).
        last_full_info: the status line of that full render.
        full_res_params: params of the full-resolution picture on disk (:attr:`last_full`).
        last_preview: params of the latest preview asked for.
        asked_before: the values asked for before :attr:`wanted` (the last other ones):
            the page's when a release or option's full render that the user made before
            them reached the server after them (:meth:`ask`).
        download_file: ``(params, format, path)`` of the latest download file written.
        folder: this session's folder for display and download files (removed with it).
        icc_profile, exif: metadata of the upload, written into the download.
        owner: the Gradio session hash of the browser tab or client that loaded it.
        upload: the session's copy of the uploaded photo (shown again after a failed upload).
        upload_name: the user's file name of the upload.
        source_path: the upload's path as Gradio gave it.
        panel: the picture the app put in the photo panel in place of the upload, or None:
            for a Lens Blur file, the embedded all-in-focus original that is rendered from,
            at display size (:meth:`RefocusApp.photo_panel`).
        last_used: ``time.monotonic()`` of its latest event.
        closed: True once :meth:`close` ran.
        closed_message: what an event on the closed session tells its user (None: the
            usual :data:`~app.reporting.CLOSED_MESSAGE`).
        brushes: the focus and blur paint (:class:`d2f_core.depth.brushes.Brushes`) every
            render of the session applies, or None; :attr:`paint_id` names it (its hash) and
            :attr:`paint_files` holds the masks as painted (PNG, for the reproduce command).
        auto_range: the focal range the load gave the photo with its automatic focus.
        loupe_point: the full-res point the 100 % loupe shows (None until the result is
            clicked).
        token: this photo's name on the page (its hidden ``photo_id`` box): every render
            event sends the one the page held when the event started, and an event started
            for another photo than the session's is dropped (:meth:`shown_by`).
    """

    key: str
    get_scene: Callable[[], Any] = field(repr=False)
    name: str
    shown_size: tuple[int, int]
    size: tuple[int, int]
    before: np.ndarray
    views: Any = field(default_factory=dict)
    pass_width: int = 0
    full_params: RenderParams | None = None
    full_seq: int = 0
    wanted: RenderParams | None = None
    last_full_params: RenderParams | None = None
    last_full_info: str = ""
    full_res_params: RenderParams | None = None
    last_preview: RenderParams | None = None
    asked_before: RenderParams | None = None
    download_file: tuple[RenderParams, str, Path] | None = None
    folder: Path | None = None
    icc_profile: bytes | None = None
    exif: bytes | None = None
    owner: str | None = None
    upload: Path | None = None
    upload_name: str | None = None
    source_path: str | None = None
    panel: Path | None = None
    last_used: float = field(default_factory=time.monotonic)
    closed: bool = False
    closed_message: str | None = None
    files_written: int = 0
    on_close: Callable[[Session], None] | None = field(default=None, repr=False)
    busy: int = 0
    token: str = field(default_factory=lambda: uuid.uuid4().hex)
    brushes: Any = field(default=None, repr=False)
    paint_id: str = ""
    paint_files: dict[str, Path] = field(default_factory=dict)
    auto_range: float = 0.0
    loupe_point: tuple[float, float] | None = None
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    @property
    def scene(self) -> Any:
        """The prepared scene (from the shared cache, or prepared again), with this
        session's brush paint (:attr:`brushes`)."""
        if self.closed:
            raise SessionClosed
        scene = self.get_scene()
        if self.brushes is not None:
            scene = dataclasses.replace(scene, brushes=self.brushes)
        return scene

    @property
    def last_full(self) -> np.ndarray | None:
        """``(H, W, 3)`` uint8 of the latest full render (read from the session's folder)."""
        if self.last_full_params is None or self.folder is None:
            return None
        if self.full_res_params != self.last_full_params:
            return None  # rendered at the screen's size only, so far
        try:
            return np.load(self.folder / "last_full.npy")
        except FileNotFoundError:
            return None

    def ask(self, params: RenderParams) -> None:
        """A render of ``params`` was asked for (call with :attr:`lock` held)."""
        if params != self.wanted:
            self.asked_before = self.wanted
        self.wanted = params

    def shows_last_full(self, status: Any) -> bool:
        """Whether a page whose status line reads ``status`` shows the last full render (a
        click's or an upload's status adds a note to the render's; call with :attr:`lock`
        held)."""
        return str(status).startswith(self.last_full_info)

    def still_wanted(self, params: RenderParams) -> bool:
        """Whether no render of other params was asked for since ``params`` (call with
        :attr:`lock` held, where the render's picture is stored)."""
        return self.wanted is None or self.wanted == params

    def shown_by(self, photo_id: Any) -> bool:
        """Whether an event that the page sent with ``photo_id`` (its ``photo_id`` box) was
        started for this photo. Gradio gives an event the session its tab holds when the
        event runs, which may be a photo uploaded after the event started; ``None`` or ``""``
        (an API client or a call from Python, which name no photo) is taken as this one."""
        return photo_id in (None, "") or str(photo_id) == self.token

    def touch(self) -> None:
        """Mark the session used now (idle sessions are closed); raise if it is closed."""
        with self.lock:
            if self.closed:
                raise SessionClosed
            self.last_used = time.monotonic()

    def hold(self) -> None:
        """An event starts using the session: it is not idle until :meth:`let_go`."""
        with self.lock:
            self.busy += 1
            self.last_used = time.monotonic()

    def let_go(self) -> None:
        with self.lock:
            self.busy -= 1
            self.last_used = time.monotonic()

    def close(self, idle_s: float | None = None) -> bool:
        """Free the pictures and delete the session's files (display, download, upload).

        With ``idle_s``, only if no event is using it and it was unused that long. Returns
        whether it was closed (now or before).
        """
        with self.lock:
            if idle_s is not None and (self.busy or time.monotonic() - self.last_used <= idle_s):
                return False
            self.closed = True
            self.views = {}
            self.before = np.zeros((1, 1, 3), np.uint8)
            self.last_full_params = None
            folder, self.folder = self.folder, None
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
        if self.on_close is not None:
            self.on_close(self)
        return True


def _libc_malloc_trim() -> Callable[[], Any] | None:
    try:
        import ctypes

        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


_MALLOC_TRIM = _libc_malloc_trim()


def give_back_memory() -> None:
    """Return the C heap's free pages to the system (glibc ``malloc_trim``).

    Freed pictures and scenes go back to malloc's arenas (one per worker thread), which
    keep the pages; after sessions close, this gives them back, so the process shrinks.
    """
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def no_scene() -> Any:
    raise SessionClosed


def delete_session(session: Session | None) -> None:
    """``gr.State`` delete callback: free the session when Gradio drops its state."""
    if isinstance(session, Session):
        session.close()


def prune_files(folder: Path, keep: int, min_age_s: float = FILE_MIN_AGE_S) -> None:
    """Delete the entries of ``folder`` beyond the newest ``keep`` (by name, which counts
    up) that are older than ``min_age_s``: a younger file may be an event's output that
    Gradio has not copied into its cache yet."""
    now = time.time()
    try:
        names = sorted(folder.iterdir())
    except FileNotFoundError:  # the session was closed meanwhile
        return
    for old in names[:-keep] if keep else names:
        try:
            if now - old.stat().st_mtime < min_age_s:
                continue
            if old.is_dir():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
        except FileNotFoundError:
            continue


def _closed_message(held: list[Session]) -> str:
    return next((s.closed_message for s in held if s.closed and s.closed_message), CLOSED_MESSAGE)


def _refusal(name: str, err: Exception, held: list[Session]) -> Exception:
    """The ``gr.Error`` a user sees for ``err`` raised by the event ``name``, logged."""
    if isinstance(err, gr.Error):
        log.info("%s refused: %s", name, one_line(err.message))
        return err
    if isinstance(err, SessionClosed):
        log.info("%s refused: the session was closed", name)
        return user_error(_closed_message(held))
    if any(session.closed for session in held):
        # the tab was closed (or the session expired) while the event ran, and its
        # files were removed under it: no fault of the input nor of the event
        log.info("%s stopped: the session was closed while it ran (%s)", name, type(err).__name__)
        return user_error(_closed_message(held))
    if isinstance(err, (ValueError, TypeError)):
        log.info("%s refused: %s", name, one_line(err))
        return user_error(str(err))
    if isinstance(err, MemoryError):
        log.error("out of memory in %s", name, exc_info=err)
        return user_error("The server ran out of memory; try a smaller photo.")
    log.error("unexpected failure in %s", name, exc_info=err)
    return user_error(f"Something went wrong ({type(err).__name__}); please retry.")


class _Dropped(Exception):
    """An event whose photo was replaced while it ran: its outputs are dropped."""


def _left_behind(owner: Any, held: list[Session], open_at_start: list[Session]) -> bool:
    """Whether a session among ``held`` was left behind by its page: closed while the event
    ran (only its own tab does that, by a new upload or by closing: idle sessions and those
    closed to make room are never in use), or closed before by the tab's new upload
    (``owner``, the :class:`SessionRegistry`, has a live session of the same tab)."""
    for session in held:
        if not session.closed:
            continue
        if any(session is s for s in open_at_start):
            return True
        if isinstance(owner, SessionRegistry) and owner.replaced(session):
            return True
    return False


@contextlib.contextmanager
def _reporting(name: str, args: tuple, dropping: bool = False) -> Iterator[None]:
    """The body of :func:`reported`: the sessions among ``args`` held (not idle) while the
    event ``name`` runs, and its exceptions turned into what the user sees. With
    ``dropping``, an event whose photo the page has left (:func:`_left_behind`) raises
    :class:`_Dropped` instead."""
    held = [a for a in args if isinstance(a, Session)]
    open_at_start = [s for s in held if not s.closed]
    for session in held:
        session.hold()
    try:
        yield
    except Exception as err:
        if dropping and _left_behind(args[0] if args else None, held, open_at_start):
            log.info("%s dropped: its photo was replaced (%s)", name, type(err).__name__)
            raise _Dropped from None
        refusal = _refusal(name, err, held)
        if refusal is err:
            raise
        raise refusal from None
    finally:
        for session in held:
            session.let_go()


def reported(fn: Callable | None = None, *, dropped: tuple | None = None) -> Callable:
    """Turn bad-input exceptions into ``gr.Error`` and anything else into a short one.

    A refused event (bad input, a closed session) logs one line naming the reason; only an
    unexpected failure logs its traceback. A generator (an event that shows a first
    picture, then the final one) is reported the same way while it runs.

    ``@reported(dropped=outputs)``: an event whose session its page has left (the tab
    uploaded another photo meanwhile, or was closed) returns (or yields) ``outputs``, its
    skips, instead of a message about a photo the page no longer shows.
    """
    if fn is None:
        return functools.partial(reported, dropped=dropped)
    dropping = dropped is not None

    if inspect.isgeneratorfunction(fn):

        @functools.wraps(fn)
        def steps(*args, **kwargs):
            try:
                with _reporting(fn.__name__, args, dropping):
                    yield from fn(*args, **kwargs)
            except _Dropped:
                yield dropped

        return steps

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            with _reporting(fn.__name__, args, dropping):
                return fn(*args, **kwargs)
        except _Dropped:
            return dropped

    return wrapper


class SessionRegistry:
    """The live sessions of a :class:`~app.handlers.RefocusApp`: admission, idle expiry
    and each session's files."""

    @property
    def live_sessions(self) -> int:
        """Sessions open now (a photo loaded, not closed)."""
        with self._sessions_lock:
            return len(self._sessions)

    def replaced(self, session: Session) -> bool:
        """Whether ``session`` is closed and the tab that loaded it has a photo open now
        (it uploaded another one: the page has left this one)."""
        if not session.closed or session.owner is None:
            return False
        with self._sessions_lock:
            return any(s.owner == session.owner for s in self._sessions.values())

    def _forget(self, session: Session) -> None:
        with self._sessions_lock:
            self._sessions.pop(id(session), None)

    def expire_idle(self) -> int:
        """Close the sessions unused for ``session_idle_s``; return how many."""
        now = time.monotonic()
        with self._sessions_lock:
            idle = [s for s in self._sessions.values() if now - s.last_used > self.session_idle_s]
        closed = 0
        for session in idle:
            if session.close(idle_s=self.session_idle_s):  # still idle: not in use since
                log.info("closed session %s: idle over %.0f s", session.name, self.session_idle_s)
                closed += 1
        if closed:
            give_back_memory()
        return closed

    def end_sessions(self, owner: str | None) -> int:
        """Close every session loaded by ``owner`` (a Gradio session hash); return how many.

        Wired to the page's unload event: a closed browser tab frees its photo at once.
        """
        if owner is None:
            return 0
        with self._sessions_lock:
            mine = [s for s in self._sessions.values() if s.owner == owner]
        for session in mine:
            session.close()
        if mine:
            give_back_memory()
        return len(mine)

    def _sweep_forever(self) -> None:
        while True:
            time.sleep(min(30.0, max(0.5, self.session_idle_s / 4)))
            try:
                self.expire_idle()
            except Exception:  # never let the sweeper die
                log.exception("session sweep failed")

    def _admit(self, replacing: Session | None) -> None:
        """Make room for one more session (``replacing`` is the uploader's own previous
        session, which the new one replaces): past :attr:`max_sessions`, the least recently
        used photo that no event is using is closed, and its user is told why when they come
        back; when every open photo is in use the upload is refused with a message."""
        if self._sweeper is None:
            self._sweeper = threading.Thread(
                target=self._sweep_forever, name="d2f-session-sweeper", daemon=True
            )
            self._sweeper.start()
        self.expire_idle()
        freed = False
        while True:
            with self._sessions_lock:
                others = [s for s in self._sessions.values() if s is not replacing]
            if len(others) < self.max_sessions:
                break
            idle = [s for s in others if not s.busy]
            if not idle:
                raise user_error(
                    f"The app is at its limit of {self.max_sessions} open photos and all of "
                    "them are in use. Please try again in a moment."
                )
            oldest = min(idle, key=lambda s: s.last_used)
            with oldest.lock:
                if oldest.busy:  # an event took it up meanwhile: look again
                    continue
                oldest.closed_message = MADE_ROOM_MESSAGE
                oldest.close()
            log.info("closed session %s to make room for a new photo", oldest.name)
            freed = True
        if freed:
            give_back_memory()

    def _register(self, session: Session) -> None:
        session.on_close = self._forget
        with self._sessions_lock:
            self._sessions[id(session)] = session
