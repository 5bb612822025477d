"""``d2f-train``: the paper's two training stages on an EBB!-format data set.

Stage 1 trains the defocus and radiance networks jointly on the low-resolution bokeh
(``L1 + 0.1 L_vgg + L_ssim + 0.1 L_grad``). Stage 2 freezes them and trains the fusion
network alone at full resolution (stage-1 terms on the fused image ``+ 10 L_p``).

``--crop`` is in pixels of the data set's images; stage 1 resizes each crop by the model's
``render_scale`` (0.5) before the networks, as the paper trains at 512 px from 1024-px EBB!
images. Pairs with ``params/<id>.json`` use its ``focus`` and ``blur``; the others (EBB!)
use the config's ``train_focus`` (1.0: EBB! focuses on the nearest subject) and
``train_blur`` (138 px at 1024x1536, the paper's 69-px largest kernel at half size).

Outputs in ``--out``: ``stage<N>.pt`` (latest; a D2F checkpoint that also carries the
optimizer, step and arguments for ``--resume``), ``stage<N>_best.pt`` (best validation PSNR),
``train_stage<N>.csv`` (step, loss terms, lr, time) and ``val_stage<N>.csv``.

Under ``torchrun`` (``WORLD_SIZE`` > 1) it runs DistributedDataParallel with a
``DistributedSampler``; rank 0 logs, validates and writes checkpoints.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import os
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn
from torch.utils.data import DataLoader, DistributedSampler, Sampler

from .. import metrics
from ..networks import optimizer_state_on_cpu, read_torch_file
from ..pipeline import D2F, D2FConfig
from ..progress import progress
from ..rendering import PLACEMENTS
from ..sizing import resize, scaled_size, size_ratio
from .data import EBBDataset
from .losses import D2FLoss
from .overrides import apply_overrides

__all__ = ["TrainResult", "build_parser", "main", "train"]

logger = logging.getLogger(__name__)

_LOSS_COLUMNS = ("total", "l1", "vgg", "ssim", "grad", "poisson")


@dataclass
class TrainResult:
    """What :func:`train` returns: the trained model (on its device, eval mode), the final
    checkpoint path, the CSV log path and the last validation ``(psnr, ssim)`` (or None)."""

    model: D2F
    checkpoint: Path
    log: Path
    val: tuple[float, float] | None


# --------------------------------------------------------------------------------------
# distributed helpers
# --------------------------------------------------------------------------------------


@dataclass
class _Dist:
    world: int = 1
    rank: int = 0
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def _init_distributed(device_arg: str) -> tuple[_Dist, torch.device]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist(), torch.device(device_arg)
    rank = int(os.environ["RANK"])
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if device_arg.startswith("cuda"):
        torch.cuda.set_device(local_rank)
        device = torch.device("cuda", local_rank)
        backend = "nccl"
    else:
        device = torch.device("cpu")
        backend = "gloo"
    if not dist.is_initialized():
        dist.init_process_group(backend=backend)
    return _Dist(world, rank, local_rank), device


class _SkipSampler(Sampler[int]):
    """Yields ``inner``'s indices after dropping the first ``skip`` (to resume mid-epoch)."""

    def __init__(self, inner: DistributedSampler, skip: int = 0) -> None:
        self.inner, self.skip = inner, skip

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        self.inner.set_epoch(epoch)
        self.skip = skip

    def __iter__(self) -> Iterator[int]:
        it = iter(self.inner)
        for _ in range(self.skip):
            next(it, None)
        return it

    def __len__(self) -> int:
        return max(0, len(self.inner) - self.skip)


class _StageForward(nn.Module):
    """One training step's forward, as a module so DistributedDataParallel can wrap it."""

    def __init__(self, model: D2F, stage: int) -> None:
        super().__init__()
        self.model, self.stage = model, stage

    def forward(self, image: Tensor, focus: Tensor, blur: Tensor) -> dict[str, Tensor]:
        if self.stage == 1:
            return self.model.forward_stage1(image, focus, blur)
        return self.model.forward_stage2(image, focus, blur)


# --------------------------------------------------------------------------------------
# one step
# --------------------------------------------------------------------------------------


def _focus_blur(batch: dict[str, Any], config: D2FConfig, device) -> tuple[Tensor, Tensor]:
    focus = batch["focus"].to(device=device, dtype=torch.float32)
    blur = batch["blur"].to(device=device, dtype=torch.float32)
    focus = torch.where(torch.isnan(focus), torch.full_like(focus, config.train_focus), focus)
    blur = torch.where(torch.isnan(blur), torch.full_like(blur, config.train_blur), blur)
    return focus, blur


