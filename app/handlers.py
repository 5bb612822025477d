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

The handlers live by concern: uploads and depth sources in :mod:`app.loading`, the render
events (views, preview, full render, click) in :mod:`app.render_events`, downloads in
:mod:`app.downloads`, the brushes in :mod:`app.painting`, the loupe in :mod:`app.loupe`,
the per-session cache in
:mod:`app.sessions`; the page's settings are in :mod:`app.settings` and the error reporting
in :mod:`app.reporting`. :class:`RefocusApp` joins them.
"""

from __future__ import annotations

import atexit
import logging
import os
import shutil
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

from app.cache import SCENE_CACHE, SceneCache
from app.downloads import DownloadEvents
from app.loading import LoadEvents
from app.loupe import LoupeEvents
from app.painting import PaintEvents
from app.render_events import RenderEvents
from app.sessions import DEFAULT_MAX_SESSIONS, DEFAULT_SESSION_IDLE_S, Session, SessionRegistry
from app.uploads import UploadGate

# the app's events log under one name, whichever module holds them
log = logging.getLogger("app.handlers")


def _env_number(name: str, default: float) -> float:
    raw = os.environ.get(name)
    try:
        return float(raw) if raw else default
    except ValueError:
        log.warning("ignoring %s=%r (not a number)", name, raw)
        return default


class RefocusApp(
    SessionRegistry, LoadEvents, RenderEvents, PaintEvents, LoupeEvents, DownloadEvents
):
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
