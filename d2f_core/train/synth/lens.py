"""Layered scene model and its exact renderers (pinhole and accumulation-buffer thin lens).

See the package docstring for the conventions."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from ...errors import InputTypeError, whole_number

logger = logging.getLogger(__name__)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Decode sRGB values in [0, 1] to linear radiance (IEC 61966-2-1 curve)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Encode linear values to sRGB; input is clipped to [0, 1] first."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


@dataclass
class Layer:
    """One planar RGBA layer, stored as a crop placed in view coordinates.

    Attributes:
        rgb: premultiplied linear radiance, float32 ``(3, h, w)``, >= 0 (lights exceed 1).
        alpha: coverage, float32 ``(h, w)`` in [0, 1].
        top, left: view coordinates of the crop's first pixel (negative = in the margin).
        disparity: plane disparity at the view centre (equals the layer's disparity when
            fronto-parallel).
        slope: ``(dd/dy, dd/dx)`` per pixel; ``(0, 0)`` for fronto-parallel layers.
        kind: short name ("background", "blob", "branch", "ground", "lights", ...).
        order: back-to-front sort key (a representative disparity of the layer).
        info: extra JSON-able description.
    """

    rgb: np.ndarray
    alpha: np.ndarray
    top: int
    left: int
    disparity: float
    slope: tuple[float, float] = (0.0, 0.0)
    kind: str = "object"
    order: float | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.order is None:
            self.order = float(self.disparity)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.alpha.shape[0]), int(self.alpha.shape[1])

    def describe(self) -> dict:
        h, w = self.shape
        out = {"kind": self.kind, "disparity": round(float(self.order), 4)}
        if self.slope != (0.0, 0.0):
            out["plane"] = [round(float(self.disparity), 5)] + [round(s, 7) for s in self.slope]
        out["box"] = [int(self.top), int(self.left), h, w]
        return out | self.info


@dataclass
class Scene:
    """A layered scene. ``layers`` are sorted back to front; ``size`` is the view (H, W);
    ``margin`` is how far (px) the content extends beyond the view on every side, which
    bounds the blur radius the scene supports; ``subject`` is the main subject's disparity."""

    layers: list[Layer]
    size: tuple[int, int]
    margin: int
    subject: float
    seed: int | None = None


# --------------------------------------------------------------------------- aperture


def aperture_samples(n: int, *, pattern: str = "fibonacci") -> np.ndarray:
    """Points spread uniformly over the unit disk, float64 ``(n, 2)`` as (x, y).

    ``fibonacci``: golden-angle spiral (even coverage for any n); ``concentric``:
    Shirley-Chiu map of a stratified square grid (n rounded down to a square, >= 1).
    """
    n = whole_number(n, "n", 1)
    if pattern == "fibonacci":
        i = np.arange(n) + 0.5
        r = np.sqrt(i / n)
        t = i * math.pi * (3.0 - math.sqrt(5.0))
        return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    if pattern == "concentric":
        m = max(1, int(math.isqrt(n)))
        g = (np.arange(m) + 0.5) / m * 2 - 1
        a, b = (v.ravel() for v in np.meshgrid(g, g))
        first = np.abs(a) > np.abs(b)
        r = np.where(first, a, b)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(first, (math.pi / 4) * b / a, math.pi / 2 - (math.pi / 4) * a / b)
        t = np.nan_to_num(t)
        return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    raise ValueError(f"pattern must be 'fibonacci' or 'concentric', got {pattern!r}")


# --------------------------------------------------------------------------- rendering


def _check_scene(scene: Scene) -> None:
    if not isinstance(scene, Scene):
        raise InputTypeError(f"scene must be a Scene, got {type(scene).__name__}")
    if not scene.layers:
        raise ValueError("scene has no layers")


def _disparity_plane(layer: Layer, ys: np.ndarray, xs: np.ndarray, size: tuple[int, int]):
    cy, cx = (size[0] - 1) / 2, (size[1] - 1) / 2
    gy, gx = layer.slope
    return layer.disparity + gy * (ys[:, None] - cy) + gx * (xs[None, :] - cx)


