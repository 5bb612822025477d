"""What the pipeline returns: a prepared photo (:class:`Scene`: ``I_hr``, ``I_lr``, the
disparity ``d`` and the radiance ``R0`` of D2F steps 1-3) and a render (:class:`Result`:
``B_hr`` of step 6 with the maps behind it).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..depth.brushes import Brushes
from ..rendering import adaptive
from ..sizing import resize

#: How many entries of each kind keyed by a size (a preview's inputs, a screen's scene, a
#: tile size) a scene keeps: the most recently used ones. A server that renders one photo at
#: many sizes keeps a scene's memory bounded (at 1 MP, 20 sizes had added 129 MB).
SIZES_KEPT = 4


class SceneCache(dict):
    """A scene's derived tensors, filled lazily: one entry per name (``"disparity_full"``,
    ``"subject"``), and of each kind keyed by a size (``("preview", size)``, ``("screen",
    ...)``) the :data:`SIZES_KEPT` most recently used. Never pickled with its scene."""

    def __getitem__(self, key: Any) -> Any:
        value = super().__getitem__(key)
        if isinstance(key, tuple):  # the most recently used goes last
            super().pop(key, None)
            super().__setitem__(key, value)
        return value

    def __setitem__(self, key: Any, value: Any) -> None:
        super().__setitem__(key, value)
        if isinstance(key, tuple) and key:
            same = [k for k in list(self) if isinstance(k, tuple) and k and k[0] == key[0]]
            for old in same[:-SIZES_KEPT]:
                super().pop(old, None)


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
        focus: the focal disparity the depth source recorded with the map (a phone's focal
            plane), ``None`` for the others; :meth:`D2F.render` focuses there by default.
        brushes: the focus and blur paint (:meth:`D2F.paint`), applied by every render for
            its focus; ``None`` when nothing is painted.
        pixel_scale: the scene's pixels per pixel of the photo: 1, or less for a photo
            downscaled to a screen (:meth:`D2F.screen_scene`); the fusion gate is a CoC in
            the photo's own pixels.
        cache: derived tensors (full-res disparity, preview-size inputs), filled lazily: a
            :class:`SceneCache` keeping the :data:`SIZES_KEPT` most recent sizes of each
            kind, left out of a pickled scene; :meth:`clear_cache` empties it.
        photo_info: the loaded photo's :class:`~d2f_core.io.ImageInfo` (ICC profile, EXIF)
            when prepared from a :class:`~d2f_core.io.Photo`, else ``None``; every render
            of the scene carries it.
    """

    image: Tensor
    image_lr: Tensor
    disparity_lr: Tensor
    radiance_lr: Tensor
    size: tuple[int, int]
    disparity_source: str = "d2f"
    disparity_output: str = "D2F network disparity"
    refined: bool = True
    focus: float | None = None
    given_disparity: Tensor | None = field(default=None, repr=False)
    brushes: Brushes | None = field(default=None, repr=False)
    pixel_scale: float = 1.0
    cache: dict[Any, Any] = field(default_factory=SceneCache, repr=False)
    photo_info: Any = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.cache, SceneCache):
            self.cache = SceneCache(self.cache)

    def __getstate__(self) -> dict[str, Any]:
        """A pickled scene leaves its cache behind (it is made again when needed)."""
        return {**self.__dict__, "cache": SceneCache()}

    def clear_cache(self) -> None:
        """Drop what renders derived from this scene (made again when needed)."""
        self.cache.clear()

    def brushed(self, focus: float) -> Scene:
        """This scene as a render focused at ``focus`` sees it: its full-resolution map
        edited by the brushes (itself when nothing is painted)."""
        if self.brushes is None:
            return self
        with torch.no_grad():
            d = self.brushes.apply(self.disparity_full_tensor(), focus)
        return replace(self, given_disparity=d, brushes=None, cache={"disparity_full": d})

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
        focus: the focal disparity rendered at (the subject's when none was given).
        focal_range: the span of disparity kept sharp around it (the subject's when no
            focus was given).
        photo_info: the loaded photo's :class:`~d2f_core.io.ImageInfo` (its ICC profile
            and EXIF) when the scene was prepared from a :class:`~d2f_core.io.Photo`, else
            ``None``: ``save_image(path, result)`` writes them with the picture.
    """

    bokeh: np.ndarray
    bokeh_lr: np.ndarray
    disparity: np.ndarray
    defocus: np.ndarray
    fusion_mask: np.ndarray
    timings: dict[str, float]
    settings: adaptive.RenderSettings | None = None
    focus: float | None = None
    focal_range: float = 0.0
    photo_info: Any = field(default=None, repr=False)
