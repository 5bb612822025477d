"""The accuracy bench's cases: seeded generated layered scenes with their thin-lens ground truth
(cached on disk), and the metrics over the whole frame, the occlusion edges and the lights.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "Case",
    "dilate",
    "edge_band",
    "jump_pixels",
    "light_band",
    "load_cases",
    "masked_metrics",
    "reach_px",
]

logger = logging.getLogger("d2f_core.bench.accuracy")


CACHE_VERSION = 1


#: The paper's runtime for a 1024x1536 frame on a GTX 1080 GPU (Luo et al. 2022, table 5).
PAPER_GPU_SECONDS = 0.58


@dataclass
class Case:
    """One scene, focus and ``K`` with its ground truth.

    Attributes:
        key: unique name (seed, size, K, focus mode).
        image: pinhole view, float32 ``(H, W, 3)`` sRGB in [0, 1] (renderer input).
        disparity: ground-truth disparity, float32 ``(H, W)`` in [0, 1], 1 = nearest.
        target: thin-lens ground truth, float32 ``(H, W, 3)`` sRGB in [0, 1].
        lights: HDR lights of the pinhole view (linear radiance above 1), bool ``(H, W)``.
        focus: focal disparity in [0, 1]; blur: ``K`` in px at this size.
    """

    key: str
    image: np.ndarray
    disparity: np.ndarray
    target: np.ndarray
    lights: np.ndarray
    focus: float
    blur: float
    size: tuple[int, int]
    seed: int
    mode: str
    bands: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``image (1, 3, H, W)`` and ``disparity (1, 1, H, W)``."""
        img = torch.from_numpy(np.ascontiguousarray(self.image)).permute(2, 0, 1)[None]
        disp = torch.from_numpy(np.ascontiguousarray(self.disparity))[None, None]
        return img.contiguous(), disp.contiguous()


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation with a (2r+1)-px disk. Shape: ``(H, W) -> (H, W)``."""
    if radius <= 0 or not mask.any():
        return mask.copy()
    t = torch.from_numpy(mask.astype(np.float32))[None, None]
    y, x = torch.meshgrid(
        torch.arange(-radius, radius + 1.0), torch.arange(-radius, radius + 1.0), indexing="ij"
    )
    disk = ((x * x + y * y) <= radius * radius + 0.5).float()[None, None]
    out = F.conv2d(t, disk, padding=radius)
    return (out[0, 0] > 0.5).numpy()


def reach_px(blur: float, divisor: int, cap: int) -> int:
    """How far (px) a band grows around what it marks: ``clamp(K / divisor, 2, cap)``."""
    return int(min(cap, max(2, math.ceil(blur / divisor))))


def jump_pixels(disparity: np.ndarray, jump: float = 0.02) -> np.ndarray:
    """Both pixels of every neighbour pair whose disparities differ by more than ``jump``.

    Shape: ``(H, W) -> (H, W)`` bool.
    """
    d = disparity.astype(np.float32)
    edges = np.zeros(d.shape, bool)
    dy = np.abs(np.diff(d, axis=0)) > jump
    dx = np.abs(np.diff(d, axis=1)) > jump
    edges[:-1] |= dy
    edges[1:] |= dy
    edges[:, :-1] |= dx
    edges[:, 1:] |= dx
    return edges


def edge_band(disparity: np.ndarray, blur: float, *, jump: float = 0.02) -> np.ndarray:
    """Pixels near an occlusion edge: a disparity jump above ``jump`` between neighbours,
    grown by ``clamp(K / 4, 2, 24)`` px, where a wrong layer order or a mask leak shows.

    Shape: ``(H, W) -> (H, W)`` bool.
    """
    return dilate(jump_pixels(disparity, jump), reach_px(blur, 4, 24))


def light_band(lights: np.ndarray, blur: float) -> np.ndarray:
    """Pixels a blurred HDR light can reach: the lights grown by ``clamp(K / 2, 2, 48)`` px.

    Shape: ``(H, W) -> (H, W)`` bool.
    """
    return dilate(lights, reach_px(blur, 2, 48))


def focus_for(scene, mode: str) -> float:
    if mode == "subject":
        return float(scene.subject)
    # "far": the farthest object in front of the background, so nearer objects blur over it
    orders = sorted(float(lay.order) for lay in scene.layers[1:] if lay.kind != "ground")
    return orders[0] if orders else float(scene.layers[0].order)


def _make_case(
    size: tuple[int, int], seed: int, blur: float, mode: str, samples: int, cache: Path | None
) -> Case:
    from ..train.synth import linear_to_srgb, make_scene, render_pinhole, render_thin_lens

    blur = round(blur, 2)
    key = f"s{seed}_{size[0]}x{size[1]}_k{blur:g}_{mode}_n{samples}_v{CACHE_VERSION}"
    path = None if cache is None else cache / f"{key}.npz"
    if path is not None and path.is_file():
        data = np.load(path)
        return Case(
            key,
            data["image"],
            data["disparity"],
            data["target"],
            data["lights"],
            float(data["focus"]),
            float(data["blur"]),
            size,
            seed,
            mode,
        )
    scene = make_scene(size, seed=seed, margin=math.ceil(blur / 2) + 2)
    focus = focus_for(scene, mode)
    radiance, disparity = render_pinhole(scene)
    target = render_thin_lens(scene, focus, blur, samples=samples)
    case = Case(
        key,
        linear_to_srgb(radiance),
        disparity.astype(np.float32),
        linear_to_srgb(target),
        (radiance > 1.0).any(axis=2),
        focus,
        blur,
        size,
        seed,
        mode,
    )
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(
            tmp,
            image=case.image,
            disparity=case.disparity,
            target=case.target,
            lights=case.lights,
            focus=focus,
            blur=blur,
        )
        os.replace(tmp, path)
    return case


def load_cases(
    sizes: Sequence[tuple[int, int]],
    seeds: Sequence[int],
    k_fracs: Sequence[float] = (),
    *,
    samples: int = 256,
    cache: str | Path | None = None,
    k_px: Sequence[float] = (),
) -> list[Case]:
    """Generated scenes with thin-lens ground truth, cached as ``.npz`` under ``cache``.

    Even seeds focus on the main subject, odd seeds on the farthest object (so nearer objects
    blur over a sharp region). ``K = k_frac * width`` for each of ``k_fracs``, then
    ``K = k`` px for each of ``k_px`` (the same K by either way shares its cache file).
    """
    if not k_fracs and not k_px:
        raise ValueError("load_cases needs at least one K: k_fracs or k_px")
    if any(not (math.isfinite(k) and k > 0) for k in (*k_fracs, *k_px)):
        raise ValueError(f"K must be finite and > 0, got {list(k_fracs)} {list(k_px)}")
    cache_path = None if cache is None else Path(cache)
    cases = []
    for size in sizes:
        blurs = [k * size[1] for k in k_fracs] + [float(k) for k in k_px]
        for seed in seeds:
            mode = "subject" if seed % 2 == 0 else "far"
            for blur in blurs:
                t0 = time.perf_counter()
                case = _make_case(tuple(size), seed, blur, mode, samples, cache_path)
                case.bands = {
                    "edges": edge_band(case.disparity, case.blur),
                    "lights": light_band(case.lights, case.blur),
                }
                logger.info("case %s ready (%.1f s)", case.key, time.perf_counter() - t0)
                cases.append(case)
    return cases


def masked_metrics(
    pred: np.ndarray, target: np.ndarray, bands: dict[str, np.ndarray]
) -> dict[str, float | None]:
    """PSNR (dB) and SSIM overall and inside each band (``None`` for an empty band).

    Shape: ``pred, target (H, W, 3)`` in [0, 1]; ``bands`` maps a name to ``(H, W)`` bool.
    SSIM uses a Gaussian window (sigma 1.5); a band's SSIM is the mean of the SSIM map there.
    """
    from skimage.metrics import structural_similarity

    a, b = pred.astype(np.float64), target.astype(np.float64)
    err = ((a - b) ** 2).mean(axis=2)
    win = min(7, min(a.shape[:2]) | 1) if min(a.shape[:2]) < 7 else None
    kw = {"win_size": win} if win else {"gaussian_weights": True, "sigma": 1.5}
    mean_ssim, smap = structural_similarity(
        a, b, data_range=1.0, channel_axis=-1, full=True, use_sample_covariance=False, **kw
    )
    smap = smap.mean(axis=2)

    def _psnr(mse: float) -> float:
        return 100.0 if mse <= 1e-10 else 10.0 * math.log10(1.0 / mse)

    out: dict[str, float | None] = {"psnr": _psnr(float(err.mean())), "ssim": float(mean_ssim)}
    for name, band in bands.items():
        if band.any():
            out[f"psnr_{name}"] = _psnr(float(err[band].mean()))
            out[f"ssim_{name}"] = float(smap[band].mean())
        else:
            out[f"psnr_{name}"] = out[f"ssim_{name}"] = None
    return out
