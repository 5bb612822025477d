"""The D2F pipeline: networks once per image (:meth:`D2F.prepare`), then cheap refocus renders.

Inference (:meth:`D2F.render`), numbered as in the paper:

1. ``I_lr``: the photo at ``render_scale`` (0.5), long side capped at ``max_render_side``.
2. Disparity ``d`` from the defocus network at ``network_size`` (or a given map), upsampled
   to ``I_lr``'s size. Unlike the paper, which bakes the training focus into ``D = |D_d - f|``,
   the signed disparity is cached, so refocusing is a change of ``focus`` only.
3. ``R0`` from the radiance network on ``I_lr``.
4.-5. ``B_lr = rendering.render(I_lr, d, focus, K_lr, radiance=R0)`` (HDR boost inside,
   depth-ordered compositing by default).
6. Deep Poisson fusion at full resolution: ``B_up = bilinear(B_lr)``,
   ``M = max(M_s, P)``, ``B_hr = M * I_hr + (1 - M) * B_up``.

About the mask ``M``:

* ``M_s = f_p(1 - D, gray(I_hr)) * [D < fusion_gate]`` where ``D = coc_to_defocus(CoC at the
  low-res pass)``. The hard gate is part of the model (training uses it too), so running
  ``f_p`` only on the image tiles that hold pixels with ``D < fusion_gate`` is exact, and a
  12 MP fusion costs only what the in-focus part of the frame costs.
* ``P`` is an in-focus prior: 1 where the full-resolution CoC is at most ``sharp_coc`` px
  (default 1 px), falling linearly to 0 at twice that. The paper's thresholded/learned mask
  can leave no sharp region at all; with ``P`` every pixel whose CoC is below a pixel is
  guaranteed to show the sharp input, whatever ``f_p`` predicts.

Checkpoints are ``{"config", "state_dict", "version"}`` files written by :meth:`D2F.save`.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from . import bundled, rendering
from .depth import sources as depth_sources
from .depth.refine import harden_edges, snap_edges
from .errors import InputTypeError
from .io.embedded import Photo
from .networks import (
    build_defocus_net,
    build_fusion_net,
    build_radiance_net,
    read_torch_file,
    rgb_to_gray,
)
from .rendering import adaptive
from .rendering.schedule import coc_to_defocus, defocus_to_coc
from .sizing import resize, scaled_size, size_ratio

__all__ = [
    "CHECKPOINT_VERSION",
    "D2F",
    "D2FConfig",
    "Result",
    "Scene",
    "default_weights_path",
    "find_subject",
    "locate_subject",
]

logger = logging.getLogger(__name__)

CHECKPOINT_VERSION = 1
_FUSION_TILE = 256


def default_weights_path() -> Path:
    """``$D2F_WEIGHTS`` if set, else the shipped weights (:func:`bundled.shipped_weights`)."""
    env = os.environ.get("D2F_WEIGHTS")
    if env:
        return Path(env)
    return bundled.shipped_weights()


@dataclass
class D2FConfig:
    """Architecture and inference settings; saved inside every checkpoint.

    Attributes:
        defocus: defocus network variant (``"lite"`` or ``"resnext50"``).
        radiance: radiance network variant (``"paper"``).
        fusion: fusion network variant (``"lite"`` or ``"paper"``).
        network_size: long side (px) the defocus network runs at in :meth:`D2F.prepare`.
        render_scale: scale of the low-resolution rendering pass (paper: 0.5).
        max_render_side: cap on the long side of the low-resolution pass (px).
        full_pass_side: a photo prepared with a given disparity map (a phone's depth, a
            user's map) whose long side is at most this (px) is rendered at its own size,
            and the fusion step, which only restores the detail a smaller pass loses, is
            skipped. With exact maps of generated scenes at 384x576 the half-size pass with
            fusion is 2.5 dB under this, 2.7 dB near depth edges. The network's own maps
            keep ``render_scale``: with them the half-size pass and fusion forgive the map's
            errors (on the held-out photo scenes 28.06 dB, against 26.86 dB at full size).
            0 keeps ``render_scale`` for every photo.
        order: compositing order passed to ``rendering.render`` (``"depth"`` or ``"paper"``).
        placement: layer placement passed to ``rendering.render`` (``"paper"`` or
            ``"nearest"``, see ``rendering.layer_plan``). A model renders with the placement
            it was trained with: the shipped ``lite`` weights use ``"paper"``.
        train_focus: focal disparity used for training pairs without ``params`` (EBB!
            focuses on the nearest subject, so 1.0 = nearest).
        train_blur: ``K`` (px at the pair's full resolution) for pairs without ``params``;
            138 px at EBB!'s 1024x1536 is the paper's 69-px largest kernel at half size.
        fusion_theta: threshold on ``D`` of the binary in-focus mask ``M_b`` (stage-2 target).
        fusion_gate: ``M_s`` is forced to 0 where ``D >= fusion_gate``.
        sharp_coc: full-res CoC (px) below which a pixel always stays sharp.
        refine: ``"none"`` (the network's map upsampled bilinearly) or ``"snap"`` (its soft
            edges moved onto the photo's colour edges at the render pass's size,
            :func:`refine.snap_edges`).
        refine_radius: the snapping window's radius as a fraction of that size's long side.
        refine_eps: squared colour distance below which two regions count as alike.
        flip_average: average the network's map with its map of the mirrored photo (one
            batch of two: about twice the network's time, a steadier map).
        edge_step: in :meth:`D2F.prepare`, every pixel of a depth edge (a window spanning at
            least this much disparity) is put on one side of it, given or predicted map
            alike (:func:`refine.harden_edges`): the pixels of a soft silhouette otherwise
            get a blur neither side has and draw a rim of the subject's colour over the
            background. 0 keeps the map as it is.
        edge_radius: that window's radius as a fraction of the render pass's long side (at
            least 3 px).
    """

    defocus: str = "lite"
    radiance: str = "paper"
    fusion: str = "lite"
    network_size: int = 768
    render_scale: float = 0.5
    max_render_side: int = 1024
    full_pass_side: int = 0
    order: str = "depth"
    placement: str = "paper"
    train_focus: float = 1.0
    train_blur: float = 138.0
    fusion_theta: float = 0.25
    fusion_gate: float = 0.3
    sharp_coc: float = 1.0
    refine: str = "none"
    refine_radius: float = 0.03
    refine_eps: float = 1e-3
    flip_average: bool = False
    edge_step: float = 0.1
    edge_radius: float = 0.004

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            kind = (
                f.type
                if isinstance(f.type, type)
                else {"str": str, "int": int, "bool": bool}.get(str(f.type), float)
            )
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
                setattr(self, f.name, value)
            if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
                raise InputTypeError(f"config.{f.name} must be {kind.__name__}, got {value!r}")
        if self.order not in ("depth", "paper"):
            raise ValueError(f"config.order must be 'depth' or 'paper', got {self.order!r}")
        if self.placement not in rendering.PLACEMENTS:
            raise ValueError(
                f"config.placement must be one of {rendering.PLACEMENTS}, got {self.placement!r}"
            )
        if self.refine not in ("none", "snap"):
            raise ValueError(f"config.refine must be 'none' or 'snap', got {self.refine!r}")
        if not (0 <= self.refine_radius <= 0.25 and self.refine_eps > 0):
            raise ValueError("config.refine_radius must be in [0, 0.25] and refine_eps > 0")
        if not (0 <= self.edge_step <= 1 and 0 <= self.edge_radius <= 0.05):
            raise ValueError("config.edge_step must be in [0, 1] and edge_radius in [0, 0.05]")
        if not 0 < self.render_scale <= 1:
            raise ValueError(f"config.render_scale must be in (0, 1], got {self.render_scale}")
        if self.full_pass_side < 0:
            raise ValueError(f"config.full_pass_side must be >= 0, got {self.full_pass_side}")
        if self.network_size < 32 or self.max_render_side < 16:
            raise ValueError("config.network_size must be >= 32 and max_render_side >= 16")
        if not 0 <= self.train_focus <= 1:
            raise ValueError(f"config.train_focus must be in [0, 1], got {self.train_focus}")
        if not (self.train_blur >= 0 and self.sharp_coc > 0 and 0 < self.fusion_gate <= 1):
            raise ValueError("config.train_blur >= 0, sharp_coc > 0, 0 < fusion_gate <= 1")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> D2FConfig:
        """Build from a dict; unknown keys raise ``ValueError``."""
        if not isinstance(data, dict):
            raise InputTypeError(f"config must be a dict, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown config keys {unknown}; known keys are {sorted(known)}")
        return cls(**data)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class Scene:
    """Everything :meth:`D2F.render` needs for one photo, computed once by :meth:`D2F.prepare`.

    Attributes:
        image: full-resolution photo, ``[1, 3, H, W]`` float32 in [0, 1].
        image_lr: low-resolution pass input, ``[1, 3, h, w]`` in [0, 1].
        disparity_lr: ``[1, 1, h, w]`` in [0, 1], 1 = nearest.
        radiance_lr: ``R0`` before the HDR boost, ``[1, 1, h, w]`` in (0, 1).
        size: ``(H, W)`` of the full-resolution photo.
        disparity_source: the depth source (:mod:`d2f_core.depth.sources`): ``"d2f"``,
            ``"embedded"``, ``"file:PATH"``, ``"transformers:MODEL"``, or ``"given"`` for a
            bare map passed to :meth:`D2F.prepare`.
        disparity_output: what that source gave (``"relative inverse depth"``, ``"metric
            depth"``, ``"apple_mpo phone depth"``, ``"D2F network disparity"``, ...).
        refined: whether :meth:`D2F.refine_disparity` ran on the map.
        cache: derived tensors (full-res disparity, preview-size inputs), filled lazily.
    """

    image: Tensor
    image_lr: Tensor
    disparity_lr: Tensor
    radiance_lr: Tensor
    size: tuple[int, int]
    disparity_source: str = "d2f"
    disparity_output: str = "D2F network disparity"
    refined: bool = True
    given_disparity: Tensor | None = field(default=None, repr=False)
    cache: dict[Any, Any] = field(default_factory=dict, repr=False)

    def disparity_full_tensor(self) -> Tensor:
        """Disparity at full resolution, ``[1, 1, H, W]`` in [0, 1] (cached).

        The given map when one was passed to ``prepare`` (resized to the photo), else the
        network's map upsampled bilinearly.
        """
        if "disparity_full" not in self.cache:
            src = self.given_disparity if self.given_disparity is not None else self.disparity_lr
            with torch.no_grad():
                self.cache["disparity_full"] = resize(src, self.size).clamp(0, 1)
        return self.cache["disparity_full"]

    def disparity_tile_range(self, tile: int) -> tuple[Tensor, Tensor]:
        """Min and max of the full-res disparity over ``tile`` x ``tile`` blocks (cached).

        Shape: two ``[ceil(H / tile), ceil(W / tile)]`` tensors.
        """
        key = ("tile_range", tile)
        if key not in self.cache:
            with torch.no_grad():
                d = self.disparity_full_tensor()
                hi = F.max_pool2d(d, tile, tile, ceil_mode=True)[0, 0]
                lo = -F.max_pool2d(-d, tile, tile, ceil_mode=True)[0, 0]
            self.cache[key] = (lo, hi)
        return self.cache[key]

    def disparity_full(self) -> np.ndarray:
        """Disparity at full resolution as ``H x W`` float32 numpy in [0, 1] (1 = nearest)."""
        return self.disparity_full_tensor()[0, 0].detach().cpu().numpy()


@dataclass
class Result:
    """One render (numpy, float32).

    Attributes:
        bokeh: ``H x W x 3`` in [0, 1] (preview size when ``max_side`` was given).
        bokeh_lr: ``h x w x 3`` in [0, 1], the low-resolution rendering pass.
        disparity: ``h x w`` in [0, 1], 1 = nearest.
        defocus: ``h x w`` in [0, 1], the paper's normalised defocus of each pixel
            (``schedule.coc_to_defocus`` of its CoC at the low-res pass).
        fusion_mask: ``H x W`` in [0, 1], weight of the sharp input in ``bokeh`` (zeros when
            fusion is off or in preview).
        timings: milliseconds per stage.
        settings: what the adaptive picker chose for this focus and blur
            (:class:`adaptive.RenderSettings`: layer count, reduced-resolution preset,
            identity path, predicted PSNR), ``None`` when the settings were fixed.
    """

    bokeh: np.ndarray
    bokeh_lr: np.ndarray
    disparity: np.ndarray
    defocus: np.ndarray
    fusion_mask: np.ndarray
    timings: dict[str, float]
    settings: adaptive.RenderSettings | None = None


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _per_sample(value: float | Tensor, batch: int, ref: Tensor) -> Tensor:
    """Scalar or ``[B]`` -> ``[B, 1, 1, 1]`` on ``ref``'s device and dtype."""
    t = torch.as_tensor(value, dtype=ref.dtype, device=ref.device).reshape(-1)
    if t.numel() == 1:
        t = t.expand(batch)
    if t.numel() != batch:
        raise ValueError(f"expected a scalar or {batch} values, got {t.numel()}")
    return t.reshape(batch, 1, 1, 1)


def _to_numpy_image(x: Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).contiguous().cpu().numpy()


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1000.0


# --------------------------------------------------------------------------------------
# the model
# --------------------------------------------------------------------------------------


class D2F(nn.Module):
    """Defocus-to-Focus: defocus, radiance and fusion networks plus the layered renderer.

    Use :meth:`from_pretrained`, :meth:`from_checkpoint` or :meth:`from_config`; all return
    the model in ``eval()`` mode. ``prepare`` runs the networks once per photo and ``render``
    refocuses cheaply; ``forward_stage1`` / ``forward_stage2`` are the differentiable
    training forwards.
    """

    def __init__(self, config: D2FConfig | dict[str, Any] | None = None) -> None:
        super().__init__()
        if config is None:
            config = D2FConfig()
        elif isinstance(config, dict):
            config = D2FConfig.from_dict(config)
        elif not isinstance(config, D2FConfig):
            raise InputTypeError(f"config must be a D2FConfig or dict, got {type(config).__name__}")
        self.config = config
        self.defocus_net = build_defocus_net(config.defocus)
        self.radiance_net = build_radiance_net(config.radiance)
        # channels-last weights make the few-channel full-res convs 3-10x faster on CPU
        self.fusion_net = build_fusion_net(config.fusion).to(memory_format=torch.channels_last)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    # ---------------------------------------------------------------- construction / io

    @classmethod
    def from_config(cls, config: D2FConfig | dict[str, Any] | None = None) -> D2F:
        """Randomly initialised model in ``eval()`` mode."""
        return cls(config).eval()

    @classmethod
    def from_checkpoint(cls, path: str | Path, map_location: str | torch.device = "cpu") -> D2F:
        """Load a ``{"config", "state_dict", "version"}`` checkpoint (extra keys are ignored).

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: the file is corrupt or truncated, lacks the expected keys, has a newer
                version, or its weights do not match its config.
        """
        path = Path(path)
        ckpt = read_torch_file(
            path,
            not_found="checkpoint not found",
            unreadable=f"checkpoint {path} is corrupt or truncated",
        )
        if not isinstance(ckpt, dict) or not {"config", "state_dict"} <= set(ckpt):
            keys = sorted(ckpt) if isinstance(ckpt, dict) else type(ckpt).__name__
            raise ValueError(f"checkpoint {path} must hold 'config' and 'state_dict', got {keys}")
        version = ckpt.get("version", CHECKPOINT_VERSION)
        if not isinstance(version, int) or version > CHECKPOINT_VERSION:
            raise ValueError(
                f"checkpoint {path} has version {version!r}; this code reads up to "
                f"{CHECKPOINT_VERSION}"
            )
        try:
            model = cls(ckpt["config"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"checkpoint {path} has an invalid config: {exc}") from exc
        state = ckpt["state_dict"]
        if not isinstance(state, dict):
            raise ValueError(f"checkpoint {path}: state_dict is not a dict")
        own = model.state_dict()
        missing = sorted(set(own) - set(state))
        unexpected = sorted(set(state) - set(own))
        mismatched = [
            k
            for k in own
            if k in state
            and (not isinstance(state[k], Tensor) or tuple(state[k].shape) != tuple(own[k].shape))
        ]
        if missing or unexpected or mismatched:
            raise ValueError(
                f"checkpoint {path} does not match its config {model.config.to_dict()}: "
                f"missing {missing[:3]}{'...' if len(missing) > 3 else ''}, "
                f"unexpected {unexpected[:3]}{'...' if len(unexpected) > 3 else ''}, "
                f"wrong shape {mismatched[:3]}{'...' if len(mismatched) > 3 else ''}"
            )
        model.load_state_dict(state)
        return model.to(map_location).eval()

    @classmethod
    def from_pretrained(cls, path: str | Path | None = None) -> D2F:
        """Load the shipped weights (``assets/weights/d2f_lite.pt``, or ``$D2F_WEIGHTS``).

        Raises:
            FileNotFoundError: naming the missing weights file.
        """
        path = Path(path) if path is not None else default_weights_path()
        if not path.is_file():
            raise FileNotFoundError(
                f"D2F weights not found: {path} (train them with d2f-train, or point "
                f"D2F_WEIGHTS / the path argument at a checkpoint)"
            )
        return cls.from_checkpoint(path)

    def checkpoint(self) -> dict[str, Any]:
        """The checkpoint dict ``{"config", "state_dict", "version"}`` (tensors on CPU)."""
        state = {k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}
        return {"config": self.config.to_dict(), "state_dict": state, "version": CHECKPOINT_VERSION}

    def save(self, path: str | Path) -> None:
        """Write :meth:`checkpoint` to ``path`` (parent folders are created)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(self.checkpoint(), path)

    # ---------------------------------------------------------------- networks

    def predict_disparity(self, image: Tensor, refine: bool = True) -> Tensor:
        """Defocus network at ``config.network_size`` (averaged with its mirror image with
        ``config.flip_average``), resized back to the input size; with ``refine`` and
        ``config.refine="snap"`` its edges are then moved onto the photo's
        (:func:`refine.snap_edges`).

        Shape: (B, 3, h, w) in [0, 1] -> (B, 1, h, w) in [0, 1].
        """
        size = tuple(image.shape[-2:])
        net_size = scaled_size(size, 1.0, self.config.network_size)
        small = resize(image, net_size)
        if self.config.flip_average:
            both = self.defocus_net(torch.cat([small, small.flip(-1)]))  # [2B,1,hn,wn]
            b = small.shape[0]
            d = 0.5 * (both[:b] + both[b:].flip(-1))
        else:
            d = self.defocus_net(small)
        d = resize(d, size)  # [B,1,h,w]
        if refine:
            d = self._snap(image, d)
        return d.clamp(0, 1)

    def _snap(self, image: Tensor, disparity: Tensor) -> Tensor:
        if self.config.refine != "snap":
            return disparity
        radius = max(1, round(self.config.refine_radius * max(image.shape[-2:])))
        return snap_edges(image, disparity, radius, self.config.refine_eps).clamp_(0, 1)

    def refine_disparity(self, image: Tensor, disparity: Tensor) -> Tensor:
        """Edge-aware refinement of a disparity map from any source, guided by the photo at
        the map's size (:meth:`prepare` runs it at the rendering pass's size): with
        ``config.edge_step > 0`` every pixel on a silhouette's ramp is put on one side of it
        by its colour (:func:`refine.harden_edges`).

        The snapping of ``config.refine="snap"`` belongs to the defocus network's own map
        (:meth:`predict_disparity`), a soft map at ``network_size``; on a phone's map it
        copies the photo's texture into the depth (the portrait with a matte, at 768x1024:
        depth-edge pixels 12k -> 48k, the silhouette's IoU with the matte 0.653 -> 0.597).

        Shape: image (1, 3, h, w) in [0, 1], disparity (1, 1, h, w) -> (1, 1, h, w) in [0, 1].
        """
        if self.config.edge_step <= 0:
            return disparity
        radius = max(3, round(self.config.edge_radius * max(image.shape[-2:])))
        return harden_edges(image, disparity, radius, self.config.edge_step)

    def fusion_mask(
        self,
        image: Tensor,
        disparity: Tensor,
        focus: float | Tensor,
        blur: float | Tensor,
        lr_ratio: float,
    ) -> tuple[Tensor, Tensor]:
        """Soft fusion mask ``M = max(M_s, P)`` at full resolution (dense, differentiable).

        Args:
            image: ``I_hr``, ``(B, 3, H, W)`` in [0, 1].
            disparity: full-resolution disparity ``(B, 1, H, W)`` in [0, 1].
            focus: focal disparity, float or ``[B]``.
            blur: ``K`` in px at full resolution, float or ``[B]``.
            lr_ratio: size of the low-res pass over full size (the defocus ``D`` fed to
                ``f_p`` is the paper's normalised defocus of the CoC at the low-res pass).

        Returns:
            ``(M, M_s)``, both ``(B, 1, H, W)`` in [0, 1].
        """
        cfg = self.config
        b = image.shape[0]
        f = _per_sample(focus, b, image)
        k = _per_sample(blur, b, image)
        coc = k * (disparity - f).abs()  # [B,1,H,W] full-res px
        prior = ((2.0 * cfg.sharp_coc - coc) / cfg.sharp_coc).clamp(0, 1)
        defocus = coc_to_defocus(coc * lr_ratio)
        gate = (defocus < cfg.fusion_gate).to(image.dtype)
        m_s = self.fusion_net(1.0 - defocus, rgb_to_gray(image)) * gate
        return torch.maximum(m_s, prior), m_s

    def _fuse_tiled(
        self,
        scene: Scene,
        bokeh_up: Tensor,
        focus: float,
        blur: float,
        lr_ratio: float,
        behind: tuple[Tensor, Tensor] | None = None,
    ) -> tuple[Tensor, Tensor]:
        """``B_hr = lerp(B_up, I_hr, M)`` computed tile by tile (inference), in place.

        Each 256-px tile is classified from the range of the disparity inside it (cached per
        scene): far from focus (``M = 0``: keep ``B_up``), entirely sharp (``CoC <= sharp_coc``
        everywhere: ``M = 1``), or mixed, where ``M`` is computed per pixel, running ``f_p``
        only if some pixel can pass its gate. The result equals the dense
        :meth:`fusion_mask` blend; the cost follows the in-focus part of the frame.

        ``behind`` (full size, from ``rendering.render(..., behind=True)``): the share of
        each pixel that the layers at and behind the focal plane make, and their colour.
        Where a blurred foreground covers an in-focus pixel, only that part is sharpened,
        ``B_hr = B_up + M * share * (I_hr - colour)``, so the foreground's blur stays over
        it (a plain lerp pasted the sharp background over the blur of a near object, which
        then ended in a hard edge); where nothing is in front this is the lerp. The mask
        returned is then ``M * share``, the weight of the sharp photo in the result.

        Returns:
            ``(bokeh, mask)``: ``(1, 3, H, W)`` (``bokeh_up``, modified) and ``(1, 1, H, W)``.
        """
        cfg = self.config
        height, width = scene.size
        t = _FUSION_TILE
        lo, hi = scene.disparity_tile_range(t)  # [gh,gw]
        # CoC range of each tile: distance of [lo, hi] to the focal plane
        coc_lo = blur * torch.clamp(torch.maximum(lo - focus, focus - hi), min=0.0)
        coc_hi = blur * torch.maximum((hi - focus).abs(), (lo - focus).abs())
        gate_coc = defocus_to_coc(cfg.fusion_gate) / lr_ratio * 1.01
        sharp = cfg.sharp_coc
        all_sharp = coc_hi <= sharp
        needs_net = (coc_lo < gate_coc) & (coc_hi > sharp)
        needs_pixels = ((coc_lo < 2 * sharp) | needs_net) & ~all_sharp
        mask = torch.zeros((1, 1, height, width), device=bokeh_up.device, dtype=bokeh_up.dtype)
        image, d_full = scene.image, scene.disparity_full_tensor()
        halo = self.fusion_net.halo

        def sharpen(y0: int, y1: int, x0: int, x1: int, m: Tensor | float) -> None:
            """Put the photo back into ``bokeh_up`` with weight ``m`` over one region."""
            region, photo = bokeh_up[..., y0:y1, x0:x1], image[..., y0:y1, x0:x1]
            if behind is None:
                mask[..., y0:y1, x0:x1] = m
                if isinstance(m, float):  # m = 1: the photo itself
                    region.copy_(photo)
                else:
                    region.copy_(torch.lerp(region, photo, m))
                return
            m = behind[0][..., y0:y1, x0:x1] * m
            mask[..., y0:y1, x0:x1] = m
            region.addcmul_(m, photo - behind[1][..., y0:y1, x0:x1])

        for row in range(lo.shape[0]):
            y0, y1 = row * t, min(height, (row + 1) * t)
            for c in torch.nonzero(all_sharp[row]).flatten().tolist():
                sharpen(y0, y1, c * t, min(width, (c + 1) * t), 1.0)
            for c0, c1 in _runs(torch.nonzero(needs_pixels[row]).flatten().tolist()):
                x0, x1 = c0 * t, min(width, (c1 + 1) * t)
                use_net = bool(needs_net[row, c0 : c1 + 1].any())
                pad = halo if use_net else 0
                ya, yb = max(0, y0 - pad), min(height, y1 + pad)
                xa, xb = max(0, x0 - pad), min(width, x1 + pad)
                coc = blur * (d_full[..., ya:yb, xa:xb] - focus).abs()  # [1,1,h',w']
                m = ((2.0 * sharp - coc) / sharp).clamp_(0, 1)
                if use_net:
                    defocus = coc_to_defocus(coc * lr_ratio)
                    m_s = self.fusion_net(
                        (1.0 - defocus).contiguous(memory_format=torch.channels_last),
                        rgb_to_gray(image[..., ya:yb, xa:xb]).contiguous(
                            memory_format=torch.channels_last
                        ),
                    )
                    m_s = m_s * (defocus < cfg.fusion_gate).to(m_s.dtype)
                    m = torch.maximum(m, m_s)
                sharpen(y0, y1, x0, x1, m[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa])
        return bokeh_up, mask

    # ---------------------------------------------------------------- inference

    def pass_size(self, size: tuple[int, int], given: bool = False) -> tuple[int, int]:
        """``(h, w)`` of the rendering pass for a photo of ``size``: with a ``given`` map the
        photo's own size up to ``config.full_pass_side``, else ``render_scale`` of it
        capped at ``max_render_side``."""
        if given and max(size) <= self.config.full_pass_side:
            return tuple(size)
        return scaled_size(size, self.config.render_scale, self.config.max_render_side)

    @torch.no_grad()
    def prepare(
        self, image: Any, disparity: Any = None, *, depth: Any = None, refine: bool = True
    ) -> Scene:
        """Run the networks once for a photo and cache what :meth:`render` needs.

        Args:
            image: ``H x W x 3`` numpy (uint8, or float32 in [0, 1]), a ``[1, 3, H, W]``
                tensor in [0, 1], or a :class:`d2f_core.io.Photo` (whose phone depth the
                ``"embedded"`` source reads).
            depth: where the disparity comes from (:mod:`d2f_core.depth.sources`): ``None``
                or ``"d2f"`` (this model's defocus network), ``"embedded"``, ``"file:PATH"``,
                ``"transformers:MODEL"``, a :class:`~d2f_core.depth.sources.DepthMap`, or a
                ready ``H' x W'`` map in [0, 1] (1 = nearest) of any size, resized to the
                photo.
            disparity: a ready map, as ``depth`` (its older name).
            refine: edge-aware refinement (:meth:`refine_disparity`) of the map at the
                rendering pass's size, the same for every source (and the network's own
                snapping, ``config.refine``); ``False`` keeps the map as the source gave it.

        Returns:
            A :class:`Scene` on the model's device; ``scene.disparity_source`` names the
            source (``"given"`` for a bare map).
        """
        if disparity is not None and depth is not None:
            raise ValueError("pass the map as depth or as disparity, not both")
        depth = disparity if depth is None else depth
        photo = None
        if isinstance(image, Photo):
            photo, image = image, image.image
        device = self.device
        image_t = rendering.image_tensor(image).to(device)  # [1,3,H,W]
        source, output = depth_sources.DEFAULT_SOURCE, "D2F network disparity"
        if isinstance(depth, (str, depth_sources.DepthSource)):
            spec = depth_sources.parse_source(depth)
            if spec.kind == "d2f":
                depth = None
            else:
                depth = depth_sources.depth_map(spec, image_t, photo=photo, device=device)
        if isinstance(depth, depth_sources.DepthMap):
            source, output, depth = depth.source, depth.output, depth.disparity
        elif depth is not None:
            source, output = "given", "disparity map"
        given = None if depth is None else rendering.disparity_tensor(depth).to(device)
        size = (int(image_t.shape[-2]), int(image_t.shape[-1]))
        lr_size = self.pass_size(size, given=given is not None)
        image_lr = resize(image_t, lr_size).clamp_(0, 1)  # [1,3,h,w]
        if given is None:
            disparity_lr = self.predict_disparity(image_lr, refine=refine)  # [1,1,h,w]
        else:
            disparity_lr = resize(given, lr_size).clamp_(0, 1)
        if refine:
            disparity_lr = self.refine_disparity(image_lr, disparity_lr)
        radiance_lr = self.radiance_net(image_lr)  # [1,1,h,w]
        return Scene(
            image=image_t,
            image_lr=image_lr,
            disparity_lr=disparity_lr,
            radiance_lr=radiance_lr,
            size=size,
            disparity_source=source,
            disparity_output=output,
            refined=bool(refine),
            given_disparity=given,
        )

    def _preview_inputs(self, scene: Scene, max_side: int) -> tuple[Tensor, Tensor, Tensor]:
        size = scaled_size(scene.size, 1.0, max_side)
        key = ("preview", size)
        if key not in scene.cache:
            lr_size = tuple(scene.image_lr.shape[-2:])
            src = scene.image_lr if size[0] <= lr_size[0] else scene.image
            scene.cache[key] = (
                resize(src, size).clamp(0, 1),
                resize(scene.disparity_lr, size).clamp(0, 1),
                resize(scene.radiance_lr, size),
            )
        return scene.cache[key]

    @torch.no_grad()
    def render(
        self,
        scene: Scene,
        focus: float = 0.5,
        blur: float = 40.0,
        fusion: bool = True,
        max_side: int | None = None,
        budget: str | float | None = adaptive.DEFAULT_QUALITY,
        **render_options: Any,
    ) -> Result:
        """Refocus a prepared photo.

        Args:
            scene: from :meth:`prepare`.
            focus: focal disparity in [0, 1] (1 = nearest); see :meth:`focus_at`.
            blur: ``K``, CoC diameter in px at FULL resolution for ``|d - focus| = 1``.
            fusion: apply deep Poisson fusion at full resolution (else plain upsampling; a
                pass at the photo's own size needs none and has none).
            max_side: preview mode: render at this long side, no fusion.
            budget: error budget of the adaptive settings (:mod:`d2f_core.rendering.adaptive`):
                ``"high"``, ``"balanced"`` or ``"fast"`` (45, 40, 30 dB against the exact
                renderer), or a PSNR in dB. The layer count and reduced-resolution preset are
                picked per focus and blur; when every CoC is under a pixel the input is
                returned without rendering (identity path), and fusion is skipped when no
                pixel is near enough to the focal plane to be fused. ``None``, an explicit
                ``num_layers`` or ``quality``, or ``order="paper"`` fix the settings.
            **render_options: passed to ``rendering.render`` (``order``, ``num_layers``,
                ``schedule``, ``kernel``, ``blades``, ``rotation``, ``highlight_boost``,
                ``quality``, ``method``).

        Returns:
            :class:`Result`; ``result.settings`` says what was picked.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        focus, blur = rendering.check_focus_blur(focus, blur)
        if max_side is not None and (isinstance(max_side, bool) or int(max_side) < 1):
            raise ValueError(f"max_side must be a positive integer or None, got {max_side!r}")
        if "radiance" in render_options:
            raise ValueError("render_options must not contain 'radiance' (it comes from scene)")
        if "checked" in render_options:
            raise ValueError("render_options must not contain 'checked' (D2F.render sets it)")
        render_options.setdefault("order", self.config.order)
        render_options.setdefault("placement", self.config.placement)
        named = isinstance(budget, str)
        if named and budget not in adaptive.BUDGETS:
            names = sorted(adaptive.BUDGETS)
            raise ValueError(f"budget must be one of {names}, a dB value or None, got {budget!r}")
        if budget is not None and not named:
            bad = f"budget must be a name, a dB value or None, got {budget!r}"
            if isinstance(budget, bool):
                raise ValueError(bad)
            try:
                budget = float(budget)
            except (TypeError, ValueError):
                raise ValueError(bad) from None
            if not math.isfinite(budget):
                raise ValueError(f"budget must be finite, got {budget}")
        pick = (
            budget is not None
            and render_options["order"] == "depth"
            and "num_layers" not in render_options
            and "quality" not in render_options
        )
        timings: dict[str, float] = {}
        t_all = time.perf_counter()

        # 1. inputs of the rendering pass (preview: its own size, cached per size)
        if max_side is not None:
            image_lr, disparity_lr, radiance_lr = self._preview_inputs(scene, int(max_side))
        else:
            image_lr, disparity_lr, radiance_lr = (
                scene.image_lr,
                scene.disparity_lr,
                scene.radiance_lr,
            )
        lr_size = (int(image_lr.shape[-2]), int(image_lr.shape[-1]))
        lr_ratio = size_ratio(lr_size, scene.size)
        blur_lr = blur * lr_ratio
        # full-res CoC under which the fusion gate can open (see _fuse_tiled)
        gate_coc = defocus_to_coc(self.config.fusion_gate) / lr_ratio * 1.01

        # 2. adaptive settings, then layered rendering at low resolution (HDR boost inside)
        settings = None
        if pick:
            t0 = time.perf_counter()
            full = max_side is None
            settings = adaptive.choose_settings(
                disparity_lr,
                focus,
                blur_lr,
                budget_db=None if named else budget,
                quality=budget if named else adaptive.DEFAULT_QUALITY,
                schedule=render_options.get("schedule", "growing"),
                placement=render_options["placement"],
                full_scale=1.0 / lr_ratio if full else 1.0,
                fusion_coc=gate_coc,
                checked=True,  # focus and blur were checked above; blur_lr <= blur
            )
            if full:
                # decide from the full-resolution map (a given map can hold finer extremes
                # than its low-res copy): identity when every output CoC is under a pixel,
                # fusion when some pixel is near enough to focus for _fuse_tiled to touch it
                lo, hi = scene.disparity_tile_range(_FUSION_TILE)
                far = float(torch.maximum((hi - focus).abs(), (lo - focus).abs()).max())
                near = float(torch.clamp(torch.maximum(lo - focus, focus - hi), min=0.0).min())
                settings.identity = blur * far < 1.0
                settings.fusion = blur * near < max(gate_coc, 2.0 * self.config.sharp_coc)
            timings["pick"] = _ms(t0)
        t0 = time.perf_counter()
        fuse = (
            fusion
            and max_side is None
            and lr_size != tuple(scene.size)  # a full-size pass lost no detail to restore
            and not (settings is not None and settings.identity)
            and (settings is None or settings.fusion)
        )
        behind_lr = None
        if settings is not None and settings.identity:
            bokeh_lr = image_lr  # every CoC is under a pixel of the output
        else:
            options = render_options | (settings.render_options() if settings else {})
            bokeh_lr = rendering.render(
                image_lr,
                disparity_lr,
                focus,
                blur_lr,
                radiance=radiance_lr,
                behind=fuse,
                # foreground layers blurred past the fusion gate: fusion never sharpens
                # them, and must not paste what lies behind them over their blur
                front_size=defocus_to_coc(self.config.fusion_gate),
                checked=True,
                **options,
            )  # [1,3,h,w]
            if fuse:
                # what the layers behind the blurred foreground make of each pixel: fusion
                # sharpens only that part
                bokeh_lr, share_lr, colour_lr = bokeh_lr
                if bool((share_lr < 1.0 - 1e-4).any()):
                    behind_lr = (share_lr, colour_lr)
        timings["render_lr"] = _ms(t0)
        defocus_lr = coc_to_defocus(blur_lr * (disparity_lr - focus).abs())

        # 3. upsample + deep Poisson fusion at full resolution
        if max_side is not None:
            bokeh = bokeh_lr
            mask = torch.zeros_like(disparity_lr)
        elif settings is not None and settings.identity:
            bokeh = scene.image.clone()
            mask = torch.ones((1, 1, *scene.size), device=bokeh.device)
        else:
            t0 = time.perf_counter()
            bokeh = resize(bokeh_lr, scene.size)  # [1,3,H,W]
            if bokeh is bokeh_lr:
                bokeh = bokeh.clone()  # fusion writes into it; bokeh_lr is returned too
            timings["upsample"] = _ms(t0)
            if fuse:
                t0 = time.perf_counter()
                behind = None
                if behind_lr is not None:
                    behind = tuple(resize(t, scene.size).clamp_(0, 1) for t in behind_lr)
                bokeh, mask = self._fuse_tiled(scene, bokeh, focus, blur, lr_ratio, behind)
                timings["fusion"] = _ms(t0)
            else:
                mask = torch.zeros((1, 1, *scene.size), device=bokeh.device)

        t0 = time.perf_counter()
        result = Result(
            bokeh=_to_numpy_image(bokeh.clamp_(0, 1)),
            bokeh_lr=_to_numpy_image(bokeh_lr),
            disparity=disparity_lr[0, 0].cpu().numpy(),
            defocus=defocus_lr[0, 0].cpu().numpy(),
            fusion_mask=mask[0, 0].cpu().numpy(),
            timings=timings,
            settings=settings,
        )
        timings["to_numpy"] = _ms(t0)
        timings["total"] = _ms(t_all)
        return result

    def focus_at(self, scene: Scene, x: float, y: float, radius: int | None = None) -> float:
        """Median disparity in a ``(2r+1)^2`` window around full-res pixel ``(x, y)``.

        ``(x, y)`` is clamped into the photo; the window is clipped at its borders.
        ``radius`` defaults to ``max(2, round(max(H, W) / 200))`` px.

        Returns:
            Focal disparity in [0, 1] for :meth:`render`.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        try:
            xf, yf = float(x), float(y)
        except (TypeError, ValueError):
            raise InputTypeError(f"x and y must be numbers, got {x!r}, {y!r}") from None
        if not (math.isfinite(xf) and math.isfinite(yf)):
            raise ValueError(f"x and y must be finite, got {x!r}, {y!r}")
        height, width = scene.size
        r = max(2, round(max(height, width) / 200)) if radius is None else int(radius)
        if r < 0:
            raise ValueError(f"radius must be >= 0, got {radius!r}")
        xi = min(max(round(xf), 0), width - 1)
        yi = min(max(round(yf), 0), height - 1)
        d = scene.disparity_full_tensor()[0, 0]
        window = d[max(0, yi - r) : yi + r + 1, max(0, xi - r) : xi + r + 1]
        return float(np.clip(np.median(window.detach().cpu().numpy()), 0.0, 1.0))

    def subject_focus(self, scene: Scene) -> tuple[float, tuple[float, float]]:
        """The focal disparity of the subject the disparity map shows, and where it is
        (:func:`find_subject`); a map in which nothing stands out (flat, or a plain ramp) gets
        the focus at the centre, as :meth:`focus_at`.

        Returns:
            ``(focus, (x, y))``, the point in full-res pixel coordinates.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        with torch.no_grad():
            d = resize(scene.disparity_lr, scaled_size(scene.size, 1.0, 128))[0, 0]
        return locate_subject(d.cpu().numpy(), scene.size, lambda x, y: self.focus_at(scene, x, y))

    # ---------------------------------------------------------------- training forwards

    def _render_batch(
        self,
        image: Tensor,
        disparity: Tensor,
        focus: Tensor,
        blur: Tensor,
        radiance: Tensor,
        **options: Any,
    ) -> Tensor:
        # rendering.render takes one blur per call; group samples that share it
        blur_list = [float(v) for v in blur.reshape(-1)]
        focus = focus.reshape(-1)
        if all(v == blur_list[0] for v in blur_list):
            return rendering.render(
                image, disparity, focus, blur_list[0], radiance=radiance, **options
            )
        outs = [
            rendering.render(
                image[i : i + 1],
                disparity[i : i + 1],
                focus[i : i + 1],
                blur_list[i],
                radiance=radiance[i : i + 1],
                **options,
            )
            for i in range(image.shape[0])
        ]
        return torch.cat(outs, dim=0)

    def forward_stage1(
        self, image_lr: Tensor, focus: float | Tensor, blur_lr: float | Tensor, **options: Any
    ) -> dict[str, Tensor]:
        """Differentiable low-resolution bokeh (training stage 1).

        Args:
            image_lr: ``(B, 3, h, w)`` in [0, 1]; the defocus network runs at this size.
            focus: focal disparity, float or ``[B]`` in [0, 1].
            blur_lr: ``K`` in px at this resolution, float or ``[B]``.
            **options: passed to ``rendering.render``.

        Returns:
            ``{"bokeh_lr": (B,3,h,w), "disparity": (B,1,h,w), "radiance": (B,1,h,w)}``.
        """
        b = image_lr.shape[0]
        options.setdefault("order", self.config.order)
        options.setdefault("placement", self.config.placement)
        disparity = self.defocus_net(image_lr)  # [B,1,h,w]
        radiance = self.radiance_net(image_lr)  # [B,1,h,w]
        f = _per_sample(focus, b, image_lr).reshape(-1)
        k = _per_sample(blur_lr, b, image_lr).reshape(-1)
        bokeh = self._render_batch(image_lr, disparity, f, k, radiance, **options)
        return {"bokeh_lr": bokeh, "disparity": disparity, "radiance": radiance}

    def forward_stage2(
        self, image: Tensor, focus: float | Tensor, blur: float | Tensor, **options: Any
    ) -> dict[str, Tensor]:
        """Full-resolution fused bokeh (training stage 2; gradients reach ``f_p`` only).

        Args:
            image: ``I_hr``, ``(B, 3, H, W)`` in [0, 1].
            focus: focal disparity, float or ``[B]``.
            blur: ``K`` in px at full resolution, float or ``[B]``.

        Returns:
            dict with ``bokeh`` (B,3,H,W) = fused ``B_hr``, ``bokeh_up`` (B,3,H,W),
            ``bokeh_lr`` (B,3,h,w), ``disparity_lr`` (B,1,h,w), ``disparity`` (B,1,H,W),
            ``defocus`` (B,1,H,W) paper-normalised, ``mask`` and ``mask_soft`` (B,1,H,W).
        """
        b = image.shape[0]
        size = (int(image.shape[-2]), int(image.shape[-1]))
        lr_size = scaled_size(size, self.config.render_scale, None)
        lr_ratio = size_ratio(lr_size, size)
        k = _per_sample(blur, b, image)
        f = _per_sample(focus, b, image)
        frozen = (self.defocus_net, self.radiance_net)
        modes = [m.training for m in frozen]
        with torch.no_grad():
            # the stage-1 networks are frozen here: batch statistics must not move
            for m in frozen:
                m.eval()
            image_lr = resize(image, lr_size).clamp(0, 1)
            low = self.forward_stage1(
                image_lr, f.reshape(-1), (k * lr_ratio).reshape(-1), **options
            )
            bokeh_up = resize(low["bokeh_lr"], size)  # [B,3,H,W]
            disparity = resize(low["disparity"], size).clamp(0, 1)  # [B,1,H,W]
            for m, mode in zip(frozen, modes, strict=True):
                m.train(mode)
        mask, mask_soft = self.fusion_mask(image, disparity, f, k, lr_ratio)
        bokeh = torch.lerp(bokeh_up, image, mask)
        defocus = coc_to_defocus(k * lr_ratio * (disparity - f).abs())
        return {
            "bokeh": bokeh,
            "bokeh_up": bokeh_up,
            "bokeh_lr": low["bokeh_lr"],
            "disparity_lr": low["disparity"],
            "disparity": disparity,
            "defocus": defocus,
            "mask": mask,
            "mask_soft": mask_soft,
        }


def find_subject(
    disparity: np.ndarray, min_prominence: float = 0.02
) -> tuple[float, tuple[float, float]] | None:
    """Where the subject of a disparity map is, and its focal disparity.

    A subject is what stands out nearer than the rest of its rows: the map minus each row's
    30th percentile (a floor or a wall sloping away in depth stands out from nothing), box
    smoothed over a fortieth of the frame and weighted by a broad centre prior. The
    subject's pixels are those within half the strongest score; the focus is their
    score-weighted median disparity and the point is the strongest of them.

    Args:
        disparity: ``H x W`` in [0, 1], 1 = nearest (any size; 128 px is plenty).
        min_prominence: below this strongest score nothing stands out.

    Returns:
        ``(focus, (x, y))`` with ``x, y`` as fractions of the width and height (pixel
        centres), or ``None`` when nothing stands out.
    """
    d = np.asarray(disparity, dtype=np.float64)
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"disparity must be a non-empty H x W map, got shape {d.shape}")
    h, w = d.shape
    prominence = d - np.percentile(d, 30, axis=1, keepdims=True)
    k = max(1, round(max(h, w) / 40))
    n = 2 * k + 1
    cs = np.pad(np.pad(prominence, k, mode="edge").cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    smooth = (cs[n:, n:] - cs[:-n, n:] - cs[n:, :-n] + cs[:-n, :-n]) / (n * n)
    yy, xx = np.mgrid[0:h, 0:w]
    centre = np.exp(-(((yy + 0.5) / h - 0.5) ** 2 + ((xx + 0.5) / w - 0.5) ** 2) / 0.18)
    score = np.clip(smooth, 0, None) * centre
    top = float(score.max())
    if not top >= min_prominence:
        return None
    region = score >= 0.5 * top
    values, weights = d[region], score[region]
    order = np.argsort(values, kind="stable")
    cum = np.cumsum(weights[order])
    focus = float(values[order][np.searchsorted(cum, 0.5 * cum[-1])])
    iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
    return float(np.clip(focus, 0.0, 1.0)), ((ix + 0.5) / w, (iy + 0.5) / h)


def locate_subject(
    disparity: np.ndarray, size: tuple[int, int], focus_at: Callable[[float, float], float]
) -> tuple[float, tuple[float, float]]:
    """:func:`find_subject` on a small ``disparity`` map of a photo of ``size`` = ``(H, W)``,
    the point in that photo's pixels; where nothing stands out, the centre and
    ``focus_at(x, y)`` there.

    Returns:
        ``(focus, (x, y))``.
    """
    height, width = size
    found = find_subject(disparity)
    if found is None:
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        return focus_at(cx, cy), (cx, cy)
    focus, (fx, fy) = found
    return focus, (fx * width - 0.5, fy * height - 0.5)


def _runs(columns: list[int]) -> list[tuple[int, int]]:
    """Merge sorted column indices into inclusive runs: [1, 2, 3, 7] -> [(1, 3), (7, 7)]."""
    runs: list[list[int]] = []
    for c in columns:
        if runs and c == runs[-1][1] + 1:
            runs[-1][1] = c
        else:
            runs.append([c, c])
    return [(a, b) for a, b in runs]