def batch_loss(
    forward: nn.Module, batch: dict[str, Any], stage: int, criterion: D2FLoss, device
) -> dict[str, Tensor]:
    """Loss terms of one batch (``"total"`` included) for ``stage`` 1 or 2.

    ``forward`` is a :class:`_StageForward` (possibly DDP-wrapped); ``batch`` comes from
    :class:`~d2f_core.train.data.EBBDataset` through a ``DataLoader``.
    """
    model: D2F = forward.module.model if hasattr(forward, "module") else forward.model
    image = batch["image"].to(device, non_blocking=True)  # [B,3,H,W]
    target = batch["target"].to(device, non_blocking=True)  # [B,3,H,W]
    focus, blur = _focus_blur(batch, model.config, device)
    if stage == 1:
        size = (int(image.shape[-2]), int(image.shape[-1]))
        lr_size = scaled_size(size, model.config.render_scale, None)
        ratio = size_ratio(lr_size, size)
        image_lr = resize(image, lr_size).clamp(0, 1)  # [B,3,h,w]
        target_lr = resize(target, lr_size).clamp(0, 1)
        out = forward(image_lr, focus, blur * ratio)
        return criterion.stage1(out["bokeh_lr"], target_lr, out["disparity"], image_lr)
    out = forward(image, focus, blur)
    return criterion.stage2(
        out["bokeh"], target, out["disparity"], image, out["bokeh_up"], out["defocus"]
    )


@torch.no_grad()
def validate(
    model: D2F, dataset: EBBDataset, stage: int, limit: int | None = None
) -> tuple[float, float]:
    """Mean PSNR / SSIM of the full pipeline (``prepare`` + ``render``) on ``dataset``.

    Stage 1 renders without fusion, stage 2 with it. Focus/blur come from each pair's
    params, else the config's training defaults.
    """
    model.eval()
    scores = []
    count = len(dataset) if limit is None else min(limit, len(dataset))
    for i in range(count):
        item = dataset[i]
        focus = float(item["focus"]) if not math.isnan(float(item["focus"])) else None
        blur = float(item["blur"]) if not math.isnan(float(item["blur"])) else None
        focus = model.config.train_focus if focus is None else focus
        blur = model.config.train_blur if blur is None else blur
        image = item["image"].permute(1, 2, 0).numpy()
        target = item["target"].permute(1, 2, 0).numpy()
        res = model.render(model.prepare(image), focus, blur, fusion=stage == 2)
        scores.append((metrics.psnr(res.bokeh, target), metrics.ssim(res.bokeh, target)))
    arr = np.asarray(scores, dtype=np.float64)
    return float(arr[:, 0].mean()), float(arr[:, 1].mean())


# --------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------


def _trainable(model: D2F, stage: int) -> list[nn.Parameter]:
    train_nets = [model.defocus_net, model.radiance_net] if stage == 1 else [model.fusion_net]
    for p in model.parameters():
        p.requires_grad_(False)
    params = []
    for net in train_nets:
        for p in net.parameters():
            p.requires_grad_(True)
            params.append(p)
    return params


def _save(path: Path, model: D2F, extra: dict[str, Any]) -> None:
    ckpt = model.checkpoint()
    ckpt.update(extra)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(ckpt, tmp)
    os.replace(tmp, path)  # a crash mid-write never leaves a truncated checkpoint


def _optimizer_to(optimizer: torch.optim.Optimizer, device) -> None:
    for state in optimizer.state.values():
        for k, v in state.items():
            if isinstance(v, Tensor) and k != "step":
                state[k] = v.to(device)


def _stage_model(args: argparse.Namespace, stage: int) -> tuple[D2F, dict | None]:
    """``(model, resume)``: the model a stage trains, from ``--resume`` (whose checkpoint,
    checked to be this stage's, is returned too), ``--init``, or a fresh config."""
    if args.resume is not None:
        resume = read_torch_file(
            args.resume,
            not_found="--resume checkpoint not found",
            unreadable=f"--resume {args.resume} cannot be read",
        )
        if resume.get("stage") != stage:
            raise ValueError(
                f"--resume {args.resume} is a stage-{resume.get('stage')} checkpoint, "
                f"not stage {stage}"
            )
        return D2F.from_checkpoint(args.resume), resume
    if args.init is not None:
        return D2F.from_checkpoint(args.init), None
    if stage == 2:
        logger.warning("stage 2 without --init: the defocus/radiance networks are random")
    model = D2F.from_config(
        {
            "defocus": args.variant,
            "fusion": args.fusion,
            "render_scale": args.render_scale,
            "placement": args.placement,
        }
    )
    if args.imagenet is not None:
        model.defocus_net.load_imagenet(args.imagenet)
    return model, None


