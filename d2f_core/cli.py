"""``d2f``: render bokeh from the command line.

    d2f render IN -o OUT [--focus F | --focus-at X,Y] --blur K [--depth FILE ...]
    d2f batch INPUT... -o OUTDIR [same options] [--recursive] [--engine local|ray] (d2f_core.batch)

Depth comes from ``--depth-model SOURCE`` (:mod:`d2f_core.depth.sources`: ``embedded``,
``file:PATH``, ``d2f``, ``transformers:MODEL``), else, in order: ``--depth``, the phone depth
embedded in the photo (Google Lens Blur, Apple portrait JPEG/HEIC), or the D2F defocus
network. Every map is refined to the photo's edges (``--no-refine-depth`` keeps it as the
source gave it); ``-v`` says which source was used. The focal plane comes from
``--focus``/``--focus-at``, else the focus stored by the phone, else the subject found in the
disparity map with the focal range that keeps it sharp (``D2F.default_focus``; the image
centre when nothing stands out). ``--sharp-mask`` and ``--blur-mask`` paint over the photo
what must stay sharp or be blurred, whatever the map says (``D2F.paint``).
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
from pathlib import Path
from typing import Any

from . import photo_render
from .io import SAVE_FORMATS, same_file
from .photo_render import (
    DEFAULT_MAX_PIXELS,
    Engine,
    RenderError,
    UsageError,
    check_output_name,
    error_message,
    one_line,
)

# named explicitly: under "python -m d2f_core.cli" __name__ is "__main__"
logger = logging.getLogger("d2f_core.cli")

PROG = "d2f"


# --------------------------------------------------------------------------- argument types


def _number_in(text: str, low: float, high: float) -> float:
    """``text`` as a number in ``[low, high]`` (NaN is not in it)."""
    bad = f"expected a number in [{low:g}, {high:g}], got {text!r}"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(bad) from None
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(bad)
    return value


def _unit_float(text: str) -> float:
    return _number_in(text, 0.0, 1.0)


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

    lo, hi = F_NUMBER_LIMITS
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not lo <= value <= hi:  # NaN too
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


def _boost(text: str) -> float:
    # the library's bound (rendering.radiance.MAX_BOOST: torch is imported lazily here)
    return _number_in(text, 0.0, 10.0)


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
    """Reports errors as one line, ``d2f: error: ... (see 'd2f render --help')``, for
    subcommands too (not ``d2f render: ...``, and without the usage block, which runs to a
    dozen lines for ``d2f render``)."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{PROG}: error: {message} (see '{self.prog} --help')\n")


def _focus_arguments(common: argparse.ArgumentParser) -> None:
    """The focus, blur, aperture and renderer options of ``render`` and ``batch``."""
    focus = common.add_argument_group("focus and blur")
    where = focus.add_mutually_exclusive_group()
    where.add_argument(
        "--focus", type=_unit_float, metavar="F", help="focal disparity in [0, 1] (1 = nearest)"
    )
    where.add_argument(
        "--focus-position",
        type=_unit_float,
        metavar="P",
        help="focus as the app's slider says it: 0 = nearest, 1 = farthest (focal disparity 1 - P)",
    )
    where.add_argument(
        "--focus-at",
        type=_point,
        metavar="X,Y",
        help="focus on the depth at this pixel of the (upright) input photo, with a focal "
        "range that keeps the subject there sharp, as the app's click (unless --focal-range)",
    )
    focus.add_argument(
        "--focal-range",
        type=_unit_float,
        metavar="R",
        help="a span of disparity around the focus that stays perfectly sharp, the blur "
        "growing from its edges (0 = thin lens; default: the subject's with --focus-at or with "
        "no focus given, else 0)",
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
    _renderer_arguments(focus)


def _renderer_arguments(focus: Any) -> None:
    """The renderer's own options, in the "focus and blur" group ``focus``: quality, kernel
    placement, the highlight boost, fusion."""
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
    boost = focus.add_mutually_exclusive_group()
    boost.add_argument(
        "--no-highlight-boost",
        action="store_true",
        help="no HDR boost of saturated pixels (the app's Boost at 0)",
    )
    boost.add_argument(
        "--highlight-boost",
        type=_boost,
        metavar="S",
        help="the strength of the boost of clipped highlights, 0-10 (default 1: far lights' "
        "discs as bright as a real lens makes them; the app's Boost)",
    )
    focus.add_argument(
        "--no-fusion",
        action="store_true",
        help="skip the full-resolution fusion (plain upsampling of the bokeh pass)",
    )


def _depth_arguments(common: argparse.ArgumentParser) -> None:
    """Where the depth comes from, and how a map is read."""
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
        "network, offline), scene (the scene teachers with the network's subjects, offline) "
        "or transformers:MODEL (a Hugging Face depth model id or a local "
        "folder; needs the hub extra). Default: --depth, else the phone's, else the weights' "
        "own (scene for the shipped weights)",
    )
    depth.add_argument(
        "--no-refine-depth",
        action="store_true",
        help="keep the depth map as its source gave it (default: its edges are refined to "
        "the photo's)",
    )


def _output_arguments(common: argparse.ArgumentParser) -> None:
    """The saved maps, the encoder, the weights, the limits and the messages."""
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


def build_parser() -> argparse.ArgumentParser:
    common = _Parser(add_help=False)
    _focus_arguments(common)
    _depth_arguments(common)
    _output_arguments(common)
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
    # one photo's paint: a batch has no mask per photo
    paint = render.add_argument_group("brushes (masks painted over the photo)")
    paint.add_argument(
        "--sharp-mask",
        type=Path,
        metavar="PNG",
        help="a mask of the photo's aspect ratio, white = painted: what it paints stays "
        "sharp wherever the focus is (drawn onto the focal plane); its edges follow the "
        "photo's",
    )
    paint.add_argument(
        "--blur-mask",
        type=Path,
        metavar="PNG",
        help="a mask, white = painted: what it paints is moved away from the focal plane "
        "and blurred",
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
    check_output_name(dst)
    if same_file(dst, src):
        raise UsageError(f"output {os.fspath(dst)!r} is the input photo; choose another name")
    if args.depth is not None:
        if args.depth.is_dir():
            raise UsageError("--depth must be a file for 'd2f render'")
        if same_file(dst, args.depth):
            raise UsageError(f"output {os.fspath(dst)!r} is the --depth file")
    for flag, mask in (("--sharp-mask", args.sharp_mask), ("--blur-mask", args.blur_mask)):
        if mask is not None and same_file(dst, mask):
            raise UsageError(f"output {os.fspath(dst)!r} is the {flag} file")
    photo_render.check_output_folder(dst)
    photo_render.render_file(src, dst, args, Engine(args.weights), args.depth)
    logger.info("wrote %s", dst)
    return 0


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
        args = parser.parse_args(argv)  # its checks import the renderer (torch): a second
    except SystemExit as exc:  # argparse already printed usage and the message
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    handler, old_level = _setup_logging(args.quiet, args.verbose)
    try:
        if args.command == "render":
            return _cmd_render(args)
        from .batch.command import run_batch

        return run_batch(args)
    except UsageError as exc:  # worded as the parser's own errors are
        hint = f"(see '{PROG} {args.command} --help')"
        print(f"{PROG}: error: {one_line(str(exc))} {hint}", file=sys.stderr)
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
