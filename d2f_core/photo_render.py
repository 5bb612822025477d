"""Render one photo file to one output file: what ``d2f render`` does, and ``d2f batch`` does
for each photo of a library (:mod:`d2f_core.batch`), with the same options.

It picks the depth (:func:`render_file`: a ``--depth`` file, the photo's phone depth, the
shipped network or a hub model), the focus (a value, a point, or the subject the map shows,
said on the terminal), the blur (px or the f-number of :mod:`d2f_core.lens`) and the focal
range, renders with :class:`~d2f_core.pipeline.D2F` (or the renderer alone with a depth map
and no weights) and writes the picture and the maps asked for.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .depth.subject import focus_in_map, range_in_map, subject_in_map
from .io import SAVE_FORMATS, load_photo, same_file, save_depth, save_image
from .io.save import check_side_limit

__all__ = [
    "DEFAULT_MAX_PIXELS",
    "Engine",
    "RenderError",
    "RenderInfo",
    "Rendered",
    "UsageError",
    "check_output_name",
    "error_message",
    "find_depth_file",
    "map_targets",
    "render_file",
    "render_with_depth_only",
]

# the CLI's own logger: these are the CLI's messages, and -v/-q set its level
logger = logging.getLogger("d2f_core.cli")

#: Photos above this many pixels are downscaled with a notice unless ``--max-pixels`` says
#: otherwise (``--max-pixels 0``: no limit). 25 MP keeps a 24 MP phone photo whole; a PNG
#: that decodes to 144 MP took minutes and several GB to render at its size.
DEFAULT_MAX_PIXELS = 25_000_000

DEPTH_SUFFIXES = ("", "_depth", "-depth", "_disparity", "-disparity")
DEPTH_FILE_EXTENSIONS = (".png", ".npy", ".pfm", ".tif", ".tiff", ".jpg", ".jpeg")
# The fallback renderer caps its working resolution like the pipeline's low-res pass.
_FALLBACK_MAX_SIDE = 1024
_SHARP_COC_PX = 1.0


class UsageError(Exception):
    """A problem with the command line itself (exit status 2)."""


class RenderError(Exception):
    """A photo could not be rendered (exit status 1)."""


@dataclass
class Engine:
    """Loads the D2F model at most once per run; remembers why it is unavailable."""

    weights: Path | None
    _model: Any = None
    _error: str | None = None
    _tried: bool = False
    _unusable: bool = False

    def model(self) -> Any:
        if self._tried:
            return self._model
        self._tried = True
        from .pipeline import D2F

        if self.weights is not None:
            if not self.weights.is_file():
                what = "is a folder" if self.weights.is_dir() else "no such file"
                raise RenderError(f"--weights {os.fspath(self.weights)!r}: {what}")
            try:
                self._model = D2F.from_checkpoint(self.weights)
            except (ValueError, FileNotFoundError) as exc:
                raise RenderError(f"--weights: {exc}") from exc
            return self._model
        try:
            self._model = D2F.from_pretrained()
        except FileNotFoundError as exc:
            self._error = str(exc)
            logger.info("D2F weights unavailable (%s)", exc)
        except ValueError as exc:  # present but unusable: a warning where a render goes on
            self._error = str(exc)
            self._unusable = True
        return self._model

    def say_unusable(self) -> None:
        """Warn, once, that the default weights are there but cannot be used, where a render
        goes on without them (where it cannot, its error says why, in one line)."""
        if self._unusable:
            self._unusable = False
            logger.warning("D2F weights unusable (%s)", self._error)

    @property
    def error(self) -> str | None:
        return self._error


@dataclass
class Rendered:
    bokeh: np.ndarray
    maps: dict[str, np.ndarray] = field(default_factory=dict)
    #: where the render's map came from, as :meth:`DepthMap.describe` says it
    source: str = ""


@dataclass
class RenderInfo:
    """What :func:`render_file` did with one photo (the columns of the batch manifest).

    Attributes:
        output: the file written.
        size: (width, height) rendered, after any ``--max-pixels`` downscale.
        depth_source: where the disparity came from, as a log line says it (``"scene
            (scene teachers' map (parse, ...))"``, ``"file:PATH (disparity map)"``).
        focus: the focal disparity in [0, 1] (1 = nearest).
        focus_point: (x, y) in the input photo's pixels that gave the focus (``--focus-at``
            or the subject found), or ``None`` when the focus was a number.
        blur: K in px at the rendered size.
        focal_range: the span of disparity kept sharp around the focus (0 = thin lens).
    """

    output: Path
    size: tuple[int, int]
    depth_source: str
    focus: float
    focus_point: tuple[float, float] | None
    blur: float
    focal_range: float = 0.0


def _say_subject(
    args: argparse.Namespace, src: Path, photo: Any, point: tuple[float, float], focus: float
) -> None:
    """Print where the automatic focus landed, in the photo's own pixels (unless ``-q``): a
    user who gave no focus must be able to tell whether it found the right subject."""
    if args.quiet or getattr(args, "command", "render") != "render":
        return  # d2f batch records the point in its manifest
    h, w = photo.image.shape[:2]
    oh, ow = photo.info.original_size
    x, y = point[0] * ow / w, point[1] * oh / h
    print(
        f"{src}: focused on the subject at ({x:.0f}, {y:.0f}), focal disparity {focus:.3f} "
        f"(--focus-at X,Y or --focus D to choose)"
    )


def render_with_depth_only(
    image: np.ndarray,
    disparity: np.ndarray,
    focus: float,
    blur: float,
    *,
    fusion: bool = True,
    focal_range: float = 0.0,
    **render_options: Any,
) -> Rendered:
    """Render without the learned networks: the layered renderer at up to 1024 px (long side),
    upsampled, with the in-focus prior (CoC <= 1 px keeps the sharp input) as fusion.

    Shape: image HxWx3 float32 [0, 1], disparity HxW [0, 1] -> bokeh HxWx3 [0, 1].
    """
    import torch
    import torch.nn.functional as F

    from .rendering import render
    from .rendering.schedule import coc_to_defocus, fold_focal_range, outside_range
    from .sizing import resize

    h, w = image.shape[:2]
    scale = min(1.0, _FALLBACK_MAX_SIDE / max(h, w))
    lr = (max(1, round(h * scale)), max(1, round(w * scale)))
    img = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    disp = torch.from_numpy(np.ascontiguousarray(disparity, dtype=np.float32))[None, None]
    with torch.no_grad():
        if lr != (h, w):
            img_lr = F.interpolate(img, lr, mode="bilinear", antialias=True, align_corners=False)
            disp_lr = F.interpolate(disp, lr, mode="bilinear", antialias=True, align_corners=False)
            img_lr, disp_lr = img_lr.clamp(0, 1), disp_lr.clamp(0, 1)
        else:
            img_lr, disp_lr = img, disp
        ratio = 0.5 * (lr[0] / h + lr[1] / w)
        bokeh_lr = render(
            img_lr, disp_lr, focus, blur * ratio, focal_range=focal_range, **render_options
        )  # [1,3,h,w]
        bokeh = bokeh_lr
        if lr != (h, w):
            bokeh = resize(bokeh_lr, (h, w))
        coc = blur * outside_range((disp - focus).abs(), focal_range)  # [1,1,H,W] full-res px
        mask = ((2.0 * _SHARP_COC_PX - coc) / _SHARP_COC_PX).clamp(0, 1)
        if fusion:
            bokeh = torch.lerp(bokeh, img, mask)
        else:
            mask = torch.zeros_like(mask)
        folded = fold_focal_range(disp_lr, focus, focal_range)
        defocus = coc_to_defocus(blur * ratio * (folded - focus).abs())
    return Rendered(
        bokeh=bokeh[0].permute(1, 2, 0).clamp(0, 1).numpy(),
        maps={
            "disparity": disparity.astype(np.float32),
            "defocus": defocus[0, 0].numpy(),
            "fusion_mask": mask[0, 0].numpy(),
        },
    )


def find_depth_file(folder: Path, stem: str) -> Path | None:
    """The photo ``stem``'s depth map in ``folder`` (``STEM[SUFFIX].EXT``), or ``None``. A
    FIFO, a device or a socket of that name is returned too, so that loading it says what it
    is: the photo never falls back to the network's map without a word."""
    for suffix in DEPTH_SUFFIXES:
        for ext in DEPTH_FILE_EXTENSIONS:
            candidate = folder / f"{stem}{suffix}{ext}"
            if candidate.is_file() or (candidate.exists() and not candidate.is_dir()):
                return candidate
    return None


def _blur_of(args: argparse.Namespace, size: tuple[int, int]) -> float:
    """K in px: ``--blur``, or ``--f-number`` on a photo of this (height, width)."""
    if getattr(args, "f_number", None) is None:
        return args.blur
    from .lens import blur_px

    return blur_px(args.f_number, max(size))


def _choose_depth(
    src: Path, photo: Any, args: argparse.Namespace, depth_file: Path | None, engine: Engine
) -> Any:
    """The photo's :class:`~d2f_core.depth.sources.DepthMap` from the source the command line
    names (``--depth-model``, else ``--depth``, else the phone's depth), or ``None`` for the
    weights' own source (the D2F network's, or the scene teachers'); logs the source
    (``-v``). The ``scene`` source runs with the weights' network (its subjects)."""
    from .depth.sources import DepthSource, depth_map

    source = args.depth_model
    if source is None:
        if depth_file is not None:
            source = DepthSource("file", str(depth_file))
        elif photo.disparity is not None:
            source = DepthSource("embedded")
        else:
            return None  # the weights' own source (D2F.prepare's default), logged there
    elif source.kind == "file" and depth_file is not None:
        raise UsageError("give the map once: --depth FILE or --depth-model file:PATH")
    elif depth_file is not None:
        raise UsageError(
            f"--depth FILE and --depth-model {source.name} name two depth sources: give one"
        )
    elif source.kind == "embedded" and args.no_embedded_depth:
        raise UsageError("--depth-model embedded and --no-embedded-depth contradict each other")
    if source.kind == "d2f":  # the network's own map, made by D2F.prepare at its pass
        return None
    model = engine.model() if source.kind == "scene" else None
    if source.kind == "scene" and model is None:
        raise RenderError(
            f"{src}: --depth-model scene needs the D2F weights, which are unavailable "
            f"({engine.error})"
        )
    depth = depth_map(
        source,
        photo.image,
        photo=photo,
        model=model,
        file_kind=args.depth_kind,
        near=args.near,
        zero_is_hole=True if args.zero_is_hole else None,
    )
    logger.info("%s: depth from %s", src, depth.describe())
    return depth


def _load_masks(args: argparse.Namespace, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """``--sharp-mask`` and ``--blur-mask`` read (each checked against the photo's aspect
    ratio before it is decoded), as :meth:`D2F.paint`'s keywords; empty without them."""
    from .io.masks import load_mask

    masks = {}
    for key, flag in (("sharp", "sharp_mask"), ("blur", "blur_mask")):
        path = getattr(args, flag, None)
        if path is not None:
            masks[key] = load_mask(path, size=size)
    return masks


def _painted_map(
    image: np.ndarray, disparity: np.ndarray, focus: float, masks: dict[str, np.ndarray]
) -> np.ndarray:
    """A bare map edited by the brushes for a render at ``focus`` (no weights: the map
    itself, as :meth:`D2F.render` edits a scene's)."""
    import torch

    from .depth.brushes import Brushes

    img = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    brushes = Brushes.painted(img, masks.get("sharp"), masks.get("blur"))
    if brushes is None:
        return disparity
    disp = torch.from_numpy(np.ascontiguousarray(disparity, dtype=np.float32))[None, None]
    with torch.no_grad():
        return brushes.apply(disp, focus)[0, 0].numpy()


def render_file(
    src: Path,
    dst: Path,
    args: argparse.Namespace,
    engine: Engine,
    depth_file: Path | None,
) -> RenderInfo:
    """Render one photo to ``dst``; raises ``ValueError``/``RenderError`` on failure."""
    cap = DEFAULT_MAX_PIXELS if args.max_pixels is None else (args.max_pixels or None)
    photo = load_photo(src, max_pixels=cap, use_embedded=not args.no_embedded_depth)
    image = photo.image
    h, w = image.shape[:2]
    if photo.info.resized and args.max_pixels is None:
        oh, ow = photo.info.original_size
        logger.warning(
            "%s is %dx%d (%.1f MP): rendered at %dx%d to stay within %g MP "
            "(--max-pixels 0 renders it at its size)",
            src, ow, oh, ow * oh / 1e6, w, h, DEFAULT_MAX_PIXELS / 1e6,
        )  # fmt: skip
    check_side_limit(dst, (h, w))  # before the render, not after it
    blur = _blur_of(args, (h, w))
    focal_range = getattr(args, "focal_range", None)
    masks = _load_masks(args, (h, w))
    depth = _choose_depth(src, photo, args, depth_file, engine)
    focus, point = _focus_asked(src, args, photo, depth, (h, w))
    disparity = None if depth is None else depth.disparity
    options = _render_options(args)
    model = engine.model()
    if model is not None:
        rendered, focus, focal_range, point = _render_with_model(
            model, src, args, photo, depth, masks, (focus, point, focal_range), blur, options
        )
    elif disparity is not None:
        engine.say_unusable()
        rendered, focus, focal_range, point = _render_with_map(
            src, args, photo, disparity, masks, (focus, point, focal_range), blur, options
        )
    else:
        raise RenderError(
            f"{src}: no depth map: the photo has no embedded phone depth and no --depth was "
            f"given, and the D2F network weights are unavailable ({engine.error}); pass "
            "--depth FILE, --depth-model transformers:MODEL or --weights CKPT"
        )
    logger.info("%s: focus %.3f, blur %g px, focal range %g", src, focus, blur, focal_range)
    _save_outputs(dst, args, photo, rendered, [src] if depth_file is None else [src, depth_file])
    if point is not None:  # back into the input photo's pixels
        oh, ow = photo.info.original_size
        point = (round(point[0] * ow / w, 1), round(point[1] * oh / h, 1))
    source = rendered.source if depth is None else depth.describe()
    return RenderInfo(dst, (w, h), source, float(focus), point, float(blur), float(focal_range))


def _focus_asked(
    src: Path, args: argparse.Namespace, photo: Any, depth: Any, size: tuple[int, int]
) -> tuple[float | None, Any]:
    """``(focus, point)`` as asked: the focal disparity when given (``--focus``,
    ``--focus-position``, or the photo's recorded focal plane), else the point to focus at
    in the loaded frame (``--focus-at``) or ``"subject"`` (the automatic focus)."""
    h, w = size
    focus = args.focus
    if getattr(args, "focus_position", None) is not None:
        from .lens import focus_of_position

        focus = focus_of_position(args.focus_position)
    if depth is not None and depth.focus is not None:
        if focus is None and args.focus_at is None:
            focus = float(depth.focus)
            logger.info("%s: focus %.3f from the photo's metadata", src, focus)
    if focus is not None:
        return focus, None
    if args.focus_at is None:
        return None, "subject"
    oh, ow = photo.info.original_size
    x, y = args.focus_at
    if x > ow - 1 or y > oh - 1:
        raise ValueError(f"--focus-at {x:g},{y:g} is outside the {ow}x{oh} photo {src}")
    # into the loaded (possibly downscaled) frame, pixel area onto pixel area
    return None, ((x + 0.5) * w / ow - 0.5, (y + 0.5) * h / oh - 0.5)


def _render_options(args: argparse.Namespace) -> dict[str, Any]:
    """The renderer's options the command line sets: the aperture's blades and rotation,
    the highlight boost, the placement."""
    options: dict[str, Any] = {"blades": args.aperture_blades, "rotation": args.rotation}
    if getattr(args, "no_highlight_boost", False):
        options["highlight_boost"] = False
    elif getattr(args, "highlight_boost", None) is not None:
        options["highlight_boost"] = args.highlight_boost
    if args.placement is not None:
        options["placement"] = args.placement
    return options


def _render_with_model(
    model: Any,
    src: Path,
    args: argparse.Namespace,
    photo: Any,
    depth: Any,
    masks: dict[str, Any],
    asked: tuple[float | None, Any, float | None],
    blur: float,
    options: dict[str, Any],
) -> tuple[Rendered, float, float, Any]:
    """``(rendered, focus, focal_range, point)`` with the D2F weights: the scene prepared
    from ``depth`` (or the weights' own source), painted, focused as ``asked`` (``(focus,
    point, focal_range)``: a point gets its subject's range unless one is given), rendered."""
    focus, point, focal_range = asked
    asked_d2f = args.depth_model is not None and args.depth_model.kind == "d2f"
    own = "d2f" if asked_d2f else None  # else the weights' own source (scene or d2f)
    scene = model.prepare(
        photo.image, depth=own if depth is None else depth, refine=not args.no_refine_depth
    )
    if depth is None:
        why = "asked" if asked_d2f else "the weights' own source"
        logger.info("%s: depth from %s (%s)", src, scene.disparity_source, why)
    if masks:
        scene = model.paint(scene, **masks)
    if point == "subject":  # the library's default focus, the app's too
        focus, auto_range, point, _ = model.default_focus(scene)
        focal_range = auto_range if focal_range is None else focal_range
        if point is not None:
            _say_subject(args, src, photo, point, focus)
    elif point is not None and focal_range is None:
        focus, focal_range = model.focus_at(scene, *point, with_range=True)
    elif point is not None:
        focus = model.focus_at(scene, *point)
    focal_range = focal_range or 0.0
    result = model.render(
        scene,
        focus=focus,
        blur=blur,
        fusion=not args.no_fusion,
        budget=args.quality,
        focal_range=focal_range,
        **options,
    )
    if result.settings is not None:
        logger.info("%s: %s", src, result.settings.describe())
    maps = {
        "disparity": scene.disparity_full(),
        "defocus": result.defocus,
        "fusion_mask": result.fusion_mask,
    }
    source = f"{scene.disparity_source} ({scene.disparity_output})"
    rendered = Rendered(bokeh=result.bokeh, maps=maps, source=source)
    return rendered, focus, focal_range, point


def _render_with_map(
    src: Path,
    args: argparse.Namespace,
    photo: Any,
    disparity: np.ndarray,
    masks: dict[str, Any],
    asked: tuple[float | None, Any, float | None],
    blur: float,
    options: dict[str, Any],
) -> tuple[Rendered, float, float, Any]:
    """:func:`_render_with_model` without weights: the depth map alone, focused by the same
    rules on the bare map (:func:`subject_in_map`, :func:`focus_in_map`)."""
    focus, point, focal_range = asked
    if point == "subject":  # D2F.default_focus on the bare map: the subject's range too
        focus, point = subject_in_map(disparity)
        _say_subject(args, src, photo, point, focus)
        if focal_range is None:
            focal_range = range_in_map(disparity, *point, focus)
    elif point is not None:
        focus = focus_in_map(disparity, *point)
        if focal_range is None:
            focal_range = range_in_map(disparity, *point, focus)
    focal_range = focal_range or 0.0
    if masks:
        disparity = _painted_map(photo.image, disparity, focus, masks)
    logger.info("%s: rendering with the depth map only (no D2F weights)", src)
    rendered = render_with_depth_only(
        photo.image,
        disparity,
        focus,
        blur,
        fusion=not args.no_fusion,
        focal_range=focal_range,
        quality=args.quality,  # the renderer preset of the same name
        **options,
    )
    return rendered, focus, focal_range, point


def _save_outputs(
    dst: Path, args: argparse.Namespace, photo: Any, rendered: Rendered, protect: list[Path]
) -> None:
    """Write the render to ``dst`` with the photo's colour profile and EXIF, and the maps
    ``--save-maps`` asks for; no output may replace an input (``protect``: the photo and the
    depth map, with the masks and a ``file:`` depth source added here)."""
    protect += [getattr(args, f) for f in ("sharp_mask", "blur_mask") if getattr(args, f, None)]
    if args.depth_model is not None and args.depth_model.kind == "file":
        protect.append(Path(args.depth_model.arg))
    # checked before writing; every map at the photo's size (the defocus map comes at the
    # low-resolution pass's)
    size = rendered.bokeh.shape[:2]
    maps = map_targets(args.save_maps, dst, rendered.maps, protect, size)
    save_image(
        dst,
        rendered.bokeh,
        quality=args.jpeg_quality,
        icc_profile=photo.info.icc_profile,
        exif=photo.info.exif,
        protect=protect,
    )
    for target, arr in maps:
        try:
            save_depth(target, np.clip(arr, 0.0, 1.0))
        except (OSError, ValueError) as exc:
            raise RenderError(f"{dst} was written, but not its map {target}: {exc}") from exc


def map_targets(
    folder: Path | None,
    dst: Path,
    maps: dict[str, np.ndarray],
    protect: list[Path],
    size: tuple[int, int] | None = None,
) -> list[tuple[Path, np.ndarray]]:
    """The ``--save-maps`` files of ``dst`` and their maps resized to ``size`` ``(H, W)``
    (bilinear; the values keep their meaning), after checking that the folder can be made
    and written and that no map would replace an input: a failure stops the render before
    anything is written."""
    if folder is None:
        return []
    if folder.exists() and not folder.is_dir():
        raise RenderError(f"--save-maps {os.fspath(folder)}: a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise RenderError(
            f"--save-maps {os.fspath(folder)}: cannot write there ({_reason(exc)})"
        ) from exc
    reason = _unwritable(folder)
    if reason:
        raise RenderError(f"--save-maps {os.fspath(folder)}: cannot write there ({reason})")
    out = []
    for name, arr in maps.items():
        target = folder / f"{dst.stem}_{name}.png"
        if any(same_file(target, p) for p in protect):
            raise ValueError(f"--save-maps: {target} would overwrite an input file")
        out.append((target, arr if size is None else _map_at_size(arr, size)))
    return out


def _map_at_size(arr: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(h, w)`` map -> ``(H, W)`` float32, bilinear (unchanged when already that size)."""
    from PIL import Image

    arr = np.asarray(arr, dtype=np.float32)
    if arr.shape[:2] == tuple(size):
        return arr
    resized = Image.fromarray(np.ascontiguousarray(arr)).resize(
        (size[1], size[0]), Image.Resampling.BILINEAR
    )
    return np.asarray(resized, dtype=np.float32)


# --------------------------------------------------------------------------- commands


def check_output_folder(path: Path) -> None:
    """Refuse, before a render, an output ``path`` whose folder is missing, is no folder, or
    cannot be written in (permissions, a read-only disk): found after the render, the render
    would be lost."""
    folder = path.parent
    if not folder.exists():
        raise RenderError(f"output folder {os.fspath(folder)!r} does not exist")
    if not folder.is_dir():
        raise RenderError(f"output {os.fspath(path)!r}: {os.fspath(folder)!r} is not a folder")
    reason = _unwritable(folder)
    if reason:
        raise RenderError(
            f"output {os.fspath(path)!r}: cannot write in {os.fspath(folder)!r} ({reason})"
        )


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def _unwritable(folder: Path) -> str:
    """Why no file can be made in ``folder`` ("" when one can): a temporary file is made
    and removed there."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            return ""
    except OSError as exc:
        return _reason(exc)


def check_output_name(path: Path) -> None:
    if path.suffix.lower() not in SAVE_FORMATS:
        known = " ".join(sorted(SAVE_FORMATS))
        raise UsageError(f"output {os.fspath(path)!r}: unknown image extension; use one of {known}")


_EXPECTED_ERRORS = (RenderError, ValueError, OSError, RuntimeError)


def error_message(exc: BaseException) -> str:
    """One line naming what went wrong (``unexpected ...`` for a defect of d2f)."""
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        text = f"{exc.filename}: {exc.strerror}"
    if not isinstance(exc, _EXPECTED_ERRORS):  # a defect of d2f, not of the input
        text = f"unexpected {type(exc).__name__}: {text} (please report it)"
    return one_line(text)


def one_line(text: str) -> str:
    """``text`` with its line breaks written as ``\\n``: a line break in a file's name (or a
    library's message) would begin a second line of an error."""
    return text.replace("\r", "\\r").replace("\n", "\\n")