def _stage_data(
    args: argparse.Namespace, ddp: Any, device: torch.device, step: int
) -> tuple[EBBDataset, EBBDataset | None, _SkipSampler, DataLoader, int]:
    """``(train_set, val_set, sampler, loader, epoch)``: the training pairs, shuffled per
    epoch and shared among the processes, starting at ``step`` (the batches of its epoch
    already seen are skipped); the validation pairs when ``--val-every`` asks for them."""
    train_set = EBBDataset(args.data, split=args.split, crop=args.crop, flip=True, seed=args.seed)
    val_set = EBBDataset(args.data, split=args.val_split) if args.val_every > 0 else None
    if len(train_set) < args.batch_size * ddp.world:
        raise ValueError(
            f"--batch-size {args.batch_size} x {ddp.world} process(es) is more than the "
            f"{len(train_set)} training pairs in {args.data}"
        )
    inner = DistributedSampler(
        train_set, num_replicas=ddp.world, rank=ddp.rank, shuffle=True, seed=args.seed,
        drop_last=True,
    )  # fmt: skip
    per_epoch = len(inner) // args.batch_size
    epoch, skip_batches = divmod(step, per_epoch)
    sampler = _SkipSampler(inner)
    sampler.set_epoch(epoch, skip_batches * args.batch_size)
    train_set.set_epoch(epoch)
    generator = torch.Generator().manual_seed(args.seed)
    loader = DataLoader(
        train_set,
        batch_size=args.batch_size,
        sampler=sampler,
        num_workers=args.workers,
        drop_last=True,
        pin_memory=device.type == "cuda",
        generator=generator,
    )
    return train_set, val_set, sampler, loader, epoch


def _stage_logs(
    out_dir: Path, stage: int, *, writes: bool, resumed: bool
) -> tuple[Path, Path, Path, Path, list]:
    """``(log, val, checkpoint, best, columns)``: a stage's files in ``out_dir`` and its
    training log's columns. The process that ``writes`` starts the two CSV logs with their
    headers, unless a resumed run has its log to append to."""
    log_path = out_dir / f"train_stage{stage}.csv"
    val_path = out_dir / f"val_stage{stage}.csv"
    columns = ["step", *_LOSS_COLUMNS[: 5 if stage == 1 else 6], "lr", "time_s"]
    if writes and (not resumed or not log_path.exists()):
        with log_path.open("w", newline="") as fh:
            csv.writer(fh).writerow(columns)
        with val_path.open("w", newline="") as fh:
            csv.writer(fh).writerow(["step", "psnr", "ssim", "images"])
    ckpt_path, best_path = out_dir / f"stage{stage}.pt", out_dir / f"stage{stage}_best.pt"
    return log_path, val_path, ckpt_path, best_path, columns


def _log_step(
    log_path: Path, columns: list, step: int, values: dict, lr: float, seconds: float
) -> None:
    """One row of the training log: the step, each loss term, the learning rate, the time."""
    row = [step, *(f"{values.get(c, 0.0):.6f}" for c in columns[1:-2])]
    row += [f"{lr:.3g}", f"{seconds:.2f}"]
    with log_path.open("a", newline="") as fh:
        csv.writer(fh).writerow(row)


def _stage_optimizer(
    model: D2F, stage: int, lr: float, resume: dict[str, Any] | None, device: torch.device
) -> tuple[torch.optim.Optimizer, int]:
    """Adam over the stage's trainable parameters, and the step to start from: a resumed
    run's optimizer state (moved to ``device``) and step, else a fresh one at step 0."""
    optimizer = torch.optim.Adam(_trainable(model, stage), lr=lr)
    if resume is None:
        return optimizer, 0
    optimizer.load_state_dict(resume["optimizer"])
    _optimizer_to(optimizer, device)
    return optimizer, int(resume["step"])


