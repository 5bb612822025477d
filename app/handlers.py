"""Event handlers of the refocusing app: convert inputs, call the core, shape the outputs.

Every handler is a method of :class:`RefocusApp`, which owns the model and the shared scene
cache; each user's work lives in a :class:`Session` kept in ``gr.State``. Handlers turn
``ValueError``/``TypeError`` from the core into ``gr.Error`` and any other failure into a
short ``gr.Error`` (the traceback goes to the log), so a user never sees a traceback and
one session's failure leaves the others alone.

Render outputs are always the 4-tuple ``(result, compare, legend, info)`` -- the selected
view as a ``gr.Image`` update, the before/after ``gr.ImageSlider`` update, the colour-bar
``gr.HTML`` update and a status line -- or ``gr.skip()`` for each when a newer render
has made this one obsolete.
"""

from __future__ import annotations

import atexit
import dataclasses
import functools
import inspect
import logging
import os
import shutil
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from app import imaging, sources
from app.cache import SCENE_CACHE, SceneCache, content_key
from app.uploads import NOT_AN_UPLOAD, UploadGate
from d2f_core.rendering.kernels import PAPER_GROWING_SIZES

log = logging.getLogger(__name__)

#: The adaptive renderer's error budgets (``D2F.render(budget=...)``), fastest last.
QUALITIES = ("high", "balanced", "fast")
VIEWS = ("Bokeh", "Before / after", "Disparity", "Defocus", "Fusion mask")
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
PREVIEW_MAX_SIDE = 512
FORMATS = ("PNG", "JPEG")
DEPTH_KINDS = ("disparity (bright = near)", "depth (bright = far)")
#: File names of the pictures the app puts in the photo panel (:meth:`RefocusApp.photo_panel`):
#: when the panel sends one back as the photo, the upload it stands for is used.
PANEL_PREFIX = "d2f-rendered-from-"
#: Focus values are rounded to the focus slider's step, so that a value the app sets and
#: the value the slider sends back compare equal.
FOCUS_DECIMALS = 3

# The controls speak a photographer's language; the library keeps its own units. The focus
# slider reads near (0, left) to far (1, right); the library's focal plane is a disparity,
# 1 = near: disparity = 1 - slider. The disparity map is relative (normalised per photo,
# not metres), so no distance scale is invented: the slider stays linear in disparity, where
# the blur of a point grows linearly with its distance |d - f| from the focal plane, and
# equal steps of the slider change the blur by equal amounts.
#
# The blur control is the f-number N of a virtual lens. With the disparity read as
# d = z_near / z (1 at the nearest point, 0 at infinity), the thin-lens blur circle on the
# sensor is about F^2 / N * |1/z - 1/z_f| = F^2 / (N z_near) * |d - d_f|, so the library's K
# (blur circle diameter in px at full resolution for |d - f| = 1) is
#     K = F^2 / (N z_near) * (long side in px / sensor width).
#: The virtual lens: focal length F (mm) on a full-frame sensor (its 36 mm width spans the
#: photo's long side), with the nearest point of the photo this far away (m).
LENS_FOCAL_MM = 50.0
SENSOR_WIDTH_MM = 36.0
NEAREST_M = 1.0
#: K per pixel of the photo's long side at f/1: F^2 / (z_near * sensor width) = 0.0694.
BLUR_PER_PX_AT_F1 = LENS_FOCAL_MM**2 / (NEAREST_M * 1000.0 * SENSOR_WIDTH_MM)
#: The aperture slider's range and default: f/1 (most blur) to f/22.
F_NUMBER_RANGE = (1.0, 22.0)
DEFAULT_F_NUMBER = 1.4
#: K is capped here (the old px slider's top, and the range the renderer is timed for):
#: f/1 reaches it on a long side of 4320 px and more (12 MP at 3:2), 278 px at 4000 px.
MAX_BLUR_PX = 300.0
#: The photo size the blur note under the aperture slider describes before an upload.
REFERENCE_SIZE = (4000, 3000)


