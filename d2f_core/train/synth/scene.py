"""Random layered scenes: textures from real photos, shapes, HDR lights, a sloped ground."""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from .lens import Layer, Scene, srgb_to_linear

logger = logging.getLogger(__name__)

# Photos bundled with scikit-image (no download needed); grey ones are tinted when used.
_SKIMAGE_TEXTURES = (
    "astronaut",
    "coffee",
    "chelsea",
    "rocket",
    "immunohistochemistry",
    "colorwheel",
    "brick",
    "grass",
    "gravel",
    "camera",
    "moon",
    "coins",
)
_LIGHT_COLOURS = ((1.0, 0.78, 0.5), (1.0, 1.0, 1.0), (0.6, 0.75, 1.0), (1.0, 0.45, 0.35))


# --------------------------------------------------------------------------- textures


@functools.lru_cache(maxsize=1)
def builtin_textures() -> tuple[np.ndarray, ...]:
    """The photos bundled with scikit-image, float32 sRGB ``(h, w, 3)`` in [0, 1]."""
    import skimage.data

    out = []
    for name in _SKIMAGE_TEXTURES:
        try:
            img = np.asarray(getattr(skimage.data, name)())
        except Exception as err:  # an optional bundled file may be missing on some installs
            logger.debug("skimage texture %s unavailable: %s", name, err)
            continue
        out.append(_as_rgb_float(img))
    if not out:
        raise RuntimeError("no scikit-image textures could be loaded")
    return tuple(out)


def load_textures(directory: str | Path) -> list[np.ndarray]:
    """Read every PNG/JPEG in ``directory`` as float32 sRGB ``(h, w, 3)`` in [0, 1]."""
    from PIL import Image

    path = Path(directory)
    if not path.is_dir():
        raise ValueError(f"directory must be an existing folder, got {str(directory)!r}")
    out = []
    for f in sorted(path.iterdir()):
        if f.suffix.lower() in {".png", ".jpg", ".jpeg"}:
            with Image.open(f) as im:
                out.append(_as_rgb_float(np.asarray(im.convert("RGB"))))
    return out


def _as_rgb_float(img: np.ndarray) -> np.ndarray:
    img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 1.0)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return np.ascontiguousarray(img[..., :3])


