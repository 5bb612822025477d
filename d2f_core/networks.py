"""The three learned networks of D2F: defocus ``f_d``, radiance ``f_r`` and fusion ``f_p``.

Architectures are picked by name from the registry dicts :data:`DEFOCUS_NETS`,
:data:`RADIANCE_NETS` and :data:`FUSION_NETS`. Nothing here reads files except
:meth:`DefocusNet.load_imagenet`, which takes an explicit local path; nothing downloads.

- :class:`DefocusNet` is a MiDaS-style encoder-decoder (encoder, four feature-fusion refine
  blocks built from residual conv units, output head). Its output goes through a sigmoid,
  so it is disparity-like in [0, 1] with 1 = nearest. The paper learns it without depth
  supervision, only through the bokeh loss.
- :class:`RadianceNet` is the authors' per-pixel network (1x1 convs 3->16->16->1, sigmoid).
- :class:`FusionNet` predicts the soft sharp-region mask ``M_s`` from ``(1 - defocus, gray)``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .encoders import LiteEncoder, ResNeXt50Encoder
from .errors import InputTypeError
from .torch_files import (  # noqa: F401  (re-exported: loaders import them from here)
    load_local_state_dict,
    optimizer_state_on_cpu,
    read_torch_file,
)

__all__ = [
    "DEFOCUS_NETS",
    "FUSION_NETS",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "RADIANCE_NETS",
    "SCENE_MAPS",
    "DefocusNet",
    "FusionNet",
    "RadianceNet",
    "ResNeXt50Encoder",
    "LiteEncoder",
    "build_defocus_net",
    "build_fusion_net",
    "build_radiance_net",
    "count_parameters",
    "rgb_to_gray",
]

logger = logging.getLogger(__name__)

#: the ImageNet normalisation (RGB mean and standard deviation) of pretrained encoders
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def count_parameters(module: nn.Module, trainable_only: bool = False) -> int:
    """Number of parameters of ``module`` (all, or only those with ``requires_grad``)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)


def rgb_to_gray(image: Tensor) -> Tensor:
    """ITU-R BT.601 luma of an RGB image.

    Shape: (B, 3, H, W) in [0, 1] -> (B, 1, H, W) in [0, 1].
    """
    if image.ndim != 4 or image.shape[1] != 3:
        raise ValueError(f"image must have shape [B,3,H,W], got {tuple(image.shape)}")
    r, g, b = image[:, 0:1], image[:, 1:2], image[:, 2:3]
    return 0.299 * r + 0.587 * g + 0.114 * b


def _check_image(image: Tensor, name: str = "image") -> None:
    if not isinstance(image, Tensor):
        raise InputTypeError(f"{name} must be a torch.Tensor, got {type(image).__name__}")
    if image.ndim != 4 or image.shape[1] != 3:
        raise ValueError(f"{name} must have shape [B,3,H,W], got {tuple(image.shape)}")


# --------------------------------------------------------------------------------------
# MiDaS-style decoder.
# --------------------------------------------------------------------------------------


def _conv3x3(cin: int, cout: int, separable: bool, bias: bool = True) -> nn.Module:
    if not separable:
        return nn.Conv2d(cin, cout, 3, 1, 1, bias=bias)
    return nn.Sequential(
        nn.Conv2d(cin, cin, 3, 1, 1, groups=cin, bias=False), nn.Conv2d(cin, cout, 1, bias=bias)
    )


class _ResidualConvUnit(nn.Module):
    """Pre-activation residual unit of RefineNet/MiDaS: x + conv(relu(conv(relu(x))))."""

    def __init__(self, features: int, separable: bool) -> None:
        super().__init__()
        self.conv1 = _conv3x3(features, features, separable)
        self.conv2 = _conv3x3(features, features, separable)

    def forward(self, x: Tensor) -> Tensor:
        y = self.conv1(F.relu(x))
        y = self.conv2(F.relu(y))
        return x + y


class _FeatureFusionBlock(nn.Module):
    """Adds the refined skip feature, refines again, upsamples x2 (MiDaS FeatureFusionBlock)."""

    def __init__(self, features: int, separable: bool, has_skip: bool) -> None:
        super().__init__()
        self.skip_unit = _ResidualConvUnit(features, separable) if has_skip else None
        self.out_unit = _ResidualConvUnit(features, separable)

    def forward(self, x: Tensor, skip: Tensor | None = None) -> Tensor:
        if skip is not None and self.skip_unit is not None:
            if skip.shape[-2:] != x.shape[-2:]:
                x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = x + self.skip_unit(skip)
        x = self.out_unit(x)
        return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=True)