def disparity_of(position: float) -> float:
    """The library's focal plane (disparity, 1 = near) for a focus slider position (0 =
    nearest, 1 = farthest)."""
    return round(1.0 - float(position), FOCUS_DECIMALS)


def position_of(disparity: float) -> float:
    """The focus slider position (0 = nearest, 1 = farthest) of a disparity (1 = near)."""
    return round(1.0 - float(disparity), FOCUS_DECIMALS)


def blur_px(f_number: float, long_side: int) -> float:
    """K (px at full resolution, for |d - f| = 1) of the virtual lens at ``f_number`` on a
    photo whose long side is ``long_side`` px, capped at :data:`MAX_BLUR_PX`, to 0.1 px."""
    return round(min(MAX_BLUR_PX, BLUR_PER_PX_AT_F1 * long_side / float(f_number)), 1)


def f_number_for(blur: float, long_side: int) -> float:
    """The f-number whose K is ``blur`` px on a photo with this long side (inverse of
    :func:`blur_px` below the cap), to 3 decimals."""
    return round(BLUR_PER_PX_AT_F1 * long_side / float(blur), 3)


#: The CoC (px at the render pass) that the defocus map draws as 1 (the paper's schedule).
MAX_DEFOCUS_COC = max(PAPER_GROWING_SIZES)

