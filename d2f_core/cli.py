"""``d2f``: render bokeh from the command line.

    d2f render IN -o OUT [--focus F | --focus-at X,Y] --blur K [--depth FILE ...]
    d2f batch INPUT... -o OUTDIR [same options] [--recursive] [--engine local|ray] (d2f_core.batch)

Depth comes from ``--depth-model SOURCE`` (:mod:`d2f_core.depth.sources`: ``embedded``,
``file:PATH``, ``d2f``, ``transformers:MODEL``), else, in order: ``--depth``, the phone depth
embedded in the photo (Google Lens Blur, Apple portrait JPEG/HEIC), or the D2F defocus
network. Every map is refined to the photo's edges (``--no-refine-depth`` keeps it as the
source gave it); ``-v`` says which source was used. The focal plane comes from
``--focus``/``--focus-at``, else the focus stored by the phone, else the subject found in the
disparity map (``D2F.subject_focus``; the image centre when nothing stands out).
Without network weights, photos with a depth map still render (the physical layered
renderer with a sharp in-focus prior instead of the learned radiance and fusion networks).

Exit status: 0 success, 1 failure (unreadable input, missing weights, ...), 2 usage error.
Errors go to stderr as ``d2f: error: ...``, without a traceback.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .io import (
    SAVE_FORMATS,
    load_photo,
    same_file,
    save_depth,
    save_image,
)

# named explicitly: under "python -m d2f_core.cli" __name__ is "__main__"
logger = logging.getLogger("d2f_core.cli")

#: Photos above this many pixels are downscaled with a notice unless ``--max-pixels`` says
#: otherwise (``--max-pixels 0``: no limit). 25 MP keeps a 24 MP phone photo whole; a PNG
#: that decodes to 144 MP took minutes and several GB to render at its size.
DEFAULT_MAX_PIXELS = 25_000_000

PROG = "d2f"
DEPTH_SUFFIXES = ("", "_depth", "-depth", "_disparity", "-disparity")
DEPTH_FILE_EXTENSIONS = (".png", ".npy", ".pfm", ".tif", ".tiff", ".jpg", ".jpeg")
# The fallback renderer caps its working resolution like the pipeline's low-res pass.
_FALLBACK_MAX_SIDE = 1024
_SHARP_COC_PX = 1.0


class UsageError(Exception):
    """A problem with the command line itself (exit status 2)."""


class RenderError(Exception):
    """A photo could not be rendered (exit status 1)."""


# --------------------------------------------------------------------------- argument types


def _unit_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}")
    return value


def _non_negative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def _blur_px(text: str) -> float:
    from .rendering import MAX_BLUR

    value = _non_negative_float(text)
    if value > MAX_BLUR:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_BLUR:g} px, got {text!r}")
    return value


def _f_number(text: str) -> float:
    from .lens import F_NUMBER_LIMITS

    value = _non_negative_float(text)
    lo, hi = F_NUMBER_LIMITS
    if not lo <= value <= hi:
        raise argparse.ArgumentTypeError(f"expected an f-number in [{lo:g}, {hi:g}], got {text!r}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _point(text: str) -> tuple[float, float]:
    parts = text.replace(" ", "").split(",")
    try:
        if len(parts) != 2:
            raise ValueError
        x, y = float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y pixel coordinates, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)) or x < 0 or y < 0:
        raise argparse.ArgumentTypeError(
            f"{text!r} is outside the photo: expected pixel coordinates X,Y >= 0"
        )
    return x, y


def _blades(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value != 0 and not 3 <= value <= 32:
        raise argparse.ArgumentTypeError(f"expected 0 (round) or 3..32 blades, got {value}")
    return value


def _positive_int(text: str) -> int:
    try:
        value = float(text)  # accepts 12e6
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if not math.isfinite(value) or value < 1 or value != int(value):
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return int(value)


def _pixel_limit(text: str) -> int:
    if text.strip() == "0":
        return 0
    try:
        return _positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected a positive number of pixels or 0 (no limit), got {text!r}"
        ) from None


def _depth_source(text: str) -> Any:
    from .depth.sources import parse_source

    try:
        return parse_source(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _jpeg_quality(text: str) -> int:
    value = _positive_int(text)
    if value > 100:
        raise argparse.ArgumentTypeError(f"expected 1..100, got {text!r}")
    return value


# --------------------------------------------------------------------------- parser


class _Parser(argparse.ArgumentParser):
    """Reports errors as ``d2f: error: ...`` for subcommands too (not ``d2f render: ...``)."""

    def error(self, message: str):  # type: ignore[override]
        self.print_usage(sys.stderr)
        self.exit(2, f"{PROG}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    common = _Parser(add_help=False)
    focus = common.add_argument_group("focus and blur")
    where = focus.add_mutually_exclusive_group()
    where.add_argument(
        "--focus", type=_unit_float, metavar="F", help="focal disparity in [0, 1] (1 = nearest)"
    )
    where.add_argument(
        "--focus-at",
        type=_point,
        metavar="X,Y",
        help="focus on the depth at this pixel of the (upright) input photo",
    )
    amount = focus.add_mutually_exclusive_group(required=True)
    amount.add_argument(
        "--blur",
        type=_blur_px,
        metavar="K",
        help="blur amount: CoC diameter in px at full resolution for |d - focus| = 1",
    )
    amount.add_argument(
        "--f-number",
        type=_f_number,
        metavar="N",
        help="blur as the f-number of the app's virtual lens (50 mm on full frame, nearest "
        "point at 1 m): K follows from each photo's long side, so photos of any size get "
        "the same look",
    )
    focus.add_argument(
        "--aperture-blades",
        type=_blades,
        default=0,
        metavar="N",
        help="polygonal aperture with N blades (0 = round, default)",
    )
    focus.add_argument(
        "--rotation", type=_finite_float, default=0.0, metavar="DEG", help="aperture rotation"
    )
    focus.add_argument(
        "--quality",
        choices=("high", "balanced", "fast"),
        default="balanced",
        help="error budget of the adaptive renderer: 45, 40 or 30 dB against the exact "
        "renderer (default: balanced)",
    )
    focus.add_argument(
        "--placement",
        choices=("nearest", "paper"),  # rendering.PLACEMENTS: torch is imported lazily here
        default=None,
        help="which kernel a CoC between two of them gets: nearest (on both sides of focus) or "
        "paper (the next smaller behind the focal plane); default: the weights' own (paper "
        "for the shipped ones), nearest without weights",
    )
    focus.add_argument(
        "--no-fusion",
        action="store_true",
        help="skip the full-resolution fusion (plain upsampling of the bokeh pass)",
    )
    depth = common.add_argument_group("depth")
    depth.add_argument(
        "--depth",
        type=Path,
        metavar="FILE",
        help="depth/disparity map of the upright photo (PNG 8/16-bit, .npy, .pfm, float "
        "TIFF); for batch a folder with maps named like the photos (STEM.png, "
        "STEM_depth.npy, ...)",
    )
    depth.add_argument(
        "--depth-kind",
        choices=("disparity", "depth"),
        default="disparity",
        help="what --depth stores: disparity (default; large = near) or metric depth",
    )
    depth.add_argument(
        "--near",
        choices=("bright", "dark"),
        default=None,
        help="which end of a --depth disparity map is near (default: bright)",
    )
    depth.add_argument(
        "--zero-is-hole",
        action="store_true",
        help="zeros in a --depth disparity map mean 'unknown' (stereo ground truth); "
        "they are always holes in metric depth maps",
    )
    depth.add_argument(
        "--no-embedded-depth",
        action="store_true",
        help="ignore phone depth embedded in the photo",
    )
    depth.add_argument(
        "--depth-model",
        type=_depth_source,
        metavar="SOURCE",
        help="where depth comes from: embedded (the phone's), file:PATH, d2f (the shipped "
        "network, offline) or transformers:MODEL (a Hugging Face depth model id or a local "
        "folder; needs the hub extra). Default: --depth, else the phone's, else d2f",
    )
    depth.add_argument(
        "--no-refine-depth",
        action="store_true",
        help="keep the depth map as its source gave it (default: its edges are refined to "
        "the photo's)",
    )
    out = common.add_argument_group("output")
    out.add_argument(
        "--save-maps",
        type=Path,
        metavar="DIR",
        help="also write STEM_disparity.png (16-bit), STEM_defocus.png, STEM_fusion_mask.png, "
        "each at the photo's size",
    )
    out.add_argument(
        "--jpeg-quality", type=_jpeg_quality, default=95, metavar="Q", help="default 95"
    )
    model = common.add_argument_group("model and limits")
    model.add_argument(
        "--weights",
        type=Path,
        metavar="CKPT",
        help="D2F checkpoint (default: shipped weights or $D2F_WEIGHTS)",
    )
    model.add_argument(
        "--max-pixels",
        type=_pixel_limit,
        metavar="N",
        help=f"downscale larger photos to at most N pixels before rendering (default "
        f"{DEFAULT_MAX_PIXELS / 1e6:g} MP, with a notice; 0 renders every photo at its size)",
    )
    verbosity = common.add_argument_group("messages")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="only errors")
    verbosity.add_argument(
        "-v", "--verbose", action="count", default=0, help="more detail (-vv for debug)"
    )

    parser = _Parser(
        prog=PROG,
        description="Single-image bokeh rendering and refocusing with D2F (Defocus to Focus).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    render = sub.add_parser(
        "render",
        parents=[common],
        help="render one photo",
        description="Render bokeh for one photo.",
    )
    render.add_argument("input", type=Path, metavar="IN", help="input photo")
    render.add_argument(
        "-o", "--output", type=Path, required=True, metavar="OUT", help="output file or folder"
    )
    from .batch.command import add_batch_arguments

    batch = sub.add_parser(
        "batch",
        parents=[common],
        help="render a photo library (folder, glob or list) on local processes or Ray",
        description="Render bokeh for every photo of a folder, a glob or a list of paths, "
        "keeping their layout, with a manifest; a rerun renders only what is missing.",
    )
    add_batch_arguments(batch)
    return parser


# --------------------------------------------------------------------------- logging


class _Formatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.levelno >= logging.ERROR:
            return f"{PROG}: error: {msg}"
        if record.levelno >= logging.WARNING:
            return f"{PROG}: warning: {msg}"
        return f"{PROG}: {msg}"


def _setup_logging(quiet: bool, verbose: int) -> tuple[logging.Handler, int]:
    """Send the package's log records to stderr; returns the handler and the old level."""
    levels = (logging.WARNING, logging.INFO, logging.DEBUG)
    level = logging.ERROR if quiet else levels[min(verbose, 2)]
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter())
    handler.setLevel(level)
    pkg = logging.getLogger("d2f_core")
    old = pkg.level
    pkg.addHandler(handler)
    pkg.setLevel(level)
    return handler, old


