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
import functools
import logging
import shutil
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gradio as gr
import numpy as np

from app import imaging
from app.cache import SCENE_CACHE, SceneCache, content_key
from d2f_core.kernels import PAPER_GROWING_SIZES

log = logging.getLogger(__name__)

#: The adaptive renderer's error budgets (``D2F.render(budget=...)``), fastest last.
QUALITIES = ("high", "balanced", "fast")
VIEWS = ("Bokeh", "Before / after", "Disparity", "Defocus", "Fusion mask")
#: Display files kept per session (Gradio copies each one into its cache when it is sent).
DISPLAY_FILES_KEPT = 8
#: Long side of the live preview rendered while a slider is dragged.
PREVIEW_MAX_SIDE = 512
FORMATS = ("PNG", "JPEG")
DEPTH_KINDS = ("disparity (bright = near)", "depth (bright = far)")
#: Focus values are rounded to the focal slider's step, so that a value the app sets and
#: the value the slider sends back compare equal.
FOCUS_DECIMALS = 3

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
    """What a render depends on besides the scene; equal params give equal pictures."""

    focus: float
    blur: float
    blades: int = 0
    rotation: float = 0.0
    highlight_boost: bool = True
    fusion: bool = True
    quality: str = "balanced"

    @classmethod
    def from_inputs(
        cls,
        focus: Any,
        blur: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        quality: Any = "balanced",
    ) -> RenderParams:
        """Validate raw widget values (numbers may arrive as str/None from API callers)."""
        try:
            f = round(float(focus), FOCUS_DECIMALS)
            k = round(float(blur), 3)
            n = int(float(blades or 0))
            r = round(float(rotation or 0.0), 3)
        except (TypeError, ValueError):
            raise user_error(
                f"Invalid slider values: focus={focus!r}, blur={blur!r}, blades={blades!r}, "
                f"rotation={rotation!r}."
            ) from None
        if not 0.0 <= f <= 1.0:
            raise user_error(f"focus must be in [0, 1], got {f}.")
        if not 0.0 <= k <= 10000.0:
            raise user_error(f"blur must be in [0, 10000] px, got {k}.")
        if n < 0 or n in (1, 2):
            raise user_error(f"blades must be 0 (round) or at least 3, got {n}.")
        quality = "balanced" if quality in (None, "") else str(quality)
        if quality not in QUALITIES:
            raise user_error(f"quality must be one of {', '.join(QUALITIES)}, got {quality!r}.")
        return cls(f, k, n, r, bool(highlight_boost), bool(fusion), quality)

    def render_options(self) -> dict[str, Any]:
        """Keyword options for ``D2F.render`` (and on to ``rendering.render``)."""
        return {
            "fusion": self.fusion,
            "blades": self.blades,
            "rotation": self.rotation,
            "highlight_boost": self.highlight_boost,
            "budget": self.quality,
        }


@dataclass
class Session:
    """One user's work: the prepared scene and what was last shown.

    Attributes:
        scene: ``d2f_core.pipeline.Scene`` of the upload (shared with the scene cache).
        name: file stem of the upload, used for the download's name.
        shown_size: ``(width, height)`` of the upload as the browser shows it; clicks come
            in these coordinates.
        size: ``(width, height)`` of the scene (the upload, possibly downscaled).
        before: ``(h, w, 3)`` uint8 input at display size.
        views: uint8 pictures of the last render per view name, at display size.
        full_params: params of the latest full-resolution render requested (None: none).
        full_seq: counts full-resolution renders; a preview that overlaps one is dropped.
        last_full: ``(H, W, 3)`` uint8 of the latest full render, for the download.
        folder: this session's folder for display and download files (removed with it).
        icc_profile, exif: metadata of the upload, written into the download.
    """

    scene: Any
    name: str
    shown_size: tuple[int, int]
    size: tuple[int, int]
    before: np.ndarray
    views: dict[str, np.ndarray] = field(default_factory=dict)
    full_params: RenderParams | None = None
    full_seq: int = 0
    last_full: np.ndarray | None = None
    last_full_params: RenderParams | None = None
    folder: Path | None = None
    icc_profile: bytes | None = None
    exif: bytes | None = None
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def close(self) -> None:
        """Delete this session's download files."""
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
            self.folder = None