_LEGENDS = {
    "Disparity": ("viridis", "0 far", "1 near", "Disparity (network map or your upload)"),
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


@dataclass(frozen=True)
class RenderParams:
    """What a render depends on besides the scene; equal params give equal pictures.

    ``focus`` and ``blur`` are the library's (disparity, 1 = near; K in px at full
    resolution); ``f_number`` is the aperture chosen (None: blur off, ``blur`` is 0).
    """

    focus: float
    blur: float
    blades: int = 0
    rotation: float = 0.0
    highlight_boost: bool = True
    fusion: bool = True
    quality: str = "balanced"
    f_number: float | None = None

    @classmethod
    def from_inputs(
        cls,
        focus: Any,
        f_number: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        quality: Any = "balanced",
        blur_on: Any = True,
        *,
        size: tuple[int, int] | None,
    ) -> RenderParams:
        """Validate raw widget values (numbers may arrive as str/None from API callers).

        Args:
            focus: focus slider position, 0 = nearest .. 1 = farthest.
            f_number: aperture of the virtual lens (:func:`blur_px`).
            blur_on: False renders no blur (the photo as it is).
            size: ``(width, height)`` of the photo K is computed for; None gives K = 0 (to
                check the inputs before the photo is known; :meth:`sized` sets it).
        """
        try:
            position = round(float(focus), FOCUS_DECIMALS)
            n = round(float(f_number), 3)
            blades_n = int(float(blades or 0))
            r = round(float(rotation or 0.0), 3)
        except (TypeError, ValueError):
            raise user_error(
                f"Invalid slider values: focus={focus!r}, f-number={f_number!r}, "
                f"blades={blades!r}, rotation={rotation!r}."
            ) from None
        if not 0.0 <= position <= 1.0:
            raise user_error(f"focus must be in [0, 1] (0 = near, 1 = far), got {position}.")
        if not 0.5 <= n <= 1000.0:
            raise user_error(f"The f-number must be in [0.5, 1000], got {n:g}.")
        if blades_n < 0 or blades_n in (1, 2):
            raise user_error(f"blades must be 0 (round) or at least 3, got {blades_n}.")
        quality = "balanced" if quality in (None, "") else str(quality)
        if quality not in QUALITIES:
            raise user_error(f"quality must be one of {', '.join(QUALITIES)}, got {quality!r}.")
        on = blur_on not in (False, None, 0, "false", "False")
        params = cls(disparity_of(position), 0.0, blades_n, r, bool(highlight_boost),
                     bool(fusion), quality, n if on else None)  # fmt: skip
        return params.sized(size)

    def sized(self, size: tuple[int, int] | None) -> RenderParams:
        """These params with K for a photo of ``size = (width, height)`` (0 for None)."""
        k = 0.0 if self.f_number is None or not size else blur_px(self.f_number, max(size))
        return dataclasses.replace(self, blur=k)

    @property
    def position(self) -> float:
        """The focus slider position of :attr:`focus` (0 = nearest, 1 = farthest)."""
        return position_of(self.focus)

    def blur_text(self) -> str:
        """The aperture and the blur it gives, for the status line."""
        if self.f_number is None:
            return "no blur"
        return f"f/{self.f_number:g}, blur {self.blur:g} px"

    def render_options(self) -> dict[str, Any]:
        """Keyword options for ``D2F.render`` (and on to ``rendering.render``)."""
        return {
            "fusion": self.fusion,
            "blades": self.blades,
            "rotation": self.rotation,
            "highlight_boost": self.highlight_boost,
            "budget": self.quality,
        }


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
        views: the last render at display size: ``"Bokeh"`` ``(h, w, 3)`` uint8, the maps
            ``(h, w)`` uint8 (0..255 for 0..1), coloured when shown.
        pass_width: width in px of the rendering pass of :attr:`views` (a preview's pass is
            its own size): the defocus map's scale (its 1 is 69 px at that pass).
        full_params: params of the full-resolution render the views hold or will hold
            (None: none, or a preview has replaced it).
        full_seq: counts full-resolution renders; a preview that overlaps one is dropped.
        last_full_params: params of the full render saved for the download.
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
    """

    key: str
    get_scene: Callable[[], Any] = field(repr=False)
    name: str
    shown_size: tuple[int, int]
    size: tuple[int, int]
    before: np.ndarray
    views: dict[str, np.ndarray] = field(default_factory=dict)
    pass_width: int = 0
    full_params: RenderParams | None = None
    full_seq: int = 0
    last_full_params: RenderParams | None = None
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
    files_written: int = 0
    on_close: Callable[[Session], None] | None = field(default=None, repr=False)
    busy: int = 0
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False)

    @property
    def scene(self) -> Any:
        """The prepared scene (from the shared cache, or prepared again)."""
        if self.closed:
            raise SessionClosed
        return self.get_scene()

    @property
    def last_full(self) -> np.ndarray | None:
        """``(H, W, 3)`` uint8 of the latest full render (read from the session's folder)."""
        if self.last_full_params is None or self.folder is None:
            return None
        try:
            return np.load(self.folder / "last_full.npy")
        except FileNotFoundError:
            return None

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


def _no_scene() -> Any:
    raise SessionClosed


def delete_session(session: Session | None) -> None:
    """``gr.State`` delete callback: free the session when Gradio drops its state."""
    if isinstance(session, Session):
        session.close()


def _prune(folder: Path, keep: int, min_age_s: float = FILE_MIN_AGE_S) -> None:
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


def user_error(message: str) -> gr.Error:
    """A ``gr.Error`` for the user's toast; expected, so no traceback in the server log."""
    return gr.Error(message, print_exception=False)


def one_line(message: Any, limit: int = 300) -> str:
    """A message on one line of at most ``limit`` characters, for the server log."""
    text = " ".join(str(message).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


#: What an event on a closed session answers.
CLOSED_MESSAGE = (
    "This photo was closed to free memory (unused for a while, or the page was closed); "
    "please upload it again."
)


def reported(fn: Callable) -> Callable:
    """Turn bad-input exceptions into ``gr.Error`` and anything else into a short one.

    A refused event (bad input, a closed session) logs one line naming the reason; only an
    unexpected failure logs its traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        # the session an event works on is not idle while the event runs
        held = [a for a in args if isinstance(a, Session)]
        for session in held:
            session.hold()
        try:
            return fn(*args, **kwargs)
        except gr.Error as err:
            log.info("%s refused: %s", fn.__name__, one_line(err.message))
            raise
        except SessionClosed:
            log.info("%s refused: the session was closed", fn.__name__)
            raise user_error(CLOSED_MESSAGE) from None
        except Exception as err:
            if any(session.closed for session in held):
                # the tab was closed (or the session expired) while the event ran, and its
                # files were removed under it: no fault of the input nor of the event
                log.info(
                    "%s stopped: the session was closed while it ran (%s)",
                    fn.__name__, type(err).__name__,
                )  # fmt: skip
                raise user_error(CLOSED_MESSAGE) from None
            if isinstance(err, (ValueError, TypeError)):
                log.info("%s refused: %s", fn.__name__, one_line(err))
                raise user_error(str(err)) from None
            if isinstance(err, MemoryError):
                log.exception("out of memory in %s", fn.__name__)
                raise user_error("The server ran out of memory; try a smaller photo.") from None
            log.exception("unexpected failure in %s", fn.__name__)
            raise user_error(
                f"Something went wrong ({type(err).__name__}); please retry."
            ) from None
        finally:
            for session in held:
                session.let_go()

    return wrapper


SKIP4 = (gr.skip(), gr.skip(), gr.skip(), gr.skip())


def _remember_load_error(fn: Callable) -> Callable:
    """Keep a failed upload's message for the tab (``request``) that sent it, so that the
    chained :meth:`RefocusApp.after_failed_load` can show it in the status line."""
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def wrapper(self, *args, **kwargs):
        try:
            return fn(self, *args, **kwargs)
        except gr.Error as err:
            request = signature.bind_partial(self, *args, **kwargs).arguments.get("request")
            self.note_load_error(getattr(request, "session_hash", None), str(err.message))
            raise

    return wrapper


#: An event that needs a photo in a session that has none.
NO_PHOTO = "Upload a photo first: no photo is loaded in this session."

#: The download button while a preview is shown: nothing that matches the screen to save.
DOWNLOAD_WAIT = {"__type__": "update", "interactive": False}


def _env_number(name: str, default: float) -> float:
    raw = os.environ.get(name)
    try:
        return float(raw) if raw else default
    except ValueError:
        log.warning("ignoring %s=%r (not a number)", name, raw)
        return default


class RefocusApp:
    """The app's logic, independent of the page layout.

    Args:
        model: a ``d2f_core.pipeline.D2F`` (anything with ``prepare``, ``render``,
            ``focus_at``).
        cache: scene cache shared across sessions (default: the process-wide one).
        download_root: where per-session download folders go (default: a temp folder).
        max_sessions: live sessions at most (default ``D2F_APP_MAX_SESSIONS`` or 16); an
            upload that would open one more gets a message asking to retry later.
        session_idle_s: a session unused this long is closed (default
            ``D2F_APP_SESSION_IDLE_S`` or 1800 s).
        files: the check of the file paths that clients' payloads name (the server's
            :class:`app.uploads.UploadGate`: Gradio's own uploads and the samples only);
            ``None`` opens any path, for calls from Python.
    """

    def __init__(
        self,
        model: Any,
        cache: SceneCache | None = None,
        download_root: str | Path | None = None,
        *,
        max_sessions: int | None = None,
        session_idle_s: float | None = None,
        files: UploadGate | None = None,
    ) -> None:
        self.model = model
        self.files = files
        self.cache = SCENE_CACHE if cache is None else cache
        if download_root is None:
            download_root = tempfile.mkdtemp(prefix="d2f-app-")
            # sessions remove their own folders; this catches those alive at exit
            atexit.register(shutil.rmtree, download_root, ignore_errors=True)
        self.download_root = Path(download_root)
        self.download_root.mkdir(parents=True, exist_ok=True)
        if max_sessions is None:
            max_sessions = int(_env_number("D2F_APP_MAX_SESSIONS", DEFAULT_MAX_SESSIONS))
        if session_idle_s is None:
            session_idle_s = _env_number("D2F_APP_SESSION_IDLE_S", DEFAULT_SESSION_IDLE_S)
        if max_sessions < 1 or session_idle_s <= 0:
            raise ValueError(
                f"max_sessions must be >= 1 and session_idle_s > 0, got {max_sessions} and "
                f"{session_idle_s}"
            )
        self.max_sessions = int(max_sessions)
        self.session_idle_s = float(session_idle_s)
        self._sessions: dict[int, Session] = {}
        self._sessions_lock = threading.Lock()
        self._sweeper: threading.Thread | None = None
        # the last failed upload's message per browser tab, for after_failed_load
        self._load_errors: OrderedDict[str, str] = OrderedDict()

    # -------------------------------------------------------------- sessions
    @property
    def live_sessions(self) -> int:
        """Sessions open now (a photo loaded, not closed)."""
        with self._sessions_lock:
            return len(self._sessions)

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
        """Make room for one more session or refuse with a message (``replacing`` is the
        uploader's own previous session, which the new one replaces)."""
        if self._sweeper is None:
            self._sweeper = threading.Thread(
                target=self._sweep_forever, name="d2f-session-sweeper", daemon=True
            )
            self._sweeper.start()
        self.expire_idle()
        with self._sessions_lock:
            others = sum(1 for s in self._sessions.values() if s is not replacing)
        if others >= self.max_sessions:
            minutes = max(1, round(self.session_idle_s / 60))
            raise user_error(
                f"The app is at its limit of {self.max_sessions} open photos. Please try again "
                f"in a few minutes (a photo unused for {minutes} min is closed)."
            )

    def _register(self, session: Session) -> None:
        session.on_close = self._forget
        with self._sessions_lock:
            self._sessions[id(session)] = session

    # ----------------------------------------------------------------- views
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

    def _display_file(self, session: Session, image: np.ndarray) -> str:
        """Write a picture for the browser as JPEG (:func:`app.imaging.write_display`) and
        return its path; the download is written apart, at full resolution.

        Gradio would encode arrays itself as PNG at level 6 (0.7 s for 1600x1200 here); it
        copies the file into its cache after the event returns, so a file is removed only
        once it is old (see :func:`_prune`).
        """
        folder = self._session_dir(session, "display")
        path = folder / self._next_name(session, ".jpg")
        imaging.write_display(image, path)
        _prune(folder, DISPLAY_FILES_KEPT)
        return str(path)

    def _store_views(self, session: Session, result: Any, bokeh: np.ndarray) -> None:
        shown = imaging.fit_display(bokeh)
        size = (shown.shape[1], shown.shape[0])
        # maps come at the render pass's size; shown at the bokeh's size they line up when
        # the user switches views. Kept grey (one byte a pixel), coloured when shown.
        session.pass_width = int(result.defocus.shape[-1])
        session.views = {
            "Bokeh": shown,
            "Disparity": imaging.map_to_grey(result.disparity, size),
            "Defocus": imaging.map_to_grey(result.defocus, size),
            "Fusion mask": imaging.map_to_grey(result.fusion_mask, size),
        }

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
        text = (
            f"{w}x{h} px | focus {params.position:.3f} (0 = near, 1 = far; disparity "
            f"{params.focus:.3f}) | {params.blur_text()} | {kind} render {ms:.0f} ms"
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
        try:
            n = round(float(f_number), 3)
            if not n > 0:
                raise ValueError
        except (TypeError, ValueError):
            return lens
        live = isinstance(session, Session) and not session.closed
        w, h = session.size if live else REFERENCE_SIZE
        k = blur_px(n, max(w, h))
        capped = " (the most the app renders)" if k >= MAX_BLUR_PX else ""
        where = f"this {w}x{h} photo" if live else f"a {w}x{h} photo"
        return f"f/{n:g}: blur K = {k:g} px{capped} on {where} ({lens})"

    # ---------------------------------------------------------------- upload
    @_remember_load_error
    @reported
    def load(
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
    ) -> tuple:
        """Decode an upload (and optional depth map), prepare it (cached), render it.

        ``focus`` is the focus slider's position (0 = nearest, 1 = farthest), ``f_number``
        the aperture (K follows from the photo's long side, :func:`blur_px`), ``blur_on``
        False renders no blur. The new session replaces ``session``; past
        :attr:`max_sessions` other live sessions the upload is refused with a message.
        ``request`` (given by Gradio) names the browser tab, whose sessions are closed when
        it is closed.

        Returns:
            ``(session, focus, result, compare, legend, info)``; ``focus`` is the slider
            position of the focal plane the photo's camera used when it carries one, of the
            subject the network found when the photo comes with no depth
            (:meth:`D2F.subject_focus`), and skipped otherwise (a depth map given without a
            focal plane keeps the slider's focus).
        """
        path = _payload_path(image)
        if path is None:  # the input was cleared
            if session is not None:
                session.close()
            cleared = (gr.update(value=None), gr.update(value=None), gr.update(visible=False))
            return (None, gr.skip(), *cleared, "")
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            size=None,
        )  # fmt: skip
        # this event takes raw payloads (Gradio does not check them): the texts are checked here
        if view not in VIEWS:
            raise user_error(f"Unknown view {view!r}; expected one of {', '.join(VIEWS)}.")
        for what, value in (("depth map kind", depth_kind), ("Hugging Face model", hub_model)):
            if value is not None and not isinstance(value, str):
                raise user_error(f"The {what} must be text, got {type(value).__name__}.")
        t0 = time.perf_counter()
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
        photo, disparity, source, depth_size = self._decode(
            path, photo_name, depth_path, depth_kind, depth_name
        )
        # the "Depth source" control (app/sources.py): the scene cache keys on the source
        chosen, note = sources.resolve(
            depth_source, hub_model, depth_path is not None, photo.disparity is not None
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
        params = params.sized(photo.size)
        t_decode = time.perf_counter()
        self._admit(session)
        key = sources.scene_key(content_key(photo.image, disparity), chosen)
        scene, cached = self.cache.get_or_prepare(
            self.model, key, lambda: sources.prepare(self.model, photo.image, disparity, chosen)
        )
        source = sources.describe(scene, source)
        t_prepare = time.perf_counter()
        subject = ""
        if disparity is None:
            # no depth and no focal plane from the camera: focus on the subject the network found
            focus_found, (sx, sy) = self.model.subject_focus(scene)
            new_focus = position_of(focus_found)
            params = dataclasses.replace(params, focus=disparity_of(new_focus))
            subject = f" | focus on the subject at ({sx:.0f}, {sy:.0f})"
        new = Session(
            key=key,
            get_scene=_no_scene,  # set below, once the upload is kept
            name=_payload_name(photo_name),
            shown_size=photo.shown_size,
            size=photo.size,
            before=imaging.fit_display(imaging.to_uint8(photo.image)),
            icc_profile=photo.icc_profile,
            exif=photo.exif,
            owner=getattr(request, "session_hash", None),
        )
        new.get_scene = self._scene_source(new, key, path, photo_name, depth_path, depth_kind,
                                           depth_name, chosen)  # fmt: skip
        # closed once the new session has its own copy of the upload (which may be the old
        # session's copy, when the panel showed the app's picture)
        if session is not None:
            session.close()
        if photo.from_original:
            self._write_panel(new)
        self._register(new)
        session = new
        try:
            outputs = self._render_full(session, params, view, scene)
        except BaseException:
            session.close()
            raise
        prep = "cached scene" if cached else f"prepare {1000 * (t_prepare - t_decode):.0f} ms"
        log.info(
            "loaded %s (%dx%d), depth: %s, %s %r", session.name, *session.size, source, prep, image
        )
        info = (
            outputs[3]
            + f" | decode {1000 * (t_decode - t0):.0f} ms | {prep} | depth: {source}"
            + subject
        )
        return (session, new_focus, *outputs[:3], info)

    def _decode(
        self,
        path: str,
        name: str,
        depth_path: str | None,
        depth_kind: Any,
        depth_name: str,
    ) -> tuple[imaging.Photo, np.ndarray | None, str, tuple[int, int] | None]:
        """``(photo, disparity or None, where the disparity comes from, the depth file's
        size or None)`` of an upload."""
        photo = imaging.load_photo(path, name)
        if depth_path is not None:
            kind = "depth" if str(depth_kind).startswith("depth") else "disparity"
            disparity, size = imaging.load_depth_map(depth_path, photo.size, kind, depth_name)
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
        kept = folder / f"photo{Path(path).suffix.lower()}"
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
        can differ in size. The panel gets that original at display size, and clicks on it
        are mapped from its size (:attr:`Session.shown_size`).
        """
        folder = self._session_dir(session, "panel")
        stem = Path(session.upload_name or session.name).stem
        safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in stem)[:60] or "photo"
        path = folder / f"{PANEL_PREFIX}{uuid.uuid4().hex[:12]}-{safe}.jpg"
        imaging.write_display(session.before, path)
        session.panel = path
        session.shown_size = (session.before.shape[1], session.before.shape[0])

    @staticmethod
    def photo_panel(session: Session | None) -> Any:
        """The photo panel after a successful load: the picture the app renders from when
        it is not the uploaded file's main picture (a Lens Blur file's embedded original),
        else ``gr.skip()`` (the panel already shows the upload).

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

    # --------------------------------------------------------------- renders
    def _render_full(
        self, session: Session, params: RenderParams, view: str, scene: Any = None
    ) -> tuple:
        session.touch()
        with session.lock:
            session.full_seq += 1
            seq = session.full_seq
            session.full_params = params
        try:
            if scene is None:
                scene = session.scene
            t0 = time.perf_counter()
            result = self.model.render(scene, params.focus, params.blur, **params.render_options())
            del scene
            ms = 1000 * (time.perf_counter() - t0)
        except BaseException:
            with session.lock:
                if session.full_seq == seq:
                    session.full_params = None
            raise
        bokeh = imaging.to_uint8(result.bokeh)
        with session.lock:
            if session.full_seq != seq or session.closed:
                return SKIP4  # a newer full render is on its way
            # the full render waits on disk for the download, not in memory
            folder = self._session_dir(session, "")
            part = folder / "last_full.part.npy"
            np.save(part, bokeh)
            os.replace(part, folder / "last_full.npy")
            session.last_full_params = params
            self._store_views(session, result, bokeh)
        extra = self._settings_text(result.settings, params.quality)
        return (*self.view_outputs(session, view), self._info(session, params, "full", ms, extra))

    @reported
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
    ) -> tuple:
        """Full-resolution render (slider released, option changed).

        ``focus`` is the focus slider's position (0 = nearest, 1 = farthest), ``f_number``
        the aperture, ``blur_on`` False renders no blur (see :meth:`RenderParams.from_inputs`).

        Without a photo loaded in the session (a slider released on an empty page, an API
        call before ``/load`` or from another session) the event is refused with a message;
        the previews of a drag before that stay silent.

        Returns:
            ``(result, compare, legend, info)``.
        """
        if session is None:
            raise user_error(NO_PHOTO)
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            size=session.size,
        )  # fmt: skip
        session.touch()
        with session.lock:
            if params == session.full_params:
                return SKIP4  # already rendered (or being rendered) at full resolution
        return self._render_full(session, params, view)

    @reported
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
    ) -> tuple:
        """Reduced-resolution render while a slider moves.

        Dropped (``gr.skip()``) when a full render of the same params was requested, or when
        a full render started while this preview ran: a preview must never replace the full
        result that the release of the slider asked for. While a preview is shown the
        download button is disabled (it would save another picture than the one on screen);
        the full render that follows enables it again.

        Returns:
            ``(result, compare, legend, info, download)``.
        """
        if session is None:
            return (*SKIP4, gr.skip())
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            size=session.size,
        )  # fmt: skip
        session.touch()
        with session.lock:
            if params == session.full_params:
                return (*SKIP4, gr.skip())
            seq = session.full_seq
        t0 = time.perf_counter()
        result = self.model.render(
            session.scene,
            params.focus,
            params.blur,
            max_side=PREVIEW_MAX_SIDE,
            **params.render_options(),
        )
        ms = 1000 * (time.perf_counter() - t0)
        bokeh = imaging.to_uint8(result.bokeh)
        with session.lock:
            if session.full_seq != seq or params == session.full_params or session.closed:
                return (*SKIP4, gr.skip())
            self._store_views(session, result, bokeh)
            # the views no longer hold the full render: releasing at its params renders again
            session.full_params = None
        extra = self._settings_text(result.settings, params.quality)
        info = self._info(session, params, "preview", ms, extra)
        return (*self.view_outputs(session, view), info, gr.update(**DOWNLOAD_WAIT))

    @reported
    def click(
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
    ) -> tuple:
        """Focus on the clicked point: ``index = [x, y]`` in the shown photo's pixels.

        Returns:
            ``(focus, result, compare, legend, info)``; the focus slider moves to ``focus``,
            the position (0 = nearest, 1 = farthest) of the clicked point's disparity.
        """
        if session is None:
            gr.Warning("Upload a photo first.")
            return (gr.skip(), *SKIP4)
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
        focus = position_of(self.model.focus_at(session.scene, xs, ys))
        ms_focus = 1000 * (time.perf_counter() - t0)
        params = RenderParams.from_inputs(
            focus, f_number, blades, rotation, highlight_boost, fusion, quality, blur_on,
            size=session.size,
        )  # fmt: skip
        outputs = self._render_full(session, params, view)
        if outputs is SKIP4:
            return (focus, *SKIP4)
        info = outputs[3] + f" | focused on the click at ({xs:.0f}, {ys:.0f}) in {ms_focus:.0f} ms"
        return (focus, *outputs[:3], info)

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

    # -------------------------------------------------------------- download
    @reported
    def download(self, session: Session | None, fmt: str = "PNG") -> Any:
        """Write the latest full-resolution render to a file for the download button.

        Returns:
            a ``gr.DownloadButton`` update with the file (or ``gr.skip()`` without a render).
        """
        fmt = str(fmt).upper()
        if fmt not in FORMATS:
            raise user_error(f"Download format must be PNG or JPEG, got {fmt!r}.")
        if session is None:
            return gr.update(value=None, label="Download", interactive=False)
        session.touch()
        with session.lock:
            params = session.last_full_params
            if params is None or session.full_params != params:
                return gr.skip()  # no full render, or a preview is shown
            done = session.download_file
            image = None
            if done is None or done[:2] != (params, fmt) or not done[2].exists():
                image = session.last_full
        if done is not None and image is None:  # written already: hand out the same file
            w, h = session.size
            label = f"Download {fmt} ({w}x{h})"
            return gr.update(value=str(done[2]), label=label, interactive=True)
        if image is None:
            return gr.skip()
        # each file in its own numbered folder, written once: a file handed to Gradio is
        # never rewritten or removed while it may still be copied (see _prune)
        root = self._session_dir(session, "download")
        folder = root / self._next_name(session, "")
        folder.mkdir()
        ext = "png" if fmt == "PNG" else "jpg"
        name = f"{session.name}_bokeh_{self._file_params(params)}.{ext}"
        path = imaging.save_image(
            image, folder / name, icc_profile=session.icc_profile, exif=session.exif
        )
        _prune(root, 2)
        with session.lock:
            if session.last_full_params != params or session.full_params != params:
                return gr.skip()  # a newer render came in while this file was written
            session.download_file = (params, fmt, path)
        h, w = image.shape[:2]
        return gr.update(value=str(path), label=f"Download {fmt} ({w}x{h})", interactive=True)