# --------------------------------------------------------------------------- rendering


@dataclass
class Engine:
    """Loads the D2F model at most once per run; remembers why it is unavailable."""

    weights: Path | None
    _model: Any = None
    _error: str | None = None
    _tried: bool = False

    def model(self) -> Any:
        if self._tried:
            return self._model
        self._tried = True
        from .pipeline import D2F

        if self.weights is not None:
            if not self.weights.is_file():
                raise RenderError(f"--weights {os.fspath(self.weights)!r}: no such file")
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
        except ValueError as exc:  # present but unusable: worth a warning
            self._error = str(exc)
            logger.warning("D2F weights unusable (%s)", exc)
        return self._model

    @property
    def error(self) -> str | None:
        return self._error


@dataclass
class Rendered:
    bokeh: np.ndarray
    maps: dict[str, np.ndarray] = field(default_factory=dict)


@dataclass
class RenderInfo:
    """What :func:`render_file` did with one photo (the columns of the batch manifest).

    Attributes:
        output: the file written.
        size: (width, height) rendered, after any ``--max-pixels`` downscale.
        depth_source: where the disparity came from (``d2f`` for the network).
        focus: the focal disparity in [0, 1] (1 = nearest).
        focus_point: (x, y) in the input photo's pixels that gave the focus (``--focus-at``
            or the subject found), or ``None`` when the focus was a number.
        blur: K in px at the rendered size.
    """

    output: Path
    size: tuple[int, int]
    depth_source: str
    focus: float
    focus_point: tuple[float, float] | None
    blur: float


