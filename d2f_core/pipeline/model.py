"""The model, D2F end to end: ``prepare`` runs the networks once per photo (steps 1-3,
``d = f_d(I_lr)``, ``R0 = f_r(I_lr)``), ``render`` refocuses it (steps 4-6) as often as asked.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from .. import rendering
from ..depth import sources as depth_sources
from ..depth.brushes import Brushes
from ..errors import InputTypeError, whole_number
from ..io.depth import check_aspect
from ..io.embedded import Photo
from ..networks import build_defocus_net, build_fusion_net, build_radiance_net, read_torch_file
from ..rendering import adaptive
from ..rendering.schedule import (
    fold_focal_range,
)
from ..sizing import resize, scaled_size, size_ratio
from .config import CHECKPOINT_VERSION, D2FConfig, default_weights_path
from .depth_stage import DepthStage
from .focus import FocusStage
from .fusion import FusionStage, ms_since
from .outputs import Result, Scene
from .render_steps import RenderSteps
from .training import TrainingStage
from .views import ViewStage


def _recorded_focus(value: Any) -> float | None:
    """A depth source's recorded focal disparity clipped to [0, 1]; ``None`` when there is
    none or it is not a finite number."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return min(max(f, 0.0), 1.0) if math.isfinite(f) else None


class D2F(DepthStage, FusionStage, FocusStage, ViewStage, RenderSteps, TrainingStage, nn.Module):
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
            unreadable=f"checkpoint {path} cannot be read",
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
                tensor in [0, 1], or a :class:`d2f_core.io.Photo` from
                :func:`~d2f_core.io.load_photo` (whose phone depth the ``"embedded"`` source
                reads, and which is the default for a photo that carries some).
            depth: where the disparity comes from (:mod:`d2f_core.depth.sources`): ``None``
                (the photo's phone depth when it has some, else this model's defocus network),
                ``"d2f"`` (the network), ``"scene"`` (the scene teachers with the network's
                subjects), ``"embedded"``, ``"file:PATH"``,
                ``"transformers:MODEL"``, a :class:`~d2f_core.depth.sources.DepthMap`, or a
                ready ``H' x W'`` map in [0, 1] (1 = nearest) of any size and the photo's
                aspect ratio (within 5 %), resized to the photo.
            disparity: a ready map, as ``depth`` (its older name).
            refine: edge-aware refinement (:meth:`refine_disparity`) of the map at the
                rendering pass's size, the same for every source (and the network's own
                snapping, ``config.refine``); ``False`` keeps the map as the source gave it.

        Returns:
            A :class:`Scene` on the model's device; ``scene.disparity_source`` names the
            source (``"given"`` for a bare map).

        Raises:
            ValueError: a map that is not a disparity in [0, 1], or whose aspect ratio is not
                the photo's (it would be stretched onto it).
        """
        if disparity is not None and depth is not None:
            raise ValueError("pass the map as depth or as disparity, not both")
        depth = disparity if depth is None else depth
        photo = None
        if isinstance(image, Photo):
            photo, image = image, image.image
            if depth is None and photo.disparity is not None:
                depth = "embedded"  # the phone's own depth, as the CLI and the app take it
        if depth is None and self.config.depth_source != "d2f":
            depth = self.config.depth_source
        device = self.device
        image_t = rendering.image_tensor(image).to(device)  # [1,3,H,W]
        source, output = depth_sources.DEFAULT_SOURCE, "D2F network disparity"
        recorded, predicted = None, True
        if isinstance(depth, (str, depth_sources.DepthSource)):
            spec = depth_sources.parse_source(depth)
            if spec.kind == "d2f":
                depth = None
            else:
                depth = depth_sources.depth_map(
                    spec, image_t, photo=photo, model=self, device=device
                )
        if isinstance(depth, depth_sources.DepthMap):
            source, output, recorded = depth.source, depth.output, depth.focus
            predicted = depth.predicted
            depth = depth.disparity
        elif depth is not None:
            source, output, predicted = "given", "disparity map", False
        given = None if depth is None else rendering.disparity_tensor(depth).to(device)
        size = (int(image_t.shape[-2]), int(image_t.shape[-1]))
        if given is not None:  # resized to the photo, never stretched onto it
            check_aspect(tuple(given.shape[-2:]), size, "depth")
        # a map this model predicts (its network's, or a DepthMap marked predicted: the scene
        # source's) is rendered at the network's pass size; a measured map at the photo's
        # own, up to full_pass_side. Only the network's own map is snapped onto the photo's
        # edges (the scene map, snapped: 31.50 dB against 31.75 on the 12 measured photos,
        # d2f-bench depth --bokeh)
        lr_size = self.pass_size(size, given=not predicted)
        image_lr = resize(image_t, lr_size).clamp_(0, 1)  # [1,3,h,w]
        if given is None:
            disparity_lr = self.predict_disparity(image_lr, refine, image_t)  # [1,1,h,w]
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
            focus=_recorded_focus(recorded),
            # a predicted map's full size is its pass's upsampled: never kept twice
            given_disparity=None if predicted else given,
            photo_info=None if photo is None else photo.info,
        )

    def paint(
        self, scene: Scene, sharp: Any = None, blur: Any = None, *, edges: bool = True
    ) -> Scene:
        """The scene with focus and blur brushes painted over it (:mod:`d2f_core.depth.brushes`).

        What ``sharp`` paints is drawn onto the focal plane of every later render, wherever
        the focus is then set, so it stays sharp; what ``blur`` paints is moved away from the
        focal plane, so it is at least as blurred as without the paint. The masks replace any
        paint the scene had; ``None`` for both clears it. The networks do not run again.

        Args:
            scene: from :meth:`prepare`.
            sharp, blur: masks of the photo's aspect ratio and any size, white (1 or 255) =
                painted, soft values partial paint: ``H x W`` numpy or tensor, or ``H x W x C``
                (the colour's mean, times alpha when there is one).
            edges: each stroke's rim follows the photo's own edges (a stroke that spills
                over a silhouette is cut back to it); ``False`` takes the masks as they are.

        Returns:
            A new :class:`Scene` sharing this one's maps; ``scene.brushes`` holds the paint.

        Raises:
            ValueError: a mask that is not a mask (see
                :func:`~d2f_core.depth.brushes.mask_tensor`) or of another aspect ratio.
        """
        if not isinstance(scene, Scene):
            kind = type(scene).__name__
            raise InputTypeError(f"scene must be a Scene from prepare(), got {kind}")
        brushes = Brushes.painted(scene.image, sharp, blur, edges=edges)
        return dataclasses.replace(scene, brushes=brushes)

    def forward(self, scene: Any, *args: Any, **kwargs: Any) -> Result:
        """``model(scene, focus, blur, ...)`` is :meth:`render` of a prepared scene."""
        if not isinstance(scene, Scene):
            raise InputTypeError(
                f"model(...) renders a Scene from model.prepare(photo), got "
                f"{type(scene).__name__}: prepare the photo first"
            )
        return self.render(scene, *args, **kwargs)

    @torch.no_grad()
    def render(
        self,
        scene: Scene,
        focus: float | None = None,
        blur: float | None = None,
        *,
        fusion: bool = True,
        max_side: int | None = None,
        budget: str | float | None = adaptive.DEFAULT_QUALITY,
        f_number: float | None = None,
        focal_range: float | None = None,
        screen: int | None = None,
        **render_options: Any,
    ) -> Result:
        """Refocus a prepared photo.

        Args:
            scene: from :meth:`prepare`.
            focus: focal disparity in [0, 1] (1 = nearest); see :meth:`focus_at`. ``None``
                (the default) focuses where the CLI and the app do with no focus given
                (:meth:`default_focus`): on the focal plane a phone recorded with its depth
                (``scene.focus``), else on the subject the map puts in front, with the focal
                range that keeps it sharp (found once per scene); ``result.focus`` and
                ``result.focal_range`` say where.
            blur: ``K``, CoC diameter in px at FULL resolution for ``|d - focus| = 1``
                (default 40 px unless ``f_number`` is given).
            f_number: the blur as the f-number of the stated virtual lens
                (:func:`d2f_core.lens.blur_px` on the photo's long side), the app's aperture;
                give ``blur`` or ``f_number``, not both.
            focal_range: ``r``, a span of disparity around ``focus`` that stays perfectly
                sharp, the blur growing from its edges (``CoC = K max(0, |d - f| - r/2)``);
                with fusion every pixel inside it is the photo's own, at full resolution.
                0 is the thin lens; :meth:`focus_at` can measure a subject's range. ``None``
                (default): the default focus's range when ``focus`` is ``None``, else 0.
            fusion: apply deep Poisson fusion at full resolution (else plain upsampling; a
                pass at the photo's own size needs none and has none).
            max_side: preview mode: render at this long side, no fusion.
            screen: the whole render at this long side, as the full render downscaled to it
                (what a screen shows of a large photo): the photo downscaled, the pass at no
                more than this side, fusion at this side (:meth:`screen_scene`); ``blur``
                stays K at the photo's full resolution. The photo's own size or larger: the
                full render.
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
        focus, blur, focal_range, budget = self._render_args(
            scene, focus, blur, f_number, focal_range, budget, render_options
        )
        if max_side is not None:
            max_side = whole_number(max_side, "max_side", 1)
        pick = (
            budget is not None
            and render_options["order"] == "depth"
            and "num_layers" not in render_options
            and "quality" not in render_options
        )
        timings: dict[str, float] = {}
        t_all = time.perf_counter()

        # 1. the scene as rendered (at the screen's size, the paint applied) and the inputs
        # of the rendering pass (preview: its own size, cached per size)
        scene, blur, (image_lr, disparity_lr, radiance_lr) = self._pass_inputs(
            scene, max_side, screen, focus, blur
        )
        # a focal range folded into the map: every later step sees its CoCs
        disparity_lr = fold_focal_range(disparity_lr, focus, focal_range)  # [1,1,h,w]
        lr_size = (int(image_lr.shape[-2]), int(image_lr.shape[-1]))
        lr_ratio = size_ratio(lr_size, scene.size)

        # 2. adaptive settings, then layered rendering at low resolution (HDR boost inside)
        preview = max_side is not None
        settings, fuse, bokeh_lr, behind_lr = self._adaptive_pass(
            scene, (image_lr, disparity_lr, radiance_lr), focus, blur, lr_ratio, focal_range,
            budget if pick else None, fusion and not preview, preview, render_options, timings,
        )  # fmt: skip

        # 3. upsample + deep Poisson fusion at full resolution, the result as numpy arrays
        result = self._result(
            scene, (bokeh_lr, behind_lr, disparity_lr), settings, fuse, focus, blur, lr_ratio,
            focal_range, preview, timings,
        )  # fmt: skip
        timings["total"] = ms_since(t_all)
        return result
