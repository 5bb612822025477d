"""The model's settings (:class:`D2FConfig`, saved inside every checkpoint) and where its
weights come from; the architecture of D2F steps 2, 3 and 6 is chosen here.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from .. import bundled, rendering
from ..errors import InputTypeError

CHECKPOINT_VERSION = 1


def default_weights_path() -> Path:
    """``$D2F_WEIGHTS`` if set, else the shipped weights (:func:`bundled.shipped_weights`)."""
    env = os.environ.get("D2F_WEIGHTS")
    if env:
        return Path(env)
    return bundled.shipped_weights()


#: The range of each float setting that no other check below bounds on both sides (a
#: checkpoint's config is read from a file: ``inf`` or ``nan`` must not pass as a setting).
_FLOAT_RANGES = {
    "train_blur": (0.0, 1000.0),
    "fusion_theta": (0.0, 1.0),
    "sharp_coc": (1e-3, 16.0),
    "refine_eps": (1e-9, 3.0),
}


#: The float settings for which +inf has a meaning (``spread_clip``: no clip limit, the
#: equalised map is the map's ranks); NaN and -inf are refused for every one.
_INFINITE_OK = {"spread_clip"}


@dataclass
class D2FConfig:
    """Architecture and inference settings; saved inside every checkpoint.

    Attributes:
        defocus: defocus network variant (``"lite"`` or ``"resnext50"``).
        radiance: radiance network variant (``"paper"``).
        fusion: fusion network variant (``"lite"`` or ``"paper"``).
        network_size: long side (px) the defocus network runs at in :meth:`D2F.prepare`.
        render_scale: scale of the low-resolution rendering pass (paper: 0.5).
        max_render_side: cap on the long side of the low-resolution pass (px); 800, the
            pass a 1600 px photo gets, so that a large photo's picture on a 1600 px screen
            costs what a photo of that size costs (on six generated 12 MP scenes with their
            true depth 35.57 dB, against 35.44 with a 1024 px pass).
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
        fusion_gate: ``M_s`` is 0 where ``D >= fusion_gate`` (``D`` at the pass a photo
            gets at ``render_scale``, so a CoC in the photo's pixels, ``D2F.gate_coc``),
            fading to it over the last half of that CoC (``fusion.GATE_FADE``).
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
        subject_lift: with a ``"-scene"`` defocus network, every subject part its scene head
            finds is moved nearer until it stands this much in front of what surrounds it
            (by at most ``subject_shift``), and its sky to the back
            (:func:`d2f_core.depth.scene.stand_subjects`), before the map's edges are
            snapped. 0 stands no part; with ``subject_blend`` 0 too the head is not run and
            the network's disparity is kept as it is.
        subject_clarity: the subjects are stood only where the scene head's subject map is
            at least this clear (``min_clarity`` of :func:`~d2f_core.depth.scene.stand_subjects`).
        subject_shift: the most a stood part is moved nearer, in disparity (``max_shift`` of
            :func:`~d2f_core.depth.scene.stand_subjects`; the blend comes on top of it): the
            head also finds "subjects" in scenes with none (a shelf, a flower bed), and a
            small shift costs their order little. 1 leaves the shift unbounded.
        subject_blend: every pixel is moved nearer by this much times the square of the
            scene head's subject probability (``blend`` of
            :func:`~d2f_core.depth.scene.stand_subjects`), whether or not ``subject_lift``
            stands its parts: the head ranks held-out subjects above their background far
            better than the disparity does. 0 leaves the map as the parts' stand has it.
        spread: share of the network's map that is replaced by the same map equalised
            (:func:`d2f_core.depth.refine.equalize`, clip limit ``spread_clip``): the network
            learns the order of depths better than their spacing, and a map bunched in a
            narrow band leaves a far background nearly as sharp as the subject. 0 keeps the
            network's map as it is; maps from any other source are never changed.
        spread_clip: the equalisation's clip limit, at least 1 (the larger, the nearer the
            equalised map is to the map's ranks; ``inf``, the ranks themselves).
        depth_source: where :meth:`D2F.prepare` takes a photo's depth from when the photo
            brings none and none is asked for: ``"d2f"`` (this defocus network) or
            ``"scene"`` (the scene teachers with this network's subjects and map,
            :mod:`d2f_core.depth.scene_source`), rendered at the network's pass size.
    """

    defocus: str = "lite"
    radiance: str = "paper"
    fusion: str = "lite"
    network_size: int = 768
    render_scale: float = 0.5
    max_render_side: int = 800
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
    subject_lift: float = 0.05
    subject_clarity: float = 0.0
    subject_shift: float = 1.0
    subject_blend: float = 0.0
    spread: float = 0.0
    spread_clip: float = 4.0
    depth_source: str = "d2f"

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
            if kind is float and not math.isfinite(value):
                if value == math.inf and f.name in _INFINITE_OK:
                    continue
                raise ValueError(f"config.{f.name} must be a finite number, got {value!r}")
        for name, (low, high) in _FLOAT_RANGES.items():
            value = getattr(self, name)
            if not low <= value <= high:
                raise ValueError(f"config.{name} must be in [{low:g}, {high:g}], got {value!r}")
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
        if not 0 <= self.subject_clarity <= 1:
            raise ValueError(
                f"config.subject_clarity must be in [0, 1], got {self.subject_clarity}"
            )
        if not 0 <= self.subject_lift <= 0.5:
            raise ValueError(f"config.subject_lift must be in [0, 0.5], got {self.subject_lift}")
        if not 0 <= self.subject_shift <= 1:
            raise ValueError(f"config.subject_shift must be in [0, 1], got {self.subject_shift}")
        if not 0 <= self.subject_blend <= 1:
            raise ValueError(f"config.subject_blend must be in [0, 1], got {self.subject_blend}")
        if self.depth_source not in ("d2f", "scene"):
            raise ValueError(
                f"config.depth_source must be 'd2f' or 'scene', got {self.depth_source!r}"
            )
        if not 0 <= self.spread <= 1:
            raise ValueError(f"config.spread must be in [0, 1], got {self.spread}")
        if not self.spread_clip >= 1:
            raise ValueError(f"config.spread_clip must be at least 1, got {self.spread_clip}")
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