def render_pinhole(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole view (aperture radius 0), composited exactly without resampling.

    Returns:
        (radiance, disparity): linear radiance float32 ``(H, W, 3)``, unclipped (lights > 1),
        and the disparity of the front-most layer with alpha >= 0.5, float32 ``(H, W)``
        clipped to [0, 1].
    """
    _check_scene(scene)
    height, width = scene.size
    acc = np.zeros((3, height, width), np.float32)
    disp = np.zeros((height, width), np.float32)
    for layer in scene.layers:
        h, w = layer.shape
        y0, y1 = max(layer.top, 0), min(layer.top + h, height)
        x0, x1 = max(layer.left, 0), min(layer.left + w, width)
        if y0 >= y1 or x0 >= x1:
            continue
        sy, sx = slice(y0 - layer.top, y1 - layer.top), slice(x0 - layer.left, x1 - layer.left)
        a = layer.alpha[sy, sx]
        acc[:, y0:y1, x0:x1] = layer.rgb[:, sy, sx] + (1 - a) * acc[:, y0:y1, x0:x1]
        d = _disparity_plane(layer, np.arange(y0, y1), np.arange(x0, x1), scene.size)
        region = disp[y0:y1, x0:x1]
        region[a >= 0.5] = np.broadcast_to(d, a.shape)[a >= 0.5]
    return acc.transpose(1, 2, 0).copy(), np.clip(disp, 0, 1)


def render_thin_lens(
    scene: Scene,
    focus: float,
    blur: float,
    *,
    samples: int = 256,
    pattern: str = "fibonacci",
    chunk: int | None = None,
    device: torch.device | str | None = None,
) -> np.ndarray:
    """Thin-lens view by the accumulation-buffer method.

    Args:
        scene: layered scene.
        focus: focal-plane disparity in [0, 1].
        blur: K, CoC diameter in px for ``|d - focus| = 1``; the aperture radius is K / 2.
        samples: aperture points averaged.
        pattern: aperture point pattern, see :func:`aperture_samples`.
        chunk: aperture points warped at once (memory ~ 28 * chunk * H * W bytes);
            default keeps about 8 M pixels per chunk.
        device: torch device for the work (default CPU).

    Returns:
        Linear radiance, float32 ``(H, W, 3)``, unclipped. ``blur == 0`` returns the
        pinhole view exactly.
    """
    _check_scene(scene)
    if not 0.0 <= float(focus) <= 1.0:
        raise ValueError(f"focus must be in [0, 1], got {focus!r}")
    if not float(blur) >= 0.0:
        raise ValueError(f"blur must be >= 0, got {blur!r}")
    if blur == 0:
        return render_pinhole(scene)[0]
    height, width = scene.size
    radius = float(blur) / 2
    reach = max(radius * abs(lay.order - focus) for lay in scene.layers)
    if reach > scene.margin + 0.5:
        logger.warning(
            "blur radius %.1f px exceeds the scene margin %d px; borders will darken",
            reach,
            scene.margin,
        )
    dev = torch.device(device) if device is not None else torch.device("cpu")
    pts = torch.as_tensor(aperture_samples(samples, pattern=pattern), dtype=torch.float64)
    n = pts.shape[0]
    chunk = chunk or max(1, min(n, (8 << 20) // (height * width)))
    cy, cx = (height - 1) / 2, (width - 1) / 2
    total = torch.zeros(3, height, width, dtype=torch.float64, device=dev)
    tensors = [
        (torch.from_numpy(np.concatenate([lay.rgb, lay.alpha[None]])).to(dev)[None], lay)
        for lay in scene.layers
    ]
    for start in range(0, n, chunk):
        v = pts[start : start + chunk] * radius  # [S,2] aperture offsets in px
        s = v.shape[0]
        acc = torch.zeros(s, 3, height, width, device=dev)
        for k, (tex, lay) in enumerate(tensors):
            gy, gx = lay.slope
            h, w = lay.shape
            # Where this layer can land: its crop grown by its largest shift.
            corners = [
                lay.disparity + gy * (y - cy) + gx * (x - cx)
                for y in (lay.top, lay.top + h)
                for x in (lay.left, lay.left + w)
            ]
            grow = math.ceil(radius * max(abs(c - focus) for c in corners)) + 1
            y0, y1 = max(lay.top - grow, 0), min(lay.top + h + grow, height)
            x0, x1 = max(lay.left - grow, 0), min(lay.left + w + grow, width)
            if y0 >= y1 or x0 >= x1:
                continue
            qy = torch.arange(y0, y1, dtype=torch.float64, device=dev)[None, :, None]
            qx = torch.arange(x0, x1, dtype=torch.float64, device=dev)[None, None, :]
            # Source point p of view point q: p = q - v (g.q + e) / (1 + g.v), the closed-form
            # inverse of q = p + v (d(p) - focus) for a plane d(p) = g.p + e + focus.
            e = lay.disparity - focus - gy * cy - gx * cx
            vy, vx = v[:, 1, None, None].to(dev), v[:, 0, None, None].to(dev)
            sc = (gy * qy + gx * qx + e) / (1 + gy * vy + gx * vx)  # [S,h|1,w|1]
            py = (qy - vy * sc - lay.top) * (2 / max(h - 1, 1)) - 1
            px = (qx - vx * sc - lay.left) * (2 / max(w - 1, 1)) - 1
            grid = torch.empty(s, y1 - y0, x1 - x0, 2, device=dev)
            # Both coordinates vary along one axis only (no x slope), so they stay small
            # until this broadcast copy.
            grid[..., 0].copy_(px)
            grid[..., 1].copy_(py)
            warped = F.grid_sample(tex.expand(s, -1, -1, -1), grid, align_corners=True)
            win = acc[:, :, y0:y1, x0:x1]
            if k == 0:
                win.copy_(warped[:, :3])
            else:
                win.mul_(1 - warped[:, 3:]).add_(warped[:, :3])
        total += acc.sum(0, dtype=torch.float64)
    return (total / n).float().permute(1, 2, 0).cpu().numpy()
