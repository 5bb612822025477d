"""Stage 0: the defocus network learns depth from real photos before any bokeh loss.

``d2f-train depth`` trains :class:`~d2f_core.networks.DefocusNet` with direct supervision:

- **Real photos with a subject** (human-drawn masks, or the VOC teacher's foreground where a
  photo has no mask). The target is a layout plus the subject in front of it: the layout is
  a "bottom of the frame is near" ramp blended with the indoor depth teacher's ranked
  disparity (``layout_teacher`` of it); every connected part of the subject stands on that
  layout where its lowest row touches it (a person standing on a floor has the floor's
  disparity at their feet), and is lifted to at least what surrounds it. The mask is
  feathered by a pixel so hair and fur edges stay soft.
- **Pasted subjects**: a subject cut out of another masked photo with its feathered alpha is
  placed over the photo, in front of everything it covers. Its disparity is exact, and it
  teaches that what looks like a subject is near wherever it lies in the frame.
- **Generated layered scenes** (:mod:`d2f_core.train.synth`) with their exact disparity, so the
  network stays calibrated on the scenes the bokeh stages and the held-out set use.

- **The keep term** (``--keep``): where a photo's target knows nothing new (outside its
  subjects, a margin around them and the sky; :func:`~d2f_core.train.scene_targets.taught_mask`),
  the network is also held to an earlier network's relative depth
  (:func:`~d2f_core.train.depth_losses.keep_loss`), so that what it learnt of whole scenes is
  not traded for the scene targets' coarser layout while those teach it subjects in front.
  Measured (``TRAINING.md``): it keeps the measured photos' scores and, with them, holds back
  the subjects' gain; the shipped weights were trained without it.

Real targets are relative (0 = farthest, 1 = nearest in each photo), so their loss is a
scale- and shift-invariant L1 plus multi-scale gradient matching (MiDaS), plus a plain L1 with
weight ``absolute_weight`` that keeps outputs in [0, 1]; generated scenes have absolute
targets and take a plain L1 plus gradient matching.

A photo is held out of training when :func:`is_heldout` says so (a hash of its name: about
one photo in ten); ``d2f-bench depth`` evaluates on exactly those.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import random
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..networks import (
    build_defocus_net,
    count_parameters,
    optimizer_state_on_cpu,
    read_torch_file,
)
from .depth_data import DepthSample, RealDepthData, resize_array
from .depth_losses import (
    depth_loss,
    gradient_matching_loss,
    keep_loss,
    rank_loss,
    scene_map_loss,
    ssi_align,
)
from .distill import Distiller, teacher_grid
from .heldout import is_heldout
from .scene_targets import subject_target
from .teachers import FeatureTeacher

__all__ = [
    "DepthSample",
    "RealDepthData",
    "gradient_matching_loss",
    "is_heldout",
    "resize_array",
    "ssi_align",
    "subject_target",
    "train_depth",
]

logger = logging.getLogger(__name__)

#: ``--layout-teacher`` when it is not given
LAYOUT_TEACHER = 0.4


def batch_shapes(sides: Sequence[int]) -> list[tuple[int, int]]:
    """Sample shapes for multi-scale training: for every long side in ``sides``, a square,
    a 4:3 landscape and a 3:4 portrait frame, both sides rounded to multiples of 32."""
    shapes = []
    for side in sides:
        short = max(32, round(side * 0.75 / 32) * 32)
        side = max(32, round(side / 32) * 32)
        shapes += [(side, side), (short, side), (side, short)]
    return shapes


class _Batches(torch.utils.data.IterableDataset):
    """Endless batches of :class:`RealDepthData` from a seeded stream (one per worker).

    With ``shapes``, every batch takes one shape drawn from them and as many samples as
    fit ``batch_size`` samples of :attr:`RealDepthData.size` in pixels (at least 2), so a
    step costs about the same at every scale.
    """

    def __init__(
        self,
        data: RealDepthData,
        batch_size: int,
        seed: int,
        shapes: Sequence[tuple[int, int]] = (),
        teacher: str | Path | None = None,
    ) -> None:
        self.data, self.batch_size, self.seed = data, batch_size, seed
        self.shapes = list(shapes)
        self.teacher = teacher

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        rng = random.Random(self.seed + (0 if info is None else 7919 * info.id))
        torch.set_num_threads(1)
        teacher = FeatureTeacher(self.teacher) if self.teacher is not None else None
        budget = self.batch_size * self.data.size[0] * self.data.size[1]
        while True:
            if not self.shapes:
                batch = self.data.batch(rng, self.batch_size)
            else:
                h, w = rng.choice(self.shapes)
                batch = self.data.batch(rng, max(2, round(budget / (h * w))), (h, w))
            if teacher is not None:
                batch = (*batch, teacher_grid(teacher, batch[0]))
            yield batch


# ------------------------------------------------------------------------------ training


def _load_defocus(net: torch.nn.Module, checkpoint: str | Path) -> torch.nn.Module:
    """``net`` with the defocus network of the D2F ``checkpoint`` loaded into it (a smaller
    lite variant grows into it, :meth:`~d2f_core.networks.DefocusNet.load_lite`)."""
    from ..pipeline import D2F

    net.load_lite(D2F.from_checkpoint(checkpoint).defocus_net.state_dict())
    return net


def _on_cpu(state: dict[str, Tensor]) -> dict[str, Tensor]:
    """A state dict with every tensor on the CPU (checkpoints load on any machine)."""
    return {k: v.detach().cpu() for k, v in state.items()}


def _real_data(args: argparse.Namespace) -> RealDepthData:
    """The photos of ``--data`` with the labels of ``--labels``, as the options ask."""
    return RealDepthData(
        args.data,
        args.labels,
        size=(args.crop, args.crop),
        paste=args.paste,
        synth=args.synth,
        layout_teacher=args.layout_teacher,
        scene_weight=args.scene_weight,
        scene=args.scene_targets,
        rescan_every=args.rescan_every,
        standing=args.standing,
        keep_on=args.keep_on if args.keep is not None else None,
        scene_maps=build_defocus_net(args.variant).scene_head is not None,
        jitter=args.jitter,
        frame_match=args.frame_match,
    )


def _check_options(args: argparse.Namespace, resuming: bool) -> None:
    """Stage 0's options checked against each other, before any photo is read.

    Raises:
        ValueError: naming the option and what it needs.
    """
    if args.head_only and args.init is None and not resuming:
        raise ValueError("--head-only needs --init: the network whose disparity stays as it is")
    if args.head_only and (args.keep is not None or args.distill is not None):
        raise ValueError("--head-only trains the scene head alone: --keep and --distill train "
                         "the rest of the network")  # fmt: skip
    if args.rank_weight < 0:
        raise ValueError(f"--rank-weight must be >= 0, got {args.rank_weight}")
    if not 0.0 <= args.rank_edge <= 1.0:
        raise ValueError(f"--rank-edge must lie in [0, 1], got {args.rank_edge}")
    if args.scene_map_weight < 0:
        raise ValueError(f"--scene-map-weight must be >= 0, got {args.scene_map_weight}")
    if args.ema and not 0.0 < args.ema < 1.0:
        raise ValueError(f"--ema must lie in (0, 1), got {args.ema}")
    if args.pack is None and (args.data is None or args.labels is None):
        raise ValueError("give --data and --labels, or --pack")
    if args.pack is not None and (args.data is not None or args.labels is not None):
        raise ValueError("--pack holds the photos and their targets: no --data or --labels")
    if args.pack is not None and (args.keep is not None or args.distill is not None):
        raise ValueError("--keep and --distill need the photos' labels: --data and --labels")
    if args.steps < 1:
        raise ValueError(f"--steps must be at least 1, got {args.steps}")
    if args.pack is not None and (
        args.scene_targets or args.rescan_every or args.layout_teacher != LAYOUT_TEACHER
    ):
        raise ValueError(
            "--scene-targets, --layout-teacher and --rescan-every build targets from the "
            "labels; a pack's targets were built when it was written (d2f-train depth-pack)"
        )
    if args.frame_match and not args.sides:
        raise ValueError(
            "--frame-match needs --sides: without it every batch is a square --crop, which "
            "fits a photo of either orientation"
        )
    if args.minutes is not None and args.minutes <= 0:
        raise ValueError(f"--minutes must be positive, got {args.minutes}")


def _save_depth_state(
    out: Path,
    args: argparse.Namespace,
    step: int,
    final: bool,
    net: torch.nn.Module,
    opt: torch.optim.Optimizer,
    ema: dict | None,
    distiller: Distiller | None,
    elapsed: float,
) -> None:
    """Write stage 0's checkpoints at ``step``: the kept weights (and their average) every
    ``--keep-every`` steps and at the end, then ``depth_last.pt``, the state a run resumes
    from, replaced in one step."""
    weights = _on_cpu(net.state_dict())
    averaged = None if ema is None else _on_cpu(ema)
    # the kept files first: a run stopped between them and depth_last.pt resumes from the
    # step before and writes them again (the other way round, it resumed at its last step
    # and never wrote them)
    if step % args.keep_every == 0 or final:
        torch.save(
            {"state_dict": weights, "step": step, "variant": args.variant},
            out / f"depth_{step:06d}.pt",
        )
        if averaged is not None:
            torch.save(
                {"state_dict": averaged, "step": step, "variant": args.variant, "ema": args.ema},
                out / f"depth_{step:06d}_ema.pt",
            )
    state = {
        "state_dict": weights,
        "elapsed_s": elapsed,
        "optimizer": optimizer_state_on_cpu(opt.state_dict()),
        "step": step,
        "variant": args.variant,
    }
    if distiller is not None:
        state["distiller"] = _on_cpu(distiller.state_dict())
    if averaged is not None:
        state["ema"] = averaged
    last = out / "depth_last.pt"
    tmp = last.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(last)


def _param_groups(net: torch.nn.Module, args: argparse.Namespace) -> list[dict]:
    """The optimiser's parameter groups: the network's trunk (frozen with ``--head-only``,
    the disparity then staying the initial network's) and its scene head, which starts
    untrained on a trained decoder and learns ten times faster."""
    head = [] if net.scene_head is None else list(net.scene_head.parameters())
    if args.head_only and not head:
        raise ValueError(f"--head-only needs a '-scene' --variant, got {args.variant!r}")
    ids = {id(q) for q in head}
    trunk = [q for q in net.parameters() if id(q) not in ids]
    groups = [] if args.head_only else [{"params": trunk, "lr_scale": 1.0}]
    if args.head_only:
        for q in trunk:
            q.requires_grad_(False)
    if head:
        groups.append({"params": head, "lr_scale": 10.0})
    return groups


def _resumed(
    last: Path,
    net: torch.nn.Module,
    opt: torch.optim.Optimizer,
    distiller: Distiller | None,
    device: torch.device,
) -> tuple[int, float, dict | None]:
    """``(step, seconds, ema)``: the state of ``last`` loaded into the network, the optimiser
    and the distiller; the step and the training seconds it had reached, and its weight
    average (on ``device``) if it kept one."""
    state = torch.load(last, map_location="cpu", weights_only=True)
    net.load_state_dict(state["state_dict"])
    opt.load_state_dict(state["optimizer"])
    ema = state.get("ema")
    if ema is not None:
        ema = {k: v.to(device) for k, v in ema.items()}
    if distiller is not None:
        if "distiller" not in state:
            raise ValueError(f"{last} was trained without --distill; use --restart")
        distiller.load_state_dict(state["distiller"])
    step = int(state["step"])
    logger.info("resumed from %s at step %d", last, step)
    return step, float(state.get("elapsed_s", 0.0)), ema


def _step_loss(
    net: torch.nn.Module,
    batch: list[Tensor],
    args: argparse.Namespace,
    keeper: torch.nn.Module | None,
    distiller: Distiller | None,
    encoder_feats: list[Tensor],
) -> tuple[Tensor, dict[str, float]]:
    """One batch's loss and its terms: the depth loss, the ranking term, the scene head's
    maps, the keep term towards ``keeper`` and the distillation of the encoder's features
    (``encoder_feats``, filled by its hook) towards the teacher's, as the options ask."""
    images, targets, relative, keep, maps, *teacher = batch
    if net.scene_head is None:
        pred = net(images)
    else:
        pred, logits = net.forward_scene(images)
    loss, parts = depth_loss(pred, targets, relative, args.absolute_weight)
    if args.rank_weight:
        ranked = rank_loss(pred, targets, edge=args.rank_edge)
        loss = loss + args.rank_weight * ranked
        parts["rank"] = ranked.item()
    if net.scene_head is not None:
        scene = scene_map_loss(logits, maps)
        loss = loss + args.scene_map_weight * scene
        parts["maps"] = scene.item()
    if keeper is not None:
        with torch.no_grad():
            reference = keeper(images)
        kept = keep_loss(pred, reference, keep)
        loss = loss + args.keep_weight * kept
        parts["keep"] = kept.item()
    if distiller is not None:
        if not bool(distiller.ready):
            distiller.fix_statistics(teacher[0])
        distill = distiller(encoder_feats.pop(), teacher[0])
        encoder_feats.clear()
        loss = loss + args.distill_weight * distill
        parts["distill"] = distill.item()
    return loss, parts


def _update_average(ema: dict[str, Tensor], net: torch.nn.Module, decay: float) -> None:
    """The weights' moving average one step on (buffers that are no floats copied)."""
    with torch.no_grad():
        for k, v in net.state_dict().items():
            if v.is_floating_point():
                ema[k].lerp_(v, 1.0 - decay)
            else:
                ema[k].copy_(v)


def _device(args: argparse.Namespace) -> torch.device:
    """The device of ``--device``, checked (cuDNN's autotuner on for CUDA)."""
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device here")
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True  # a few batch shapes, each seen many times
    return device


def _training_data(args: argparse.Namespace) -> RealDepthData:
    """The photos of ``--pack`` (a packed file) or of ``--data``."""
    if args.pack is None:
        return _real_data(args)
    from .depth_pack import PackedDepthData

    if "scene" in args.variant:
        raise ValueError("a pack holds no scene maps: a '-scene' --variant needs --data")
    data = PackedDepthData(
        args.pack, size=(args.crop, args.crop), paste=args.paste, synth=args.synth,
        scene_weight=args.scene_weight, standing=args.standing, jitter=args.jitter,
        frame_match=args.frame_match,
    )  # fmt: skip
    largest = max(args.sides or [args.crop])
    if largest > data.side:
        logger.warning(
            "batches up to %d px from a pack of %d px photos: the larger crops are "
            "upscaled", largest, data.side,
        )  # fmt: skip
    return data


def _networks(args: argparse.Namespace, device: torch.device) -> tuple:
    """``(net, groups, distiller, encoder_feats, keeper)`` on ``device``: the network to
    train (from ``--init``), its parameter groups, the ``--distill`` projection (its
    parameters a group of their own) with the list its hook fills with the encoder's output,
    and the frozen ``--keep`` network (``None`` without those options)."""
    net = build_defocus_net(args.variant)
    if args.init is not None:
        _load_defocus(net, args.init)
        logger.info("defocus network initialised from %s", args.init)
    distiller = None
    encoder_feats: list[Tensor] = []  # the encoder's output, kept by a hook for --distill
    groups = _param_groups(net, args)
    if args.distill is not None:
        distiller = Distiller(net.encoder.channels, args.distill_channels)
        # the projection starts at zero and must catch up with a trained encoder before
        # its gradient says anything to it: it learns ten times faster
        groups.append({"params": list(distiller.parameters()), "lr_scale": 10.0})
        net.encoder.register_forward_hook(lambda _m, _i, out: encoder_feats.append(out))
    keeper = None
    if args.keep is not None:
        keeper = _load_defocus(build_defocus_net(args.variant), args.keep)
        keeper.eval().requires_grad_(False)
        logger.info("keep term: weight %g towards %s", args.keep_weight, args.keep)
    for module in (net, keeper, distiller):
        if module is not None:
            module.to(device)
    return net, groups, distiller, encoder_feats, keeper


def _loader(
    data: RealDepthData, args: argparse.Namespace, step: int, device: torch.device
) -> Iterator:
    """An endless iterator of training batches from ``step`` on (its own seed per step)."""
    return iter(
        torch.utils.data.DataLoader(
            _Batches(
                data,
                args.batch_size,
                args.seed * 1_000_003 + step,
                batch_shapes(args.sides) if args.sides else (),
                teacher=args.distill,
            ),
            batch_size=None,
            num_workers=args.workers,
            pin_memory=device.type == "cuda",
            prefetch_factor=4 if args.workers else None,
        )
    )


def train_depth(args: argparse.Namespace) -> Path:
    """Run (or resume) stage 0; returns the path of the last checkpoint."""
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    last = out / "depth_last.pt"
    resuming = last.is_file() and not args.restart
    _check_options(args, resuming)  # the options alone, before the photos are scanned
    device = _device(args)
    data = _training_data(args)
    net, groups, distiller, encoder_feats, keeper = _networks(args, device)
    opt = torch.optim.AdamW(groups, lr=args.lr, weight_decay=1e-4)
    # the step, the seconds of training before this run (for --minutes) and the average
    step, spent, ema = _resumed(last, net, opt, distiller, device) if resuming else (0, 0.0, None)
    if not args.ema:
        ema = None
    elif ema is None:  # the average starts at the weights training starts from
        ema = {k: v.detach().clone() for k, v in net.state_dict().items()}
    torch.manual_seed(args.seed + step)
    logger.info(
        "stage 0: %s, %d params, %d photos (%d masked), crop %d, batch %d",
        args.variant,
        count_parameters(net),
        len(data.photos),
        len(data.masked),
        args.crop,
        args.batch_size,
    )
    net.train()
    if args.head_only:
        net.eval()  # the trunk's batch norms keep their statistics
    loader = _loader(data, args, step, device)
    t0 = time.perf_counter()
    log = open(out / "depth_log.jsonl", "a")  # noqa: SIM115
    budget = None if args.minutes is None else 60.0 * args.minutes

    def progress() -> float:
        """How far along the schedule: steps done, or the time budget spent if sooner."""
        done = step / args.steps
        if budget is not None:
            done = max(done, (spent + time.perf_counter() - t0) / budget)
        return min(1.0, done)

    done = progress() >= 1.0
    while not done:
        lr = args.lr * 0.5 * (1 + math.cos(math.pi * progress()))
        warm = min(1.0, (step + 1) / 200)
        for g in opt.param_groups:
            g["lr"] = lr * warm * g.get("lr_scale", 1.0)
        batch = [t.to(device, non_blocking=True) for t in next(loader)]
        loss, parts = _step_loss(net, batch, args, keeper, distiller, encoder_feats)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        step += 1
        if ema is not None:
            _update_average(ema, net, args.ema)
        if step % args.log_every == 0:
            elapsed = round(spent + time.perf_counter() - t0, 1)
            _log_step(log, step, loss.item(), parts, lr, elapsed)
        final = done = progress() >= 1.0
        if step % args.save_every == 0 or final:
            elapsed = spent + time.perf_counter() - t0
            _save_depth_state(out, args, step, final, net, opt, ema, distiller, elapsed)
    log.close()
    return last


def _log_step(log: Any, step: int, loss: float, parts: dict, lr: float, elapsed: float) -> None:
    """One line of ``depth_log.jsonl`` and of the log."""
    rec = {"step": step, "loss": loss, **parts, "lr": lr, "elapsed_s": elapsed}
    log.write(json.dumps(rec) + "\n")
    log.flush()
    logger.info("step %d loss %.4f %s", step, loss, parts)


def export_checkpoint(
    depth: str | Path, base: str | Path, out: str | Path, overrides: Sequence[str] = ()
) -> Path:
    """A D2F checkpoint: ``base`` with its defocus network replaced by the stage-0 weights
    in ``depth`` (a ``depth_*.pt`` file) and ``KEY=VALUE`` config overrides applied."""
    from ..pipeline import D2F
    from .overrides import apply_overrides

    model = D2F.from_checkpoint(base)
    config = apply_overrides(model.config.to_dict(), overrides)
    state = read_torch_file(
        depth, not_found="stage-0 weights not found", unreadable=f"{depth} cannot be read"
    )
    wanted = "give a depth_*.pt file of d2f-train depth"
    if isinstance(state, dict) and "config" in state:
        raise ValueError(
            f"{depth} holds no stage-0 weights (it is a whole D2F checkpoint): {wanted}"
        )
    if not isinstance(state, dict) or "state_dict" not in state:
        raise ValueError(f"{depth} holds no stage-0 weights: {wanted}")
    variant = state.get("variant", config["defocus"])
    config["defocus"] = variant
    fresh = D2F(config)
    fresh.radiance_net.load_state_dict(model.radiance_net.state_dict())
    fresh.fusion_net.load_state_dict(model.fusion_net.state_dict())
    fresh.defocus_net.load_state_dict(state["state_dict"])
    fresh.save(out)
    return Path(out)