def delete_session(session: Session | None) -> None:
    """``gr.State`` delete callback: free the session's files when it expires."""
    if isinstance(session, Session):
        session.close()


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


def reported(fn: Callable) -> Callable:
    """Turn bad-input exceptions into ``gr.Error`` and anything else into a short one."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except gr.Error:
            raise
        except (ValueError, TypeError) as err:
            raise user_error(str(err)) from None
        except MemoryError:
            log.exception("out of memory in %s", fn.__name__)
            raise user_error("The server ran out of memory; try a smaller photo.") from None
        except Exception as err:
            log.exception("unexpected failure in %s", fn.__name__)
            raise user_error(
                f"Something went wrong ({type(err).__name__}); please retry."
            ) from None

    return wrapper


SKIP4 = (gr.skip(), gr.skip(), gr.skip(), gr.skip())


class RefocusApp:
    """The app's logic, independent of the page layout.

    Args:
        model: a ``d2f_core.pipeline.D2F`` (anything with ``prepare``, ``render``,
            ``focus_at``).
        cache: scene cache shared across sessions (default: the process-wide one).
        download_root: where per-session download folders go (default: a temp folder).
    """

    def __init__(
        self,
        model: Any,
        cache: SceneCache | None = None,
        download_root: str | Path | None = None,
    ) -> None:
        self.model = model
        self.cache = SCENE_CACHE if cache is None else cache
        if download_root is None:
            download_root = tempfile.mkdtemp(prefix="d2f-app-")
            # sessions remove their own folders; this catches those alive at exit
            atexit.register(shutil.rmtree, download_root, ignore_errors=True)
        self.download_root = Path(download_root)
        self.download_root.mkdir(parents=True, exist_ok=True)

    # ----------------------------------------------------------------- views
    def _session_dir(self, session: Session, name: str) -> Path:
        if session.folder is None:
            session.folder = self.download_root / uuid.uuid4().hex
        folder = session.folder / name
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def _display_file(self, session: Session, image: np.ndarray) -> str:
        """Write a picture for the browser as a fast PNG and return its path.

        Gradio would encode arrays itself at PNG level 6 (0.7 s for 1600x1200 here, 0.14 s
        at level 1); it copies the file into its cache, so only the newest few are kept.
        """
        folder = self._session_dir(session, "display")
        path = folder / f"{time.monotonic_ns()}_{uuid.uuid4().hex[:8]}.png"
        imaging.write_png(image, path)
        for old in sorted(folder.iterdir())[:-DISPLAY_FILES_KEPT]:
            old.unlink(missing_ok=True)
        return str(path)

    def _store_views(self, session: Session, result: Any, bokeh: np.ndarray) -> None:
        shown = imaging.fit_display(bokeh)
        size = (shown.shape[1], shown.shape[0])
        # maps come at the render pass's size; shown at the bokeh's size they line up when
        # the user switches views
        session.views = {
            "Bokeh": shown,
            "Disparity": imaging.map_to_display(result.disparity, size, "viridis"),
            "Defocus": imaging.map_to_display(result.defocus, size, "magma"),
            "Fusion mask": imaging.map_to_display(result.fusion_mask, size, "gray"),
        }

    @staticmethod
    def _legend(session: Session, view: str) -> tuple[str, str, str, str] | None:
        """The legend of ``view``; the defocus map's top end in full-resolution pixels."""
        legend = _LEGENDS.get(view)
        if legend is None or view != "Defocus":
            return legend
        # the defocus map is the paper's D of the CoC at the render pass, 1 = 69 px there;
        # the pass is smaller than the photo by the width ratio of the two
        px = round(MAX_DEFOCUS_COC * session.size[0] / session.scene.image_lr.shape[-1])
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
        picture = session.views.get(view, session.views["Bokeh"])
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
            f"{w}x{h} px | focus {params.focus:.3f} | blur {params.blur:g} px | "
            f"{kind} render {ms:.0f} ms"
        )
        return text + (f" | {extra}" if extra else "")

    # ---------------------------------------------------------------- upload
    @reported
    def load(
        self,
        image: Any,
        depth: Any,
        depth_kind: str,
        session: Session | None,
        focus: Any,
        blur: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
    ) -> tuple:
        """Decode an upload (and optional depth map), prepare it (cached), render it.

        Returns:
            ``(session, focus, result, compare, legend, info)``; ``focus`` is the focal plane
            the photo's camera used when it carries one, the subject the network found when
            the photo comes with no depth (:meth:`D2F.subject_focus`), and skipped otherwise
            (a depth map given without a focal plane keeps the slider's focus).
        """
        path = _payload_path(image)
        if path is None:  # the input was cleared
            if session is not None:
                session.close()
            cleared = (gr.update(value=None), gr.update(value=None), gr.update(visible=False))
            return (None, gr.skip(), *cleared, "")
        params = RenderParams.from_inputs(
            focus, blur, blades, rotation, highlight_boost, fusion, quality
        )
        t0 = time.perf_counter()
        photo = imaging.load_photo(path, _payload_name(image, ext=True))
        if photo.notice:
            gr.Warning(photo.notice)
        disparity, new_focus, source = None, gr.skip(), "network"
        depth_path = _payload_path(depth)
        if depth_path is not None:
            kind = "depth" if str(depth_kind).startswith("depth") else "disparity"
            disparity, (dw, dh) = imaging.load_depth_map(
                depth_path, photo.size, kind, _payload_name(depth, "depth map", ext=True)
            )
            source = f"your {kind} map"
            w, h = photo.size
            if (dw, dh) != (w, h):
                gr.Info(f"The depth map ({dw}x{dh}) was resized to the photo ({w}x{h}).")
        elif photo.disparity is not None:
            disparity = photo.disparity
            source = f"depth embedded in the photo ({photo.depth_source})"
            gr.Info(f"Using the {source}.")
            if photo.focus is not None:
                new_focus = round(float(photo.focus), FOCUS_DECIMALS)
                params = RenderParams.from_inputs(
                    new_focus, blur, blades, rotation, highlight_boost, fusion, quality
                )
        t_decode = time.perf_counter()
        key = content_key(photo.image, disparity)
        scene, cached = self.cache.get_or_prepare(
            self.model, key, lambda: self.model.prepare(photo.image, disparity=disparity)
        )
        t_prepare = time.perf_counter()
        subject = ""
        if disparity is None:
            # no depth and no focal plane from the camera: focus on the subject the network found
            focus_found, (sx, sy) = self.model.subject_focus(scene)
            new_focus = round(float(focus_found), FOCUS_DECIMALS)
            params = RenderParams.from_inputs(
                new_focus, blur, blades, rotation, highlight_boost, fusion, quality
            )
            subject = f" | focus on the subject at ({sx:.0f}, {sy:.0f})"
        if session is not None:
            session.close()
        session = Session(
            scene=scene,
            name=_payload_name(image),
            shown_size=photo.shown_size,
            size=photo.size,
            before=imaging.fit_display(imaging.to_uint8(photo.image)),
            icc_profile=photo.icc_profile,
            exif=photo.exif,
        )
        outputs = self._render_full(session, params, view)
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

    # --------------------------------------------------------------- renders
    def _render_full(self, session: Session, params: RenderParams, view: str) -> tuple:
        with session.lock:
            session.full_seq += 1
            seq = session.full_seq
            session.full_params = params
        try:
            t0 = time.perf_counter()
            result = self.model.render(
                session.scene, params.focus, params.blur, **params.render_options()
            )
            ms = 1000 * (time.perf_counter() - t0)
        except BaseException:
            with session.lock:
                if session.full_seq == seq:
                    session.full_params = None
            raise
        bokeh = imaging.to_uint8(result.bokeh)
        with session.lock:
            if session.full_seq != seq:
                return SKIP4  # a newer full render is on its way
            session.last_full = bokeh
            session.last_full_params = params
            self._store_views(session, result, bokeh)
        extra = self._settings_text(result.settings, params.quality)
        return (*self.view_outputs(session, view), self._info(session, params, "full", ms, extra))

    @reported
    def render_full(
        self,
        session: Session | None,
        focus: Any,
        blur: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
    ) -> tuple:
        """Full-resolution render (slider released, option changed).

        Returns:
            ``(result, compare, legend, info)``.
        """
        if session is None:
            return SKIP4
        params = RenderParams.from_inputs(
            focus, blur, blades, rotation, highlight_boost, fusion, quality
        )
        with session.lock:
            if params == session.full_params:
                return SKIP4  # already rendered (or being rendered) at full resolution
        return self._render_full(session, params, view)

    @reported
    def render_preview(
        self,
        session: Session | None,
        focus: Any,
        blur: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
    ) -> tuple:
        """Reduced-resolution render while a slider moves.

        Dropped (``gr.skip()``) when a full render of the same params was requested, or when
        a full render started while this preview ran: a preview must never replace the full
        result that the release of the slider asked for.

        Returns:
            ``(result, compare, legend, info)``.
        """
        if session is None:
            return SKIP4
        params = RenderParams.from_inputs(
            focus, blur, blades, rotation, highlight_boost, fusion, quality
        )
        with session.lock:
            if params == session.full_params:
                return SKIP4
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
            if session.full_seq != seq or params == session.full_params:
                return SKIP4
            self._store_views(session, result, bokeh)
        extra = self._settings_text(result.settings, params.quality)
        info = self._info(session, params, "preview", ms, extra)
        return (*self.view_outputs(session, view), info)

    @reported
    def click(
        self,
        session: Session | None,
        index: Any,
        blur: Any,
        blades: Any = 0,
        rotation: Any = 0.0,
        highlight_boost: Any = True,
        fusion: Any = True,
        view: str = "Bokeh",
        quality: Any = "balanced",
    ) -> tuple:
        """Focus on the clicked point: ``index = [x, y]`` in the shown photo's pixels.

        Returns:
            ``(focus, result, compare, legend, info)``; the focal slider moves to ``focus``.
        """
        if session is None:
            gr.Warning("Upload a photo first.")
            return (gr.skip(), *SKIP4)
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
        focus = round(float(self.model.focus_at(session.scene, xs, ys)), FOCUS_DECIMALS)
        ms_focus = 1000 * (time.perf_counter() - t0)
        params = RenderParams.from_inputs(
            focus, blur, blades, rotation, highlight_boost, fusion, quality
        )
        outputs = self._render_full(session, params, view)
        if outputs is SKIP4:
            return (focus, *SKIP4)
        info = outputs[3] + f" | focus_at ({xs:.0f}, {ys:.0f}) {ms_focus:.0f} ms"
        return (focus, *outputs[:3], info)

    @reported
    def show_view(self, session: Session | None, view: str) -> tuple:
        """Switch the result panel to ``view`` without rendering.

        Returns:
            ``(result, compare, legend)``.
        """
        if view not in VIEWS:
            raise user_error(f"Unknown view {view!r}; expected one of {', '.join(VIEWS)}.")
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
        with session.lock:
            image, params = session.last_full, session.last_full_params
        if image is None or params is None:
            return gr.skip()
        folder = self._session_dir(session, "download")
        for old in folder.iterdir():
            old.unlink(missing_ok=True)
        ext = "png" if fmt == "PNG" else "jpg"
        name = f"{session.name}_bokeh_f{params.focus:.3f}_K{params.blur:g}.{ext}"
        path = imaging.save_image(
            image, folder / name, icc_profile=session.icc_profile, exif=session.exif
        )
        h, w = image.shape[:2]
        return gr.update(value=str(path), label=f"Download {fmt} ({w}x{h})", interactive=True)
