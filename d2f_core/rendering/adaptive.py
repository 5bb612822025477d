"""Adaptive render settings beside the plan: no more model than a scene needs (the layer count
``L`` of ``f_l`` and the reduced-resolution preset, per error budget).

:func:`choose_settings` looks at the disparity map, the focal plane and the requested blur
``K`` and picks the cheapest renderer settings whose expected error stays within a budget
(PSNR in dB against the exact reference of the same model: ``quality="exact"``,
``num_layers=15``, every other option unchanged):

* ``K * max|d - focus| < 1`` px: nothing is blurred, the input is the answer (identity path:
  no layers, no fusion).
* the layer count and the reduced-resolution preset (:data:`rendering.QUALITY_PRESETS`) come
  from a calibration table of worst-case PSNR per largest-CoC bin, measured on seeded
  generated scenes by ``d2f-bench accuracy --calibrate``. The renderer itself already skips
  empty layers and stops its kernel schedule at the scene's largest CoC, so a small ``K``
  needs few layers whatever is picked here.
* fusion (full-resolution sharpening of the in-focus region) is needed only if some pixel is
  close enough to the focal plane for the fusion gate to open.

:func:`render_adaptive` is :func:`rendering.render` with those settings.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F

from .api import render
from .blur import grid_factor
from .inputs import check_focus_blur
from .plan import layer_plan

__all__ = [
    "BLEND_CALIBRATION",
    "BUDGETS",
    "CALIBRATION",
    "CANDIDATES",
    "RenderSettings",
    "choose_settings",
    "coc_bin",
    "predicted_psnr",
    "render_adaptive",
]

#: User-facing quality/speed option -> PSNR budget (dB) against the exact reference.
BUDGETS: dict[str, float] = {"high": 45.0, "balanced": 40.0, "fast": 30.0}
DEFAULT_QUALITY = "balanced"

#: (num_layers, renderer quality preset) pairs the picker chooses from.
CANDIDATES: tuple[tuple[int, str], ...] = tuple(
    (layers, quality)
    for layers in (5, 7, 9, 11, 15)
    for quality in ("exact", "high", "balanced", "fast")
)

#: Upper edges (px) of the largest-CoC bins of :data:`CALIBRATION`; the last bin is open.
COC_BINS: tuple[float, ...] = (4.0, 8.0, 16.0, 32.0, 64.0, 128.0)

#: Worst-case PSNR (dB) against the exact 15-layer reference, per largest-CoC bin (one value
#: per bin of :data:`COC_BINS` plus the open bin; ``None`` = not measured), depth order, soft
#: disk, growing schedule, placement "nearest" or "paper". The minimum over these runs of
#: ``d2f-bench accuracy --calibrate`` (:func:`d2f_core.bench.accuracy.calibrate`; three focal
#: planes per scene, both placements):
#: ``--sizes 512x768 --seeds 207 208 --k-fracs 0.02 0.05 0.1 0.17``,
#: ``--sizes 256x384 --seeds 201 202 --k-fracs 0.005 0.01 0.03 0.3``,
#: ``--sizes 256x384 --seeds 201 202 203 --k-fracs 0.015 0.02 0.06 0.12`` and
#: ``--sizes 512x768 --seeds 209 --k-fracs 0.3`` and
#: ``--sizes 96x144 128x192 --seeds 211 212 213 214 --k-fracs 0.02 0.05 0.1 0.2 0.4`` and
#: ``--sizes 96x144 128x192 --seeds 211 212 213 214 --k-fracs 0.7 1.0 1.4`` (CoCs of 100-200 px
#: on a small frame: the open bin's worst cases).
#: Reduced resolution costs 41-53 dB; fewer layers cost far more (18-35 dB).
CALIBRATION: dict[tuple[int, str], tuple[float | None, ...]] = {
    (5, "exact"): (20.9, 18.2, 21.6, 22.2, 22.1, 25.0, 25.1),
    (5, "high"): (20.9, 18.2, 21.6, 22.2, 22.1, 25.0, 25.1),
    (5, "balanced"): (20.9, 18.2, 21.6, 22.2, 22.1, 25.0, 25.2),
    (5, "fast"): (20.9, 18.2, 21.6, 22.2, 22.1, 25.2, 25.2),
    (7, "exact"): (25.4, 27.2, 21.8, 25.3, 29.1, 27.4, 26.5),
    (7, "high"): (25.4, 27.2, 21.8, 25.3, 29.1, 27.4, 26.6),
    (7, "balanced"): (25.4, 27.2, 21.8, 25.3, 29.1, 27.4, 26.6),
    (7, "fast"): (25.4, 27.2, 21.8, 25.3, 29.0, 27.4, 26.8),
    (9, "exact"): (25.4, 28.6, 24.7, 26.2, 31.0, 32.5, 32.4),
    (9, "high"): (25.4, 28.6, 24.7, 26.2, 31.0, 32.4, 32.4),
    (9, "balanced"): (25.4, 28.6, 24.7, 26.2, 31.0, 32.4, 32.6),
    (9, "fast"): (25.4, 28.6, 24.7, 26.2, 31.0, 32.7, 32.5),
    (11, "exact"): (31.2, 25.9, 29.9, 31.8, 31.3, 34.5, 34.5),
    (11, "high"): (31.2, 25.9, 29.9, 31.8, 31.3, 34.5, 34.6),
    (11, "balanced"): (31.2, 25.9, 29.9, 31.8, 31.3, 34.4, 34.6),
    (11, "fast"): (31.2, 25.9, 30.3, 31.4, 31.1, 34.5, 34.6),
    (15, "high"): (100.0, 100.0, 100.0, 51.6, 50.7, 51.7, 52.2),
    (15, "balanced"): (100.0, 100.0, 49.5, 48.0, 49.1, 49.8, 50.0),
    (15, "fast"): (100.0, 53.2, 43.8, 40.9, 44.9, 43.4, 44.5),
}

#: :data:`CALIBRATION` for ``placement="blend"``: the same runs with ``--placements blend``.
#: Its reduced-resolution worst cases are lower (a pixel is in two layers, often one of them on
#: a coarser grid: 41.5 dB for ``"balanced"`` in the 8-16 px bin), and fewer layers cost more
#: at the largest CoCs (15-19 dB in the open bin: a CoC between the 1-px kernel and a large one
#: is drawn with both).
BLEND_CALIBRATION: dict[tuple[int, str], tuple[float | None, ...]] = {
    (5, "exact"): (20.5, 22.6, 22.3, 20.3, 24.8, 17.2, 15.8),
    (5, "high"): (20.5, 22.6, 22.4, 20.3, 24.8, 17.3, 15.8),
    (5, "balanced"): (20.5, 22.6, 22.4, 20.3, 24.8, 17.3, 15.9),
    (5, "fast"): (20.5, 22.6, 22.4, 20.3, 24.8, 17.4, 15.9),
    (7, "exact"): (24.2, 27.6, 26.4, 25.2, 25.8, 16.8, 15.3),
    (7, "high"): (24.2, 27.6, 26.4, 25.2, 25.8, 16.8, 15.3),
    (7, "balanced"): (24.2, 27.6, 26.4, 25.2, 25.8, 16.8, 15.3),
    (7, "fast"): (24.2, 27.4, 26.4, 25.2, 25.8, 16.8, 15.4),
    (9, "exact"): (24.2, 30.3, 26.4, 25.3, 25.8, 22.8, 18.8),
    (9, "high"): (24.2, 30.3, 26.4, 25.3, 25.8, 22.7, 18.8),
    (9, "balanced"): (24.2, 30.3, 26.4, 25.3, 25.8, 22.7, 18.8),
    (9, "fast"): (24.2, 30.3, 26.4, 25.3, 25.8, 22.6, 18.8),
    (11, "exact"): (44.8, 31.6, 32.5, 29.2, 30.7, 21.3, 18.3),
    (11, "high"): (44.8, 31.6, 32.5, 29.3, 30.7, 21.3, 18.3),
    (11, "balanced"): (44.8, 31.6, 32.0, 29.3, 30.7, 21.3, 18.3),
    (11, "fast"): (44.8, 31.6, 32.0, 29.0, 30.5, 21.3, 18.3),
    (15, "high"): (100.0, 100.0, 100.0, 45.7, 46.0, 47.3, 47.0),
    (15, "balanced"): (100.0, 100.0, 41.5, 43.0, 43.8, 44.0, 44.8),
    (15, "fast"): (100.0, 46.8, 36.7, 35.6, 40.9, 38.1, 38.5),
}

# Subtracted from the calibrated worst case: the calibration scenes are not the user's. The
# error of a coarser layer schedule depends on where the scene's CoCs fall between its kernel
# sizes, so it varies far more from scene to scene than the reduced-resolution error does.
SAFETY_DB = 1.0
LAYER_SAFETY_DB = 3.0
# Full-resolution CoC (px) under which the pipeline's fusion gate opens: the paper's
# D < 0.3 at a half-resolution pass is an 11.8 px CoC there, 23.6 px at full resolution.
FUSION_COC_PX = 23.6
# Long side of the map the picker inspects: the layer occupancy needs no more.
_PROBE_SIDE = 64


@dataclass
class RenderSettings:
    """What :func:`choose_settings` picked for one scene and slider value.

    Attributes:
        num_layers: kernel sizes per side of the focal plane for ``rendering.render``.
        quality: renderer reduced-resolution preset (``"exact"`` ... ``"fast"``).
        identity: nothing is blurred: the input is the result, no layer is rendered.
        fusion: the full-resolution fusion step can change the result.
        max_coc: largest CoC diameter in the scene (px at the disparity's resolution).
        min_coc: smallest CoC diameter (px at the disparity's resolution).
        layers: ``(centre, kernel px, share of pixels)`` of the occupied layers, back to
            front, at the picked layer count.
        predicted_psnr: calibrated worst case (dB) against the exact reference, ``inf`` for
            the identity path and the reference itself.
        budget_db: the budget the settings were picked for.
        cost: relative cost estimate (full-frame kernel passes at full resolution).
    """

    num_layers: int
    quality: str
    identity: bool
    fusion: bool
    max_coc: float
    min_coc: float
    budget_db: float
    predicted_psnr: float = math.inf
    cost: float = 0.0
    layers: list[tuple[int, int, float]] = field(default_factory=list)

    def render_options(self) -> dict[str, object]:
        """Keyword arguments for ``rendering.render``."""
        return {"num_layers": self.num_layers, "quality": self.quality}

    def describe(self) -> str:
        """One line for people: what was picked."""
        if self.identity:
            return "every blur under 1 px: input shown"
        text = f"{self.num_layers} layers, {self.quality} preset"
        return text + ("" if self.fusion else ", fusion skipped")

    def to_dict(self) -> dict[str, object]:
        out = asdict(self)
        out["predicted_psnr"] = None if math.isinf(self.predicted_psnr) else self.predicted_psnr
        return out


def coc_bin(max_coc: float) -> int:
    """Index of the :data:`COC_BINS` interval that holds ``max_coc`` (px): the column of
    :data:`CALIBRATION` a scene with that largest CoC reads."""
    for i, edge in enumerate(COC_BINS):
        if max_coc < edge:
            return i
    return len(COC_BINS)


def predicted_psnr(
    num_layers: int, quality: str, max_coc: float, placement: str = "blend"
) -> float:
    """Calibrated worst-case PSNR (dB) of a candidate for a scene whose largest CoC is
    ``max_coc`` px, with the layer ``placement`` (:data:`BLEND_CALIBRATION` for
    ``"blend"``, else :data:`CALIBRATION`); ``inf`` for the reference itself, ``-inf`` when
    not calibrated."""
    if num_layers == 15 and quality == "exact":
        return math.inf
    table = BLEND_CALIBRATION if placement == "blend" else CALIBRATION
    row = table.get((num_layers, quality))
    if row is None:
        return -math.inf
    value = row[coc_bin(max_coc)]
    if value is None:
        return -math.inf
    return value - (SAFETY_DB if num_layers == 15 else LAYER_SAFETY_DB)


def _probe(disparity: torch.Tensor) -> torch.Tensor:
    """The first map of the batch, area-downsampled to a long side of at most 64 px."""
    d = disparity[:1].detach().float()
    scale = _PROBE_SIDE / max(d.shape[-2:])
    if scale < 1:
        size = (max(1, round(d.shape[-2] * scale)), max(1, round(d.shape[-1] * scale)))
        d = F.interpolate(d, size=size, mode="area")
    return d


def _occupancy(
    disparity: torch.Tensor,
    focus: float,
    blur: float,
    num_layers: int,
    schedule: str,
    placement: str = "blend",
) -> list[tuple[int, int, float]]:
    """``(centre, kernel px, share of pixels)`` of each layer that holds pixels."""
    f = torch.full((1, 1, 1, 1), focus, dtype=disparity.dtype)
    plan = layer_plan(
        disparity, f, blur, num_layers=num_layers, schedule=schedule, placement=placement
    )
    coord = plan.coord.flatten()[None]  # [1,P]
    centres = torch.tensor([c for c, _ in plan.order], dtype=coord.dtype)[:, None]  # [n,1]
    # a layer takes the pixels within one layer unit of its centre, on its side of focus
    near = (coord - centres).abs() < 1.0
    near &= (centres == 0) | (torch.sign(coord) == torch.sign(centres))
    shares = near.float().mean(dim=1).tolist()
    return [
        (centre, size, share)
        for (centre, size), share in zip(plan.order, shares, strict=True)
        if share > 0
    ]


def _cost(layers: list[tuple[int, int, float]], quality: str) -> float:
    """Relative render cost: each blurred layer's share of the frame, at its resolution."""
    total = 0.0
    for _, size, share in layers:
        if size <= 1:
            total += 0.1 * share  # masked and composited, not convolved
            continue
        f = grid_factor(size, quality)
        # a layer's support box is larger than its pixels, and every layer pays some overhead
        total += (0.05 + min(1.0, 2.0 * share)) / (f * f)
    return total


def choose_settings(
    disparity: torch.Tensor,
    focus: float,
    blur: float,
    *,
    budget_db: float | None = None,
    quality: str = DEFAULT_QUALITY,
    schedule: str = "growing",
    full_scale: float = 1.0,
    fusion_coc: float = FUSION_COC_PX,
    placement: str = "blend",
    checked: bool = False,
) -> RenderSettings:
    """Cheapest renderer settings whose expected error stays within a PSNR budget.

    Args:
        disparity: ``(B, 1, H, W)`` in [0, 1], 1 = nearest (the first map is inspected).
        focus: focal disparity in [0, 1].
        blur: ``K``, CoC diameter in px at the disparity's resolution for ``|d - focus| = 1``.
        budget_db: PSNR (dB) against the exact reference that the result must reach; default
            from ``quality``.
        quality: user-facing option, ``"high"``, ``"balanced"`` or ``"fast"``
            (:data:`BUDGETS`).
        schedule: kernel-size schedule the render will use.
        full_scale: full-resolution px per px of ``disparity`` (2 for a half-resolution pass);
            used for the identity and fusion decisions, which concern the full-size output.
        fusion_coc: full-resolution CoC (px) below which fusion can change a pixel.
        placement: the render's layer placement (``rendering.layer_plan``).
        checked: ``True`` from a caller that has put ``focus`` and ``blur`` through
            ``rendering.check_focus_blur`` already (``D2F.render``, :func:`render_adaptive`):
            they are used as given, not checked again.

    Returns:
        :class:`RenderSettings`; ``settings.render_options()`` goes to ``rendering.render``.
    """
    if not isinstance(disparity, torch.Tensor) or disparity.ndim != 4 or disparity.shape[1] != 1:
        shape = tuple(disparity.shape) if isinstance(disparity, torch.Tensor) else None
        raise ValueError(f"disparity must be a (B, 1, H, W) tensor, got {shape}")
    if not checked:
        focus, blur = check_focus_blur(focus, blur)
    if quality not in BUDGETS:
        raise ValueError(f"quality must be one of {sorted(BUDGETS)}, got {quality!r}")
    budget = BUDGETS[quality] if budget_db is None else float(budget_db)
    if not full_scale > 0:
        raise ValueError(f"full_scale must be > 0, got {full_scale}")

    d = disparity.detach().clamp(0, 1)
    distance = (d - focus).abs()
    max_coc = blur * float(distance.max())
    min_coc = blur * float(distance.min())
    if max_coc * full_scale < 1.0:
        # every CoC is below a pixel of the output: nothing to blur, nothing to fuse
        return RenderSettings(15, "exact", True, False, max_coc, min_coc, budget)
    fusion = min_coc * full_scale < fusion_coc and full_scale > 1.0

    probe = _probe(d)
    occupancy: dict[int, list[tuple[int, int, float]]] = {}
    best: RenderSettings | None = None
    for num_layers, preset in CANDIDATES:
        expected = predicted_psnr(num_layers, preset, max_coc, placement)
        if expected < budget:
            continue
        if num_layers not in occupancy:
            occupancy[num_layers] = _occupancy(probe, focus, blur, num_layers, schedule, placement)
        layers = occupancy[num_layers]
        cost = _cost(layers, preset)
        if best is None or (cost, -expected) < (best.cost, -best.predicted_psnr):
            best = RenderSettings(
                num_layers, preset, False, fusion, max_coc, min_coc, budget, expected, cost, layers
            )
    if best is None:  # only when the table lacks the reference's own entry
        best = RenderSettings(15, "exact", False, fusion, max_coc, min_coc, budget)
    return best


def render_adaptive(
    image: torch.Tensor,
    disparity: torch.Tensor,
    focus: float,
    blur: float,
    *,
    budget_db: float | None = None,
    quality: str = DEFAULT_QUALITY,
    **options,
) -> tuple[torch.Tensor, RenderSettings]:
    """:func:`rendering.render` with :func:`choose_settings`' layer count and preset.

    Args:
        image: ``(B, 3, H, W)`` in [0, 1]; disparity ``(B, 1, H, W)`` in [0, 1].
        focus, blur: as for ``rendering.render`` (``blur`` in px at this resolution).
        budget_db, quality: see :func:`choose_settings`.
        **options: other ``rendering.render`` options (``order``, ``kernel``, ``radiance``...);
            ``num_layers`` and ``quality`` are picked here.

    Returns:
        ``(bokeh (B, 3, H, W) in [0, 1], settings)``. On the identity path the input is
        returned (clamped) and no layer is rendered.
    """
    for key in ("num_layers", "quality", "checked"):
        if key in options:
            raise ValueError(f"options must not contain {key!r}: render_adaptive sets it")
    focus, blur = check_focus_blur(focus, blur)
    settings = choose_settings(
        disparity,
        focus,
        blur,
        budget_db=budget_db,
        quality=quality,
        schedule=options.get("schedule", "growing"),
        placement=options.get("placement", "blend"),
        checked=True,
    )
    if settings.identity and options.get("order", "depth") == "depth":
        if not isinstance(image, torch.Tensor) or image.ndim != 4 or image.shape[1] != 3:
            raise ValueError("image must be a (B, 3, H, W) tensor")
        return image.clamp(0, 1), settings
    if options.get("order", "depth") == "paper":
        # the paper's order stretches its 15 kernels to K: the layer count is the model's
        settings.num_layers = 15
    options |= settings.render_options()
    return render(image, disparity, focus, blur, checked=True, **options), settings