def resize_image(img: np.ndarray, h: int, w: int) -> np.ndarray:
    """Bilinear, antialiased resize of an ``H x W x C`` float array to ``h x w x C``."""
    t = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
    t = F.interpolate(t, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return t[0].permute(1, 2, 0).numpy()


def texture(
    rng: np.random.Generator,
    textures: Sequence[np.ndarray],
    h: int,
    w: int,
    scale: tuple[float, float] = (0.4, 1.6),
) -> np.ndarray:
    """A jittered random crop, linear radiance ``(3, h, w)``."""
    tex = textures[rng.integers(len(textures))]
    th, tw = tex.shape[:2]
    s = max(rng.uniform(*scale) * max(h, w) / max(th, tw), (h + 1) / th, (w + 1) / tw)
    # Resize only the source window that the crop needs.
    ch, cw = min(th, math.ceil(h / s) + 2), min(tw, math.ceil(w / s) + 2)
    y, x = rng.integers(th - ch + 1), rng.integers(tw - cw + 1)
    img = resize_image(tex[y : y + ch, x : x + cw], math.ceil(ch * s), math.ceil(cw * s))[:h, :w]
    if rng.random() < 0.5:
        img = img[:, ::-1]
    grey = img.mean(axis=2, keepdims=True)
    tint = rng.uniform(0.55, 1.0, 3) if np.ptp(tex[::8, ::8].mean(axis=(0, 1))) < 1e-3 else 1.0
    sat = rng.uniform(0.6, 1.4)
    img = (grey + sat * (img - grey)) * tint * rng.uniform(0.85, 1.15, 3) * rng.uniform(0.6, 1.3)
    return srgb_to_linear(img).transpose(2, 0, 1).copy()


# --------------------------------------------------------------------------- shapes


def coverage(sd: np.ndarray) -> np.ndarray:
    """Antialiased coverage from a signed distance in px (negative inside)."""
    return np.clip(0.5 - sd, 0.0, 1.0).astype(np.float32)


def _segments_alpha(segs: np.ndarray, top: int, left: int, h: int, w: int) -> np.ndarray:
    """Union of capsules ``(y0, x0, y1, x1, width)`` rasterised in a crop."""
    yy, xx = np.mgrid[top : top + h, left : left + w].astype(np.float32)
    alpha = np.zeros((h, w), np.float32)
    for y0, x0, y1, x1, wd in segs:
        dy, dx = y1 - y0, x1 - x0
        t = np.clip(((yy - y0) * dy + (xx - x0) * dx) / max(dy * dy + dx * dx, 1e-9), 0, 1)
        dist = np.hypot(yy - (y0 + t * dy), xx - (x0 + t * dx))
        np.maximum(alpha, coverage(dist - wd / 2), out=alpha)
    return alpha


def _layer_from_segments(rng, textures, segs, disparity, kind, size, margin) -> Layer | None:
    segs = np.asarray(segs, np.float32)
    pad = float(segs[:, 4].max()) + 2
    top = int(math.floor(min(segs[:, 0].min(), segs[:, 2].min()) - pad))
    left = int(math.floor(min(segs[:, 1].min(), segs[:, 3].min()) - pad))
    bottom = int(math.ceil(max(segs[:, 0].max(), segs[:, 2].max()) + pad))
    right = int(math.ceil(max(segs[:, 1].max(), segs[:, 3].max()) + pad))
    top, left = max(top, -margin), max(left, -margin)
    bottom, right = min(bottom, size[0] + margin), min(right, size[1] + margin)
    if bottom - top < 2 or right - left < 2:
        return None
    alpha = _segments_alpha(segs, top, left, bottom - top, right - left)
    colour = texture(rng, textures, bottom - top, right - left) * rng.uniform(0.2, 1.0)
    return Layer(
        colour * alpha,
        alpha,
        top,
        left,
        disparity,
        kind=kind,
        info={"width_px": round(float(segs[:, 4].max()), 2)},
    )


def blob(rng, textures, cy, cx, radius, disparity, size, margin, striped=False) -> Layer:
    """A superellipse with a wavy rim, randomly stretched and rotated."""
    aspect, rot, p = rng.uniform(0.6, 1.6), rng.uniform(0, math.pi), rng.uniform(2.0, 5.0)
    k = np.arange(2, 6)
    amp, phase = rng.uniform(-0.08, 0.08, 4) / (k - 1), rng.uniform(0, 2 * math.pi, 4)
    ext = int(radius * max(aspect, 1 / aspect) * 1.5) + 3
    top, left = max(int(cy) - ext, -margin), max(int(cx) - ext, -margin)
    h = min(int(cy) + ext, size[0] + margin) - top
    w = min(int(cx) + ext, size[1] + margin) - left
    if h <= 0 or w <= 0:
        # centre so far outside that the blob misses the content area: keep a 1-px box at
        # the nearest border (its coverage there is ~0) instead of an empty array
        top = min(max(top, -margin), size[0] + margin - 1)
        left = min(max(left, -margin), size[1] + margin - 1)
        h, w = max(h, 1), max(w, 1)
    yy, xx = np.mgrid[top : top + h, left : left + w].astype(np.float32)
    y, x = yy - cy, xx - cx
    u = (x * math.cos(rot) + y * math.sin(rot)) / math.sqrt(aspect)
    v = (-x * math.sin(rot) + y * math.cos(rot)) * math.sqrt(aspect)
    theta = np.arctan2(v, u)
    norm = (np.abs(u) ** p + np.abs(v) ** p) ** (1 / p)
    rim = radius * (
        1 + (amp[:, None, None] * np.cos(k[:, None, None] * theta + phase[:, None, None])).sum(0)
    )
    alpha = coverage(norm - rim)
    if striped:
        c = srgb_to_linear(rng.uniform(0.05, 0.95, (2, 3)))
        period, ang = rng.uniform(4, 16), rng.uniform(0, math.pi)
        phase_px = (xx * math.cos(ang) + yy * math.sin(ang)) / period
        mix = np.clip(2.5 * np.sin(2 * math.pi * phase_px) + 0.5, 0, 1)[None]
        rgb = c[0][:, None, None] * mix + c[1][:, None, None] * (1 - mix)
    else:
        rgb = texture(rng, textures, h, w)
    shade = np.clip(1.1 - 0.35 * (norm / np.maximum(rim, 1e-3)) ** 2, 0.6, 1.0)
    kind = "stripes" if striped else "blob"
    return Layer(
        (rgb * shade * alpha).astype(np.float32),
        alpha,
        top,
        left,
        disparity,
        kind=kind,
        info={"radius_px": round(float(radius), 1)},
    )


def _branch_segments(rng, size, margin) -> list:
    height, width = size
    side = rng.integers(4)
    along = rng.uniform(0.1, 0.9)
    start = [
        (-margin, along * width),
        (height + margin, along * width),
        (along * height, -margin),
        (along * height, width + margin),
    ][side]
    angle = [math.pi / 2, -math.pi / 2, 0.0, math.pi][side] + rng.uniform(-0.6, 0.6)
    segs, stack = (
        [],
        [(start[0], start[1], angle, rng.uniform(0.35, 0.6) * max(size), rng.uniform(2.0, 3.0), 0)],
    )
    while stack:
        y, x, ang, length, wd, depth = stack.pop()
        # A few kinks per limb look more like wood than a straight capsule.
        for _ in range(3):
            ang += rng.uniform(-0.25, 0.25)
            ny, nx = y + math.sin(ang) * length / 3, x + math.cos(ang) * length / 3
            segs.append((y, x, ny, nx, wd))
            y, x = ny, nx
        if depth < 3:
            for sgn in (-1, 1):
                if rng.random() < 0.85:
                    stack.append(
                        (
                            y,
                            x,
                            ang + sgn * rng.uniform(0.3, 0.9),
                            length * rng.uniform(0.5, 0.75),
                            max(1.0, wd - 0.6),
                            depth + 1,
                        )
                    )
    return segs


def _fence(rng, textures, disparity, size, margin) -> Layer:
    height, width = size
    slat = rng.uniform(1.0, 6.0)
    period = slat + rng.uniform(2.0, 3.0 * slat + 6.0)
    ang = rng.uniform(-0.3, 0.3) + (math.pi / 2 if rng.random() < 0.3 else 0.0)
    top = int(rng.uniform(-margin, 0.5 * height))
    bottom = int(rng.uniform(top + 0.3 * height, height + margin))
    left = int(rng.uniform(-margin, 0.4 * width))
    right = int(rng.uniform(left + 0.3 * width, width + margin))
    h, w = bottom - top, right - left
    yy, xx = np.mgrid[top:bottom, left:right].astype(np.float32)
    t = (xx * math.cos(ang) + yy * math.sin(ang)) / period
    dist = np.abs(t - np.round(t)) * period
    alpha = coverage(dist - slat / 2)
    rgb = texture(rng, textures, h, w) * rng.uniform(0.3, 1.0)
    return Layer(
        rgb * alpha,
        alpha,
        top,
        left,
        disparity,
        kind="fence",
        info={"slat_px": round(slat, 2), "period_px": round(period, 2)},
    )


def lights(rng, disparity, size, margin, group) -> list[Layer]:
    """A group of small emitters at one disparity, one tiny layer each (a single sparse
    layer spanning the frame would cost a full-frame warp per aperture point)."""
    height, width = size
    count = int(rng.integers(3, 30))
    if rng.random() < 0.5:  # a string of lights along a gentle curve
        xs = np.linspace(rng.uniform(-margin, 0.3 * width), rng.uniform(0.7 * width, width), count)
        ys = rng.uniform(0.1, 0.8) * height + rng.uniform(-0.15, 0.15) * height * np.sin(
            xs / width * rng.uniform(2, 6) + rng.uniform(0, 6)
        )
    else:
        ys, xs = rng.uniform(0, height, count), rng.uniform(0, width, count)
    radii = rng.uniform(0.6, 2.5, count)
    base = np.array(_LIGHT_COLOURS[rng.integers(len(_LIGHT_COLOURS))], np.float32)
    radiance = np.exp(rng.uniform(math.log(3), math.log(30), count))
    layers = []
    for y, x, r, q in zip(ys, xs, radii, radiance, strict=True):
        top, left = int(math.floor(y - r)) - 2, int(math.floor(x - r)) - 2
        side = int(math.ceil(2 * r)) + 5
        yy, xx = np.mgrid[top : top + side, left : left + side].astype(np.float32)
        cov = coverage(np.hypot(yy - y, xx - x) - r)
        colour = base * rng.uniform(0.85, 1.0, 3) if rng.random() < 0.8 else rng.uniform(0.3, 1, 3)
        rgb = (cov[None] * (q * colour)[:, None, None]).astype(np.float32)
        info = {"group": group, "radiance": round(float(q), 2)}
        layers.append(Layer(rgb, cov, top, left, disparity, kind="light", info=info))
    return layers


def describe_layers(layers: Sequence[Layer]) -> list[dict]:
    """Layer summaries for the JSON; each light group and the ground's pieces are folded into
    one entry each (the ground's ``order`` lists its pieces' sort keys)."""
    out, groups = [], {}
    for lay in layers:
        if lay.kind == "light":
            key = ("light", lay.info["group"])
            if key not in groups:
                groups[key] = {
                    "kind": "lights",
                    "disparity": round(float(lay.order), 4),
                    "count": 0,
                    "radiance_max": 0.0,
                }
                out.append(groups[key])
            entry = groups[key]
            entry["count"] += 1
            entry["radiance_max"] = max(entry["radiance_max"], lay.info["radiance"])
        elif lay.kind == "ground":
            if "ground" not in groups:
                groups["ground"] = lay.describe() | {"pieces": 0, "order": []}
                out.append(groups["ground"])
            entry = groups["ground"]
            entry["pieces"] += 1
            entry["order"].append(round(float(lay.order), 4))
            top, _, h, _ = entry["box"]
            bottom = max(top + h, lay.top + lay.shape[0])
            entry["box"][0] = min(top, lay.top)
            entry["box"][2] = bottom - entry["box"][0]
        else:
            out.append(lay.describe())
    return out


def trim(layer: Layer) -> Layer:
    """Crop a layer to its non-transparent box plus a 1 px transparent rim."""
    rows, cols = np.flatnonzero(layer.alpha.any(1)), np.flatnonzero(layer.alpha.any(0))
    if rows.size == 0:
        return layer
    h, w = layer.shape
    y0, y1 = max(rows[0] - 1, 0), min(rows[-1] + 2, h)
    x0, x1 = max(cols[0] - 1, 0), min(cols[-1] + 2, w)
    layer.rgb = np.ascontiguousarray(layer.rgb[:, y0:y1, x0:x1])
    layer.alpha = np.ascontiguousarray(layer.alpha[y0:y1, x0:x1])
    layer.top, layer.left = layer.top + int(y0), layer.left + int(x0)
    return layer


def _ground(rng, textures, horizon, d_far, d_near, cuts, size, margin) -> list[Layer]:
    """A textured ground plane from ``horizon`` (row) down, disparity linear in the row, cut
    into pieces at ``cuts`` (other layers' disparities) so depth order holds at each cut."""
    height, width = size
    slope = (d_near - d_far) / (height - 1 - horizon)
    cy = (height - 1) / 2
    d_centre = d_far + slope * (cy - horizon)
    top, bottom = int(math.floor(horizon)), height + margin
    left, w = -margin, width + 2 * margin
    rows = np.arange(top, bottom, dtype=np.float32)
    d_rows = np.maximum(d_far + slope * (rows - horizon), 1e-3)
    # Perspective texture lookup: world (X, Z) ~ ((x - cx) / d, 1 / d).
    tex = texture(rng, textures, 256, 256, scale=(1.0, 1.0))
    scale = rng.uniform(0.15, 0.5)
    xs = np.arange(left, left + w, dtype=np.float32) - (width - 1) / 2
    # Random offsets keep the mirror tiling's seams away from the vanishing point.
    u = (xs[None, :] / d_rows[:, None]) * scale / 128 + rng.uniform(0, 4)
    v = (1 / d_rows[:, None]) * scale * 1.2 * np.ones_like(u) + rng.uniform(0, 4)
    grid = torch.from_numpy(np.stack([u, v], axis=-1) % 4 - 1)[None].float()
    grid = torch.where(grid > 1, 2 - grid, grid)  # mirror tiling
    rgb = F.grid_sample(torch.from_numpy(tex)[None], grid, align_corners=False)[0].numpy()
    # Haze towards the horizon hides the aliasing of the compressed far texture.
    haze = np.clip((d_near - d_rows) / (d_near - d_far), 0, 1)[None, :, None] ** 3 * 0.85
    rgb = rgb * (1 - haze) + rgb.mean(axis=(1, 2), keepdims=True) * haze
    alpha = np.ones((len(rows), w), np.float32)
    alpha[0] = np.float32(1 - (horizon - top))
    splits = sorted(horizon + (c - d_far) / slope for c in cuts if d_far < c < d_rows[-1])
    bounds = [top] + [int(math.ceil(r)) for r in splits] + [bottom]
    layers = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b <= a:
            continue
        # The farther piece runs 2 rows under the nearer one so the seam stays opaque.
        b_ext = min(b + 2, bottom)
        sl = slice(a - top, b_ext - top)
        mid = d_far + slope * ((a + b - 1) / 2 - horizon)
        layers.append(
            Layer(
                (rgb[:, sl] * alpha[sl]).astype(np.float32),
                alpha[sl].copy(),
                a,
                left,
                d_centre,
                (slope, 0.0),
                kind="ground",
                order=float(mid),
            )
        )
    return layers


# --------------------------------------------------------------------------- scenes


def make_scene(
    size: tuple[int, int] = (512, 512),
    *,
    seed: int,
    margin: int | None = None,
    textures: Sequence[np.ndarray] | None = None,
) -> Scene:
    """A random layered scene. Same ``(size, seed, margin, textures)`` -> identical scene.

    Args:
        size: view (H, W) in px, each >= 16.
        seed: RNG seed.
        margin: content beyond the view on each side (px); it must be >= the largest blur
            radius K / 2 used to render. Default ``ceil(0.06 * max(size)) + 2``.
        textures: sRGB float images ``(h, w, 3)`` in [0, 1]; default the scikit-image photos.
    """
    if len(size) != 2 or min(size) < 16:
        raise ValueError(f"size must be (H, W) with both >= 16, got {size!r}")
    height, width = int(size[0]), int(size[1])
    size = (height, width)
    margin = math.ceil(0.06 * max(size)) + 2 if margin is None else int(margin)
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin!r}")
    textures = builtin_textures() if textures is None else tuple(textures)
    if not textures:
        raise ValueError("textures must not be empty")
    rng = np.random.default_rng(seed)
    short = min(size)

    night = rng.random() < 0.3
    d_bg = rng.uniform(0.0, 0.12)
    bg = texture(rng, textures, height + 2 * margin, width + 2 * margin, scale=(1.0, 2.5))
    bg *= rng.uniform(0.05, 0.3) if night else 1.0
    layers = [
        Layer(
            bg,
            np.ones(bg.shape[1:], np.float32),
            -margin,
            -margin,
            d_bg,
            kind="background",
            info={"night": bool(night)},
        )
    ]

    d_subject = rng.uniform(0.45, 0.9)
    ground = rng.random() < 0.6
    horizon = rng.uniform(0.3, 0.7) * height
    d_far, d_near = min(d_bg + rng.uniform(0.02, 0.12), 0.3), rng.uniform(0.5, 0.95)
    d_near = max(d_near, d_far + 0.2)
    # Keep the plane's disparity <= 1 down to the bottom of the margin as well.
    ratio = margin / (height - 1 - horizon)
    d_near = min(d_near, (1 + d_far * ratio) / (1 + ratio))

    def base_row(d: float) -> float:
        return horizon + (d - d_far) / (d_near - d_far) * (height - 1 - horizon)

    objects: list[Layer] = []
    for i in range(int(rng.integers(2, 6)) + 1):
        subject = i == 0
        d = d_subject if subject else rng.uniform(d_bg + 0.05, d_subject)
        radius = (rng.uniform(0.12, 0.3) if subject else rng.uniform(0.05, 0.18)) * short
        cx = rng.uniform(0.3, 0.7) * width if subject else rng.uniform(-0.1, 1.1) * width
        cy = rng.uniform(0.35, 0.65) * height
        if ground and d_far < d < d_near and rng.random() < 0.7:
            cy = base_row(d) - 0.8 * radius  # stands on the ground at its own depth
        lay = blob(
            rng,
            textures,
            cy,
            cx,
            radius,
            d,
            size,
            margin,
            striped=rng.random() < (0.25 if subject else 0.15),
        )
        if subject:
            lay.info["subject"] = True
        objects.append(lay)
    for _ in range(int(rng.integers(0, 3))):  # poles and wires
        y0, x0 = rng.uniform(-0.1, 1.1, 2) * size
        ang, length = rng.uniform(0, math.pi), rng.uniform(0.3, 1.2) * max(size)
        seg = [
            (
                y0,
                x0,
                y0 + math.sin(ang) * length,
                x0 + math.cos(ang) * length,
                rng.uniform(1.0, 3.0),
            )
        ]
        lay = _layer_from_segments(
            rng, textures, seg, rng.uniform(d_bg + 0.05, 1.0), "bar", size, margin
        )
        objects += [lay] if lay is not None else []
    if rng.random() < 0.5:
        d = rng.uniform(d_bg + 0.05, 1.0) if rng.random() < 0.5 else rng.uniform(d_subject, 1.0)
        lay = _layer_from_segments(
            rng, textures, _branch_segments(rng, size, margin), d, "branch", size, margin
        )
        objects += [lay] if lay is not None else []
    if rng.random() < 0.3:
        objects.append(_fence(rng, textures, rng.uniform(d_bg + 0.05, 1.0), size, margin))
    for group in range(int(rng.integers(0, 4)) if not night else int(rng.integers(1, 4))):
        d = rng.uniform(d_bg, d_subject - 0.1) if rng.random() < 0.8 else rng.uniform(0, 1)
        objects += lights(rng, d, size, margin, group)

    if ground:
        layers += _ground(
            rng, textures, horizon, d_far, d_near, [o.order for o in objects], size, margin
        )
    layers += objects
    layers[1:] = sorted((trim(lay) for lay in layers[1:]), key=lambda lay: lay.order)
    return Scene(layers, size, margin, float(d_subject), seed)