def train(args: argparse.Namespace) -> TrainResult:
    """Run one training stage described by parsed ``d2f-train`` arguments."""
    stage = 1 if args.stage == "stage1" else 2
    ddp, device = _init_distributed(args.device)
    out_dir = Path(args.out)
    if ddp.main:
        out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)

    # 1. model: resume > init checkpoint > fresh config
    model, resume = _stage_model(args, stage)
    model.to(device).train()
    optimizer, step = _stage_optimizer(model, stage, args.lr, resume, device)
    criterion = D2FLoss(args.vgg_weights, theta=model.config.fusion_theta).to(device)
    forward: nn.Module = _StageForward(model, stage)
    if ddp.world > 1:
        forward = nn.parallel.DistributedDataParallel(
            forward, device_ids=[device.index] if device.type == "cuda" else None
        )

    # 2. data, from where a resumed run stopped
    train_set, val_set, sampler, loader, epoch = _stage_data(args, ddp, device, step)

    # 3. logs
    log_path, val_path, ckpt_path, best_path, columns = _stage_logs(
        out_dir, stage, writes=ddp.main, resumed=resume is not None
    )
    best = float(resume.get("best_psnr", -math.inf)) if resume is not None else -math.inf
    run_args = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}

    def extra() -> dict[str, Any]:
        return {
            "stage": stage,
            "step": step,
            "optimizer": optimizer_state_on_cpu(optimizer.state_dict()),
            "best_psnr": best,
            "args": run_args,
        }

    def run_validation() -> tuple[float, float] | None:
        nonlocal best
        if val_set is None or not ddp.main:
            return None
        scores = validate(model, val_set, stage, args.val_limit)
        model.train()
        with val_path.open("a", newline="") as fh:
            csv.writer(fh).writerow([step, f"{scores[0]:.4f}", f"{scores[1]:.5f}", len(val_set)])
        logger.info("step %d: val PSNR %.3f dB, SSIM %.4f", step, *scores)
        if scores[0] > best:
            best = scores[0]
            _save(best_path, model, extra())
        return scores

    # 4. loop
    val_scores = None
    start = time.perf_counter()
    bar = progress(total=args.steps, initial=step, disable=not ddp.main, desc=f"stage{stage}")
    while step < args.steps:
        for batch in loader:
            terms = batch_loss(forward, batch, stage, criterion, device)
            optimizer.zero_grad(set_to_none=True)
            terms["total"].backward()
            optimizer.step()
            step += 1
            bar.update(1)
            if ddp.main and (step % args.log_every == 0 or step == args.steps or step == 1):
                values = {k: float(v.detach()) for k, v in terms.items()}
                bar.set_postfix(loss=f"{values['total']:.4f}")
                lr = optimizer.param_groups[0]["lr"]
                _log_step(log_path, columns, step, values, lr, time.perf_counter() - start)
            if args.val_every > 0 and step % args.val_every == 0:
                val_scores = run_validation() or val_scores
            if ddp.main and (step % args.save_every == 0 or step == args.steps):
                _save(ckpt_path, model, extra())
            if ddp.world > 1 and (step % args.val_every == 0 if args.val_every > 0 else False):
                dist.barrier()
            if step >= args.steps:
                break
        epoch += 1
        sampler.set_epoch(epoch, 0)
        train_set.set_epoch(epoch)
    bar.close()
    if args.val_every > 0 and step % args.val_every != 0:
        val_scores = run_validation() or val_scores
    if ddp.main and not ckpt_path.exists():
        _save(ckpt_path, model, extra())
    if ddp.world > 1:
        dist.barrier()
        dist.destroy_process_group()
    model.eval()
    return TrainResult(model, ckpt_path, log_path, val_scores)