class GlobalContext(nn.Module):
    """Whole-image context for the deepest feature map (a pyramid pooling module).

    The map is average-pooled to 1x1, 2x2 and 4x4 cells; each pooled map, with the cells'
    vertical and horizontal positions in the frame (0 at the top / left, 1 at the bottom /
    right), goes through a 1x1 convolution and is upsampled back; the sum is added to the
    input. A 3x3 kernel at stride 32 sees a few hundred pixels, so without this the network
    cannot relate a region to the layout of the whole frame (a far arch at the end of a
    tunnel looks like a near subject up close). The output convolution starts at zero, so a
    network grown from one without this module computes the same map until it is trained.

    Shape: (B, C, h, w) -> (B, C, h, w).
    """

    grids = (1, 2, 4)

    def __init__(self, channels: int, hidden: int = 64) -> None:
        super().__init__()
        self.branches = nn.ModuleList(
            nn.Sequential(nn.Conv2d(channels + 2, hidden, 1), nn.ReLU(inplace=True))
            for _ in self.grids
        )
        self.out = nn.Conv2d(hidden * len(self.grids), channels, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    @staticmethod
    def _positions(x: Tensor) -> Tensor:
        b, _, h, w = x.shape
        ys = (torch.arange(h, dtype=x.dtype, device=x.device) + 0.5) / h
        xs = (torch.arange(w, dtype=x.dtype, device=x.device) + 0.5) / w
        yy = ys.view(1, 1, h, 1).expand(b, 1, h, w)
        xx = xs.view(1, 1, 1, w).expand(b, 1, h, w)
        return torch.cat([yy, xx], dim=1)

    def forward(self, x: Tensor, valid: tuple[int, int] | None = None) -> Tensor:
        """``valid``: the ``(h, w)`` of the map that is image, not padding (pooling and
        positions use only that part)."""
        h, w = x.shape[-2:]
        vh, vw = valid if valid is not None else (h, w)
        core = x[..., :vh, :vw]
        outs = []
        for grid, branch in zip(self.grids, self.branches, strict=True):
            pooled = F.adaptive_avg_pool2d(core, (min(grid, vh), min(grid, vw)))
            y = branch(torch.cat([pooled, self._positions(pooled)], dim=1))
            outs.append(F.interpolate(y, size=(vh, vw), mode="bilinear", align_corners=False))
        delta = self.out(torch.cat(outs, dim=1))
        if (vh, vw) != (h, w):
            delta = F.pad(delta, (0, w - vw, 0, h - vh), mode="replicate")
        return x + delta


#: each lite defocus variant: its encoder's expansion (one for all stages, or one per stage)
#: and its context module's hidden channels (None: no context module)
LITE_VARIANTS: dict[str, tuple[int | tuple[int, ...], int | None]] = {
    "lite": (4, None),
    "lite-ctx": (4, 64),
    "lite-wide": ((4, 4, 8, 8), 128),
    "lite-xl": ((6, 8, 12, 16), 192),
}


class DefocusNet(nn.Module):
    """Monocular disparity network ``f_d`` (encoder + 4 refine blocks + head, sigmoid).

    Args:
        variant: ``"resnext50"`` (paper: ResNeXt50 32x4d encoder, 256 decoder features),
            ``"lite"`` (MobileNetV2-like encoder, separable decoder; about 1.1 M parameters),
            ``"lite-ctx"`` (``"lite"`` with :class:`GlobalContext` on its deepest map),
            ``"lite-wide"`` (``"lite-ctx"`` with twice the expansion in the encoder's two
            deepest stages and twice the context's hidden channels; about 2.2 M parameters,
            1.15x the time) or ``"lite-xl"`` (expansions 6, 8, 12 and 16 from the shallowest
            stage to the deepest and three times the context's hidden channels; about 4.0 M
            parameters, 1.4x the time at 512x768). A smaller lite network's state dict loads
            into a larger one with :meth:`load_lite`, which then computes the same map.
        scene_maps: channels of a second head on the decoder's features, the logits of
            :data:`SCENE_MAPS` (:meth:`forward_scene`; ``"lite-ctx-scene"`` has it), which a
            smaller lite network's state dict leaves at its initialisation.

    The input is an RGB image in [0, 1]; ImageNet normalisation happens inside. Any input
    size works: the image is padded to a multiple of 32 and the output cropped back.

    Shape: (B, 3, H, W) in [0, 1] -> (B, 1, H, W) in [0, 1], 1 = nearest.
    """

    def __init__(self, variant: str = "lite", scene_maps: int = 0) -> None:
        super().__init__()
        context_hidden = None
        if scene_maps and variant == "resnext50":
            raise ValueError("scene maps are a head of the lite variants")
        if variant == "resnext50":
            self.encoder: nn.Module = ResNeXt50Encoder()
            features, separable = 256, False
        elif variant in LITE_VARIANTS:
            expand, context_hidden = LITE_VARIANTS[variant]
            self.encoder = LiteEncoder(expand)
            features, separable = 64, True
        else:
            raise ValueError(
                f"variant must be 'resnext50', 'lite', 'lite-ctx', 'lite-wide' or 'lite-xl', "
                f"got {variant!r}"
            )
        self.variant = variant
        channels = self.encoder.channels
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        self.project = nn.ModuleList(_conv3x3(c, features, separable, bias=False) for c in channels)
        self.context = None if context_hidden is None else GlobalContext(features, context_hidden)
        self.refine = nn.ModuleList(
            _FeatureFusionBlock(features, separable, has_skip=i < 3) for i in range(4)
        )
        if variant == "resnext50":
            # MiDaS head: conv, x2 upsample to full resolution, conv, relu, 1x1.
            self.head = nn.Sequential(
                nn.Conv2d(features, features // 2, 3, 1, 1),
                nn.Upsample(scale_factor=2.0, mode="bilinear", align_corners=True),
                nn.Conv2d(features // 2, 32, 3, 1, 1),
                nn.ReLU(inplace=True),
                nn.Conv2d(32, 1, 1),
            )
        else:
            # The lite head stays at stride 2 and upsamples the single logit channel:
            # full-resolution 3x3 convs would cost more than the whole encoder.
            self.head = nn.Sequential(
                _conv3x3(features, 32, separable=True),
                nn.ReLU(inplace=True),
                nn.Conv2d(32, 1, 1),
                nn.Upsample(scale_factor=2.0, mode="bilinear", align_corners=True),
            )
        # the scene maps' logits (:data:`SCENE_MAPS`), from the same decoder features
        self.scene_head = None
        if scene_maps:
            self.scene_head = nn.Sequential(
                _conv3x3(features, 32, separable=True),
                nn.ReLU(inplace=True),
                nn.Conv2d(32, scene_maps, 1),
                nn.Upsample(scale_factor=2.0, mode="bilinear", align_corners=True),
            )

    def forward(self, image: Tensor) -> Tensor:
        y, (h, w) = self._decode(image)
        return torch.sigmoid(self.head(y)[..., :h, :w])

    def forward_scene(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """The disparity and the scene maps' logits (one channel per :data:`SCENE_MAPS`).

        Shape: (B, 3, H, W) -> (B, 1, H, W) in [0, 1] and (B, len(SCENE_MAPS), H, W).

        Raises:
            ValueError: the network has no scene head (a variant without ``-scene``).
        """
        if self.scene_head is None:
            raise ValueError(f"the {self.variant!r} defocus network has no scene maps")
        y, (h, w) = self._decode(image)
        return torch.sigmoid(self.head(y)[..., :h, :w]), self.scene_head(y)[..., :h, :w]

    def _decode(self, image: Tensor) -> tuple[Tensor, tuple[int, int]]:
        """The last refine block's features (stride 2, padded to a multiple of 32) and the
        input's ``(H, W)``."""
        _check_image(image)
        h, w = image.shape[-2:]
        ph, pw = (-h) % 32, (-w) % 32
        x = (image - self.mean) / self.std  # [B,3,H,W]
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        feats = self.encoder(x)
        f1, f2, f3, f4 = (proj(f) for proj, f in zip(self.project, feats, strict=True))
        if self.context is not None:
            f4 = self.context(f4, (-(-h // 32), -(-w // 32)))
        y = self.refine[3](f4)  # [B,F,H/16,W/16]
        y = self.refine[2](y, f3)  # [B,F,H/8,W/8]
        y = self.refine[1](y, f2)  # [B,F,H/4,W/4]
        y = self.refine[0](y, f1)  # [B,F,H/2,W/2]
        return y, (h, w)

    def load_lite(self, state: Mapping[str, Tensor]) -> None:
        """Load a smaller lite network's state dict: ``"lite"`` into ``"lite-ctx"``, or
        ``"lite"`` / ``"lite-ctx"`` into ``"lite-wide"`` or ``"lite-xl"``. The larger network
        computes what the smaller one did: a missing context module keeps its zero output,
        and the extra hidden channels of a wider block or context keep their random input
        weights but get zero output weights (function-preserving widening, as in Net2Net). A
        state dict of the network's own variant loads as it is."""
        own = self.state_dict()
        unexpected = sorted(set(state) - set(own))
        missing = sorted(
            k for k in set(own) - set(state) if not k.startswith(("context.", "scene_head."))
        )
        if unexpected or missing:
            raise ValueError(
                f"not a 'lite' defocus state dict: missing {missing[:3]}, "
                f"unexpected {unexpected[:3]}"
            )
        grown = dict(own)
        for key, small in state.items():
            big = own[key]
            if small.shape == big.shape:
                grown[key] = small.clone()
                continue
            if small.dim() != big.dim() or any(a > b for a, b in zip(small.shape, big.shape)):
                raise ValueError(f"{key}: {tuple(small.shape)} does not fit {tuple(big.shape)}")
            value = big.clone()
            if key == "context.out.weight":
                # its input is the branches' outputs side by side: copy each branch's block
                value.zero_()
                h_small = small.shape[1] // len(GlobalContext.grids)
                h_big = big.shape[1] // len(GlobalContext.grids)
                for i in range(len(GlobalContext.grids)):
                    value[:, i * h_big : i * h_big + h_small] = small[
                        :, i * h_small : (i + 1) * h_small
                    ]
            elif key.endswith("block.6.weight"):
                # a block's projection: the new hidden channels start with no say
                value.zero_()
                value[:, : small.shape[1]] = small
            else:
                # expansion, depthwise and their batch norms: new channels keep their init
                value[tuple(slice(0, n) for n in small.shape)] = small
            grown[key] = value
        self.load_state_dict(grown)

    def load_imagenet(self, path: str | Path) -> None:
        """Load ImageNet weights into the ResNeXt50 encoder from a LOCAL state-dict file.

        Accepts torchvision's ``resnext50_32x4d`` state dict (optionally wrapped in
        ``{"state_dict": ...}`` / ``{"model": ...}`` and with ``module.``, ``encoder.`` or
        ``backbone.`` key prefixes); the classifier ``fc.*`` is ignored.

        Raises:
            FileNotFoundError: ``path`` does not exist.
            ValueError: the file is not a readable state dict, or its keys/shapes do not
                match a ResNeXt50 32x4d.
        """
        if self.variant != "resnext50":
            raise ValueError(f"load_imagenet needs variant 'resnext50', this is {self.variant!r}")
        state = load_local_state_dict(path, "ImageNet")
        mapped = {}
        for key, value in state.items():
            for prefix in ("module.", "encoder.", "backbone."):
                if key.startswith(prefix):
                    key = key[len(prefix) :]
            if key.startswith("fc.") or key.endswith("num_batches_tracked"):
                continue
            mapped[key] = value
        own = self.encoder.state_dict()
        own = {k: v for k, v in own.items() if not k.endswith("num_batches_tracked")}
        missing = sorted(set(own) - set(mapped))
        unexpected = sorted(set(mapped) - set(own))
        if missing or unexpected:
            raise ValueError(
                f"{path} is not a ResNeXt50 32x4d state dict: {len(missing)} missing keys "
                f"(e.g. {missing[:3]}), {len(unexpected)} unexpected keys (e.g. {unexpected[:3]})"
            )
        bad = [k for k, v in own.items() if tuple(mapped[k].shape) != tuple(v.shape)]
        if bad:
            raise ValueError(
                f"{path}: shape mismatch for {len(bad)} tensors, e.g. {bad[0]}: "
                f"{tuple(mapped[bad[0]].shape)} vs expected {tuple(own[bad[0]].shape)}"
            )
        self.encoder.load_state_dict(mapped, strict=False)
        logger.info("loaded ImageNet encoder weights from %s", path)


# --------------------------------------------------------------------------------------
# Radiance and fusion networks.
# --------------------------------------------------------------------------------------


class RadianceNet(nn.Module):
    """Radiance virtualisation ``f_r``: per-pixel 1x1 convs 3->16->16->1 and a sigmoid.

    Shape: (B, 3, H, W) in [0, 1] -> R0 (B, 1, H, W) in (0, 1).
    """

    def __init__(self, hidden: int = 16) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, hidden, 1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, hidden, 1),
            nn.ReLU(inplace=True),
            nn.Conv2d(hidden, 1, 1),
        )

    def forward(self, image: Tensor) -> Tensor:
        _check_image(image)
        return torch.sigmoid(self.net(image))


class FusionNet(nn.Module):
    """Deep Poisson fusion ``f_p``: soft sharp-region mask from focus prior and gray image.

    Args:
        variant: ``"paper"`` (conv3x3 2->64->16->16->1, about 12.8 k MAC per pixel) or
            ``"lite"`` (conv3x3 2->4->4, 1x1 4->1, 220 MAC per pixel: 58x cheaper, which
            matters at 12 MP; 4-wide layers also run about 2x faster per MAC on CPU than
            8-wide ones, measured with channels-last weights).

    Shape: focus (B, 1, H, W) = ``1 - defocus`` in [0, 1], gray (B, 1, H, W) in [0, 1]
    -> M_s (B, 1, H, W) in [0, 1] (1 = keep the sharp input).
    """

    #: How many pixels of context each output pixel sees, per side (stacked 3x3 convs).
    halo: int

    def __init__(self, variant: str = "lite") -> None:
        super().__init__()
        if variant == "paper":
            widths, last_k = (2, 64, 16, 16), 3
        elif variant == "lite":
            widths, last_k = (2, 4, 4), 1
        else:
            raise ValueError(f"variant must be 'paper' or 'lite', got {variant!r}")
        self.variant = variant
        layers: list[nn.Module] = []
        for cin, cout in zip(widths[:-1], widths[1:], strict=True):
            layers += [nn.Conv2d(cin, cout, 3, 1, 1), nn.ReLU(inplace=True)]
        layers.append(nn.Conv2d(widths[-1], 1, last_k, 1, last_k // 2))
        self.net = nn.Sequential(*layers)
        self.halo = (len(widths) - 1) + last_k // 2

    def forward(self, focus: Tensor, gray: Tensor) -> Tensor:
        if focus.ndim != 4 or focus.shape[1] != 1:
            raise ValueError(f"focus must have shape [B,1,H,W], got {tuple(focus.shape)}")
        if gray.shape != focus.shape:
            raise ValueError(
                f"gray must have the shape of focus {tuple(focus.shape)}, got {tuple(gray.shape)}"
            )
        return torch.sigmoid(self.net(torch.cat([focus, gray], dim=1)))


#: what the scene head of a ``"-scene"`` defocus variant predicts, one logit map each: the
#: subjects (every salient thing and near occluder that stands in front of the scene) and the
#: sky; :func:`d2f_core.depth.scene.stand_subjects` composes them with the disparity
SCENE_MAPS = ("subject", "sky")

DEFOCUS_NETS: dict[str, Callable[[], nn.Module]] = {
    "lite": lambda: DefocusNet("lite"),
    "lite-ctx": lambda: DefocusNet("lite-ctx"),
    "lite-wide": lambda: DefocusNet("lite-wide"),
    "lite-xl": lambda: DefocusNet("lite-xl"),
    "lite-ctx-scene": lambda: DefocusNet("lite-ctx", scene_maps=len(SCENE_MAPS)),
    "resnext50": lambda: DefocusNet("resnext50"),
}
RADIANCE_NETS: dict[str, Callable[[], nn.Module]] = {"paper": RadianceNet}
FUSION_NETS: dict[str, Callable[[], nn.Module]] = {
    "paper": lambda: FusionNet("paper"),
    "lite": lambda: FusionNet("lite"),
}


def _build(registry: Mapping[str, Callable[[], nn.Module]], name: str, what: str) -> nn.Module:
    if name not in registry:
        raise ValueError(f"unknown {what} variant {name!r}; choose one of {sorted(registry)}")
    return registry[name]()


def build_defocus_net(name: str = "lite") -> DefocusNet:
    """Defocus network from :data:`DEFOCUS_NETS` (``"lite"`` or ``"resnext50"``)."""
    return _build(DEFOCUS_NETS, name, "defocus")  # type: ignore[return-value]


def build_radiance_net(name: str = "paper") -> RadianceNet:
    """Radiance network from :data:`RADIANCE_NETS`."""
    return _build(RADIANCE_NETS, name, "radiance")  # type: ignore[return-value]


def build_fusion_net(name: str = "lite") -> FusionNet:
    """Fusion network from :data:`FUSION_NETS` (``"paper"`` or ``"lite"``)."""
    return _build(FUSION_NETS, name, "fusion")  # type: ignore[return-value]