def _focus_from_map(disparity: np.ndarray, x: float, y: float) -> float:
    """Median disparity around pixel (x, y); same window as ``D2F.focus_at``."""
    h, w = disparity.shape
    r = max(2, round(max(h, w) / 200))
    xi = min(max(round(x), 0), w - 1)
    yi = min(max(round(y), 0), h - 1)
    win = disparity[max(0, yi - r) : yi + r + 1, max(0, xi - r) : xi + r + 1]
    return float(np.clip(np.median(win), 0.0, 1.0))


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


def _subject_from_map(disparity: np.ndarray) -> tuple[float, tuple[float, float]]:
    """``D2F.subject_focus`` for a bare disparity map (the centre when nothing stands out)."""
    from .pipeline import locate_subject

    step = max(1, max(disparity.shape) // 128)
    return locate_subject(
        disparity[::step, ::step], disparity.shape, lambda x, y: _focus_from_map(disparity, x, y)
    )


def render_with_depth_only(
    image: np.ndarray,
    disparity: np.ndarray,
    focus: float,
    blur: float,
    *,
    fusion: bool = True,
    **render_options: Any,
) -> Rendered:
    """Render without the learned networks: the layered renderer at up to 1024 px (long side),
    upsampled, with the in-focus prior (CoC <= 1 px keeps the sharp input) as fusion.

    Shape: image HxWx3 float32 [0, 1], disparity HxW [0, 1] -> bokeh HxWx3 [0, 1].
    """
    import torch
    import torch.nn.functional as F

    from .rendering import render
    from .rendering.schedule import coc_to_defocus
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
        bokeh_lr = render(img_lr, disp_lr, focus, blur * ratio, **render_options)  # [1,3,h,w]
        bokeh = bokeh_lr
        if lr != (h, w):
            bokeh = resize(bokeh_lr, (h, w))
        coc = blur * (disp - focus).abs()  # [1,1,H,W] px at full resolution
        mask = ((2.0 * _SHARP_COC_PX - coc) / _SHARP_COC_PX).clamp(0, 1)
        if fusion:
            bokeh = torch.lerp(bokeh, img, mask)
        else:
            mask = torch.zeros_like(mask)
        defocus = coc_to_defocus(blur * ratio * (disp_lr - focus).abs())
    return Rendered(
        bokeh=bokeh[0].permute(1, 2, 0).clamp(0, 1).numpy(),
        maps={
            "disparity": disparity.astype(np.float32),
            "defocus": defocus[0, 0].numpy(),
            "fusion_mask": mask[0, 0].numpy(),
        },
    )


def find_depth_file(folder: Path, stem: str) -> Path | None:
    for suffix in DEPTH_SUFFIXES:
        for ext in DEPTH_FILE_EXTENSIONS:
            candidate = folder / f"{stem}{suffix}{ext}"
            if candidate.is_file():
                return candidate
    return None


def _blur_of(args: argparse.Namespace, size: tuple[int, int]) -> float:
    """K in px: ``--blur``, or ``--f-number`` on a photo of this (height, width)."""
    if getattr(args, "f_number", None) is None:
        return args.blur
    from .lens import blur_px

    return blur_px(args.f_number, max(size))


def _choose_depth(src: Path, photo: Any, args: argparse.Namespace, depth_file: Path | None) -> Any:
    """The photo's :class:`~d2f_core.depth.sources.DepthMap` from the source the command line
    names (``--depth-model``, else ``--depth``, else the phone's depth), or ``None`` for the
    D2F network; logs the source (``-v``)."""
    from .depth.sources import DepthSource, depth_map

    source = args.depth_model
    if source is None:
        if depth_file is not None:
            source = DepthSource("file", str(depth_file))
        elif photo.disparity is not None:
            source = DepthSource("embedded")
        else:
            source = DepthSource("d2f")
    elif source.kind == "file" and depth_file is not None:
        raise UsageError("give the map once: --depth FILE or --depth-model file:PATH")
    elif source.kind == "embedded" and args.no_embedded_depth:
        raise UsageError("--depth-model embedded and --no-embedded-depth contradict each other")
    if source.kind == "d2f":
        logger.info("%s: depth from d2f (the shipped network)", src)
        return None
    depth = depth_map(
        source,
        photo.image,
        photo=photo,
        file_kind=args.depth_kind,
        near=args.near,
        zero_is_hole=True if args.zero_is_hole else None,
    )
    logger.info("%s: depth from %s", src, depth.describe())
    return depth


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
    blur = _blur_of(args, (h, w))
    focus = args.focus
    depth = _choose_depth(src, photo, args, depth_file)
    if depth is not None and depth.focus is not None:
        if focus is None and args.focus_at is None:
            focus = float(depth.focus)
            logger.info("%s: focus %.3f from the photo's metadata", src, focus)
    disparity = None if depth is None else depth.disparity

    point = None
    if focus is None:
        oh, ow = photo.info.original_size
        if args.focus_at is not None:
            x, y = args.focus_at
            if x > ow - 1 or y > oh - 1:
                raise ValueError(f"--focus-at {x:g},{y:g} is outside the {ow}x{oh} photo {src}")
            # into the loaded (possibly downscaled) frame, pixel area onto pixel area
            point = ((x + 0.5) * w / ow - 0.5, (y + 0.5) * h / oh - 0.5)
        else:
            point = "subject"

    options: dict[str, Any] = {"blades": args.aperture_blades, "rotation": args.rotation}
    if args.placement is not None:
        options["placement"] = args.placement
    model = engine.model()
    if model is not None:
        scene = model.prepare(image, depth=depth, refine=not args.no_refine_depth)
        if point == "subject":
            focus, (sx, sy) = model.subject_focus(scene)
            _say_subject(args, src, photo, (sx, sy), focus)
            point = (sx, sy)
        elif point is not None:
            focus = model.focus_at(scene, *point)
        result = model.render(
            scene,
            focus=focus,
            blur=blur,
            fusion=not args.no_fusion,
            budget=args.quality,
            **options,
        )
        if result.settings is not None:
            logger.info("%s: %s", src, result.settings.describe())
        rendered = Rendered(
            bokeh=result.bokeh,
            maps={
                "disparity": scene.disparity_full(),
                "defocus": result.defocus,
                "fusion_mask": result.fusion_mask,
            },
        )
    elif disparity is not None:
        if point == "subject":
            focus, (sx, sy) = _subject_from_map(disparity)
            _say_subject(args, src, photo, (sx, sy), focus)
            point = (sx, sy)
        elif point is not None:
            focus = _focus_from_map(disparity, *point)
        logger.info("%s: rendering with the depth map only (no D2F weights)", src)
        rendered = render_with_depth_only(
            image,
            disparity,
            focus,
            blur,
            fusion=not args.no_fusion,
            quality=args.quality,  # the renderer preset of the same name
            **options,
        )
    else:
        raise RenderError(
            f"{src}: no depth map: the photo has no embedded phone depth and no --depth was "
            f"given, and the D2F network weights are unavailable ({engine.error}); pass "
            "--depth FILE, --depth-model transformers:MODEL or --weights CKPT"
        )
    logger.info("%s: focus %.3f, blur %g px", src, focus, blur)

    protect = [src] + ([depth_file] if depth_file is not None else [])
    if args.depth_model is not None and args.depth_model.kind == "file":
        protect.append(Path(args.depth_model.arg))
    # checked before writing; every map at the photo's size (the defocus map comes at the
    # low-resolution pass's)
    size = rendered.bokeh.shape[:2]
    maps = _map_targets(args.save_maps, dst, rendered.maps, protect, size)
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
    if point is not None:  # back into the input photo's pixels
        oh, ow = photo.info.original_size
        point = (round(point[0] * ow / w, 1), round(point[1] * oh / h, 1))
    source = "d2f" if depth is None else depth.describe()
    return RenderInfo(dst, (w, h), source, float(focus), point, float(blur))


def _map_targets(
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
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise RenderError(
            f"--save-maps {os.fspath(folder)}: cannot write there ({reason})"
        ) from exc
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


def _check_output_name(path: Path) -> None:
    if path.suffix.lower() not in SAVE_FORMATS:
        known = " ".join(sorted(SAVE_FORMATS))
        raise UsageError(f"output {os.fspath(path)!r}: unknown image extension (use {known})")


def _cmd_render(args: argparse.Namespace) -> int:
    src: Path = args.input
    if not src.exists():
        raise RenderError(f"{os.fspath(src)}: no such file")
    if src.is_dir():
        raise UsageError(f"{os.fspath(src)} is a folder; use 'd2f batch' for folders")
    dst: Path = args.output
    if dst.is_dir():
        ext = src.suffix.lower() if src.suffix.lower() in SAVE_FORMATS else ".jpg"
        dst = dst / f"{src.stem}_bokeh{ext}"
    _check_output_name(dst)
    if same_file(dst, src):
        raise UsageError(f"output {os.fspath(dst)!r} is the input photo; choose another name")
    if args.depth is not None:
        if args.depth.is_dir():
            raise UsageError("--depth must be a file for 'd2f render'")
        if same_file(dst, args.depth):
            raise UsageError(f"output {os.fspath(dst)!r} is the --depth file")
    if not dst.parent.exists():
        raise RenderError(f"output folder {os.fspath(dst.parent)!r} does not exist")
    render_file(src, dst, args, Engine(args.weights), args.depth)
    logger.info("wrote %s", dst)
    return 0


_EXPECTED_ERRORS = (RenderError, ValueError, OSError, RuntimeError)


def error_message(exc: BaseException) -> str:
    """One line naming what went wrong (``unexpected ...`` for a defect of d2f)."""
    text = str(exc) or type(exc).__name__
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        text = f"{exc.filename}: {exc.strerror}"
    if not isinstance(exc, _EXPECTED_ERRORS):  # a defect of d2f, not of the input
        text = f"unexpected {type(exc).__name__}: {text} (please report it)"
    return text


def _join_negative_points(argv: list[str]) -> list[str]:
    """``--focus-at -1,-1`` as ``--focus-at=-1,-1``: argparse takes a value that starts with
    ``-`` (other than a plain negative number) for an option, and said "expected one
    argument"; joined, the value reaches the option's own check and its message."""
    out: list[str] = []
    tokens = iter(argv)
    for token in tokens:
        if token == "--focus-at":
            value = next(tokens, None)
            if value is not None and value.startswith("-") and value[1:2] in tuple("0123456789.,"):
                out.append(f"{token}={value}")
                continue
            out.append(token)
            if value is not None:
                out.append(value)
            continue
        out.append(token)
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``d2f`` command. Returns the exit status."""
    parser = build_parser()
    argv = _join_negative_points(list(sys.argv[1:] if argv is None else argv))
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed usage and the message
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    handler, old_level = _setup_logging(args.quiet, args.verbose)
    try:
        if args.command == "render":
            return _cmd_render(args)
        from .batch.command import run_batch

        return run_batch(args)
    except UsageError as exc:
        parser.print_usage(sys.stderr)
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # expected ones name the problem; any other, one line too
        print(f"{PROG}: error: {error_message(exc)}", file=sys.stderr)
        logger.debug("traceback", exc_info=True)
        return 1
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    finally:
        logging.getLogger("d2f_core").removeHandler(handler)
        logging.getLogger("d2f_core").setLevel(old_level)


if __name__ == "__main__":
    sys.exit(main())