def build_parser() -> argparse.ArgumentParser:
    """The ``d2f-train`` argument parser (subcommands ``stage1`` and ``stage2``)."""
    parser = argparse.ArgumentParser(
        prog="d2f-train",
        description="Train D2F: stage1 = defocus + radiance networks, stage2 = fusion network.",
    )
    parser.epilog = (
        "Also: 'd2f-train label' (teacher pseudo-labels of real photos), 'd2f-train depth' "
        "(stage 0, the defocus network on real photos; 'd2f-train depth export' makes a D2F "
        "checkpoint of it) and 'd2f-train port-teachers' (the scene teachers' original files into "
        "the torch weights the scene source ships): see TRAINING.md."
    )
    sub = parser.add_subparsers(dest="stage", required=True)
    for name, crop, help_text in (
        ("stage1", 1024, "defocus + radiance networks on the low-res bokeh"),
        ("stage2", 1024, "fusion network alone at full resolution (others frozen)"),
    ):
        p = sub.add_parser(name, help=help_text)
        p.add_argument("--data", type=Path, required=True, help="EBB!-format data folder")
        p.add_argument("--out", type=Path, required=True, help="output folder")
        p.add_argument("--variant", choices=("lite", "resnext50"), default="lite")
        p.add_argument("--fusion", choices=("lite", "paper"), default="lite")
        p.add_argument("--render-scale", type=float, default=0.5)
        p.add_argument(
            "--placement",
            choices=PLACEMENTS,
            default="paper",
            help="renderer layer placement of a new model (kept from --init/--resume)",
        )
        p.add_argument("--steps", type=int, default=100_000)
        p.add_argument("--batch-size", type=int, default=4)
        p.add_argument("--crop", type=int, default=crop, help="square crop, px of the data images")
        p.add_argument("--lr", type=float, default=1e-4)
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--split", default="train", help="training split (default: train)")
        p.add_argument("--val-split", default="val470")
        p.add_argument("--val-every", type=int, default=1000, help="0 = never")
        p.add_argument("--val-limit", type=int, default=None, help="validate on N images")
        p.add_argument("--save-every", type=int, default=1000)
        p.add_argument("--log-every", type=int, default=10)
        p.add_argument("--resume", type=Path, default=None, help="checkpoint of this stage")
        p.add_argument(
            "--init", type=Path, default=None, help="start from this model (stage 2: stage-1 ckpt)"
        )
        p.add_argument("--vgg-weights", type=Path, default=None, help="local VGG19 state dict")
        p.add_argument(
            "--imagenet", type=Path, default=None, help="local ResNeXt50 ImageNet state dict"
        )
        p.add_argument(
            "--device", default="cuda" if torch.cuda.is_available() else "cpu",
            help="cpu or cuda",
        )  # fmt: skip
        p.add_argument("--workers", type=int, default=2)
        p.add_argument("-v", "--verbose", action="store_true")
    p = sub.add_parser(
        "export", help="write a shippable checkpoint (no optimizer state), with config changes"
    )
    p.add_argument("checkpoint", type=Path, help="a stage-1 or stage-2 checkpoint")
    p.add_argument("out", type=Path, help="the checkpoint to write")
    p.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="config override for inference, e.g. --set network_size=384 --set render_scale=0.5",
    )  # fmt: skip
    p.add_argument("-v", "--verbose", action="store_true")
    return parser


def export(checkpoint: Path, out: Path, overrides: Sequence[str]) -> Path:
    """Reload ``checkpoint``, apply ``KEY=VALUE`` config overrides, save to ``out``."""
    model = D2F.from_checkpoint(checkpoint)
    config = apply_overrides(model.config.to_dict(), overrides)
    # validates the new config before anything is written
    model.config = type(model.config).from_dict(config)
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["label-scene"]:  # every teacher's labels, the scene ones included
        from .scene_teachers import run_label_scene

        return run_label_scene(argv[1:])
    if argv[:1] == ["label"]:  # pseudo-labels of real photos by the teachers
        from .teachers import run_label

        return run_label(argv[1:])
    if argv[:1] == ["depth-pack"]:  # stage 0's photos and targets, packed small
        from .depth_pack import main as pack_main

        return pack_main(argv[1:])
    if argv[:1] == ["port-teachers"]:  # the scene teachers' original files -> torch weights
        from .port_teachers import main as port_main

        return port_main(argv[1:])
    if argv[:1] == ["depth"]:  # stage 0: depth from real photos
        from .depth_cli import main as depth_main

        return depth_main(argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if args.stage == "export":
        try:
            logger.info("wrote %s", export(args.checkpoint, args.out, args.set))
        except (ValueError, TypeError, FileNotFoundError) as exc:
            logger.error("%s", exc)
            return 2
        return 0
    for name in ("steps", "batch_size", "crop", "save_every", "log_every"):
        if getattr(args, name) < 1:
            raise SystemExit(f"d2f-train: --{name.replace('_', '-')} must be >= 1")
    try:
        result = train(args)
    except (ValueError, FileNotFoundError) as exc:
        logger.error("%s", exc)
        return 2
    if os.environ.get("RANK", "0") == "0":
        logger.info("wrote %s (log %s)", result.checkpoint, result.log)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
