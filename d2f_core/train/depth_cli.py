"""``d2f-train depth``: stage 0's command line (:func:`build_parser`, :func:`main`) over
:mod:`d2f_core.train.depth_train`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from .depth_data import JITTERS
from .depth_train import LAYOUT_TEACHER, export_checkpoint, train_depth

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    """The ``d2f-train depth`` argument parser, its options in groups."""
    p = argparse.ArgumentParser(
        prog="d2f-train depth",
        description="stage 0: train the defocus network on real photos with depth targets",
    )
    _input_options(p)
    _batch_options(p)
    _target_options(p)
    _teacher_options(p)
    _run_options(p)
    return p


def _input_options(p: argparse.ArgumentParser) -> None:
    """Stage 0's options: the photos and their targets, the device, the time budget, the
    output folder."""
    p.add_argument("--data", type=Path, default=None, help="datasets folder")
    p.add_argument("--labels", type=Path, default=None, help="teacher labels (d2f-train label)")
    p.add_argument(
        "--pack",
        type=Path,
        default=None,
        help="train on a pack of the photos and their targets (d2f-train depth-pack) instead "
        "of --data and --labels",
    )
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument(
        "--minutes",
        type=float,
        default=None,
        help="a time budget: the learning-rate schedule follows the time spent or the steps "
        "done, whichever is further along, and training ends at either",
    )
    p.add_argument("--out", type=Path, required=True)


def _batch_options(p: argparse.ArgumentParser) -> None:
    """Stage 0's options: the network, the schedule and the batches (their sizes, the pasted
    subjects, the jitter, the generated share)."""
    p.add_argument("--variant", default="lite")
    p.add_argument("--steps", type=int, default=6000)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--crop", type=int, default=256)
    p.add_argument(
        "--sides",
        type=lambda v: [int(x) for x in v.split(",")],
        default=None,
        metavar="A,B,...",
        help="multi-scale: long sides of the batches (square, 4:3 and 3:4 frames; "
        "each batch holds --batch-size crops of --crop in pixels)",
    )
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--paste", type=float, default=0.4)
    p.add_argument(
        "--jitter", choices=JITTERS, default="mild",
        help="photometric jitter of the photos: mild (exposure) or strong (also white "
        "balance, saturation, blur and noise)",
    )  # fmt: skip
    p.add_argument(
        "--frame-match", type=float, default=0.0, metavar="SHARE",
        help="share of the photo samples drawn landscape in a landscape frame and portrait in "
        "a portrait one, as the network reads whole photos",
    )  # fmt: skip
    p.add_argument("--synth", type=float, default=0.15)


def _target_options(p: argparse.ArgumentParser) -> None:
    """Stage 0's options: the targets and the loss terms on them (the layout, the ranking
    term, the scene targets, the standing scenes)."""
    p.add_argument(
        "--layout-teacher",
        type=float,
        default=LAYOUT_TEACHER,
        help="weight of the depth teacher in the layout; -1: per photo, by its agreement "
        "with the ramp (teacher_weight)",
    )
    p.add_argument("--absolute-weight", type=float, default=0.25)
    p.add_argument(
        "--rank-weight",
        type=float,
        default=0.0,
        help="weight of the pairwise ranking term (pixel pairs kept in their targets' order)",
    )
    p.add_argument(
        "--rank-edge",
        type=float,
        default=0.0,
        help="share of the ranking term's close pairs that start on a target edge",
    )
    p.add_argument(
        "--scene-weight",
        type=float,
        default=1.0,
        help="draw the photos of whole scenes (SUN, Urban100, BSDS) this many times as often",
    )
    p.add_argument(
        "--scene-targets",
        action="store_true",
        help="targets from the scene model (d2f_core.train.scene_targets) on photos whose labels "
        "hold the scene teachers' maps (d2f-train label-scene)",
    )
    p.add_argument(
        "--standing",
        type=float,
        default=0.0,
        help="share of the generated scenes drawn from d2f_core.train.synth.standing (a near post "
        "across the frame, a subject over a far floor, far lights at night)",
    )
    p.add_argument(
        "--rescan-every",
        type=int,
        default=0,
        metavar="N",
        help="look for new label files every N samples (labelling still running)",
    )


def _teacher_options(p: argparse.ArgumentParser) -> None:
    """Stage 0's options: what the network learns from besides its targets (a feature
    teacher, a network to keep, the scene head) and the weight average."""
    p.add_argument(
        "--distill",
        type=Path,
        default=None,
        metavar="ONNX",
        help="feature distillation from this teacher (the VOC teacher's ASPP features)",
    )
    p.add_argument("--distill-weight", type=float, default=0.2)
    p.add_argument(
        "--keep",
        type=Path,
        default=None,
        metavar="D2F_CHECKPOINT",
        help="hold the network to this checkpoint's relative depth where a photo's target "
        "knows nothing new (outside its subjects, their margins and the sky)",
    )
    p.add_argument("--keep-weight", type=float, default=1.0)
    p.add_argument(
        "--head-only",
        action="store_true",
        help="train the scene head alone; the rest of the network, and its disparity, stay "
        "as --init has them",
    )
    p.add_argument(
        "--scene-map-weight",
        type=float,
        default=0.5,
        help="weight of the scene head's cross-entropy (a '-scene' --variant: subjects, sky)",
    )
    p.add_argument(
        "--keep-on",
        choices=("background", "plain"),
        default="background",
        help="background: every photo outside its subjects, their margins and the sky; "
        "plain: only photos with no subject, weighted by how little sky and ground they show",
    )
    p.add_argument(
        "--ema",
        type=float,
        default=0.0,
        metavar="DECAY",
        help="also keep an exponential moving average of the weights (e.g. 0.99), saved "
        "beside every kept checkpoint as depth_<step>_ema.pt",
    )
    p.add_argument("--distill-channels", type=int, default=256)


def _run_options(p: argparse.ArgumentParser) -> None:
    """Stage 0's options: the seed, threads, logging, checkpoints, data workers, and where a
    run starts."""
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--save-every", type=int, default=100)
    p.add_argument("--keep-every", type=int, default=1000)
    p.add_argument("--workers", type=int, default=1, help="data-loading processes")
    p.add_argument("--init", type=Path, default=None, help="D2F checkpoint to start from")
    p.add_argument("--restart", action="store_true", help="ignore an existing depth_last.pt")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["export"]:
        e = argparse.ArgumentParser(
            prog="d2f-train depth export",
            description="a D2F checkpoint from a base checkpoint and stage-0 weights",
        )
        e.add_argument("depth", type=Path)
        e.add_argument("base", type=Path)
        e.add_argument("out", type=Path)
        e.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
        a = e.parse_args(argv[1:])
        try:
            print(export_checkpoint(a.depth, a.base, a.out, a.set))
        except (ValueError, FileNotFoundError, KeyError) as exc:
            print(f"d2f-train depth export: error: {exc}", file=sys.stderr)
            return 2
        return 0
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        path = train_depth(args)
    except (ValueError, FileNotFoundError) as exc:
        print(f"d2f-train depth: error: {exc}", file=sys.stderr)
        return 2
    print(f"stage 0 checkpoint: {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
