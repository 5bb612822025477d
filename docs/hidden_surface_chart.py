"""Draw what the hidden surface changes: ``assets/charts/hidden_surface.png``.

    python docs/hidden_surface_chart.py [--data ../shared/data] [--out PATH]

Top row, a generated scene (``d2f_core.train.synth``): a near box blurred to a 28 px CoC in front
of a sharp striped wall, as the thin-lens ground truth sees it, then d2f's renderer without
and with the hidden surface (``rendering.render(..., hidden=False / True)``). Bottom row,
when the Google Lens Blur sample of ``--data`` is there: a crop of the photo around its near
lamp, then the pipeline's renders at K = 120 with the photo's own depth, focused on the far
wall, without and with it. Columns are separated by white.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from d2f_core import D2F, load_photo, rendering
from d2f_core.train.synth import Layer, Scene, render_pinhole, render_thin_lens

ROOT = Path(__file__).resolve().parents[1]
GAP = 6


def generated_row() -> list[np.ndarray]:
    """Truth, without, with: the striped wall behind a blurred near box (focus on the wall)."""
    h, w, m = 96, 128, 40
    yy, xx = np.mgrid[-m : h + m, -m : w + m]
    stripes = ((yy // 8) % 2).astype(np.float32) * 0.6 + 0.2 + 0 * xx
    rgb = np.stack([stripes, 1 - stripes, 0.4 + 0 * stripes]).astype(np.float32)
    wall = Layer(rgb, np.ones(rgb.shape[1:], np.float32), -m, -m, 0.2)
    box = (
        np.zeros((3, 40, 56), np.float32) + np.array([0.85, 0.25, 0.15], np.float32)[:, None, None]
    )
    scene = Scene([wall, Layer(box, np.ones((40, 56), np.float32), 28, 36, 0.9)], (h, w), m, 0.2)
    pinhole, disp = render_pinhole(scene)
    truth = np.clip(render_thin_lens(scene, 0.2, 40.0, samples=256), 0, 1)
    image = torch.from_numpy(np.clip(pinhole, 0, 1)).permute(2, 0, 1)[None].contiguous()
    d = torch.from_numpy(disp)[None, None]
    row = [truth]
    for hidden in (False, True):
        out = rendering.render(image, d, 0.2, 40.0, kernel="hard", hidden=hidden)
        row.append(out[0].permute(1, 2, 0).numpy())
    return [np.kron(x, np.ones((3, 3, 1))) for x in row]  # 3x, nearest: the rim stays visible


def photo_row(data: Path) -> list[np.ndarray] | None:
    """Photo, without, with: the Lens Blur sample's near lamp, focused on the far wall."""
    path = data / "google_lensblur_depthy" / "lensblur_sample.jpg"
    if not path.is_file():
        return None
    photo = load_photo(path)
    model = D2F.from_pretrained()
    scene = model.prepare(photo.image, disparity=photo.disparity)
    focus = float(model.focus_at(scene, 300, 150))
    crop = (slice(200, 700), slice(0, 330))
    image = np.asarray(photo.image)
    row = [image[crop] / 255.0 if image.dtype == np.uint8 else image[crop]]
    for hidden in (False, True):
        row.append(model.render(scene, focus, 120.0, hidden=hidden).bokeh[crop])
    return row


def _strip(row: list[np.ndarray], height: int) -> np.ndarray:
    parts = []
    for x in row:
        img = Image.fromarray((np.clip(x, 0, 1) * 255).round().astype(np.uint8))
        img = img.resize((round(img.width * height / img.height), height), Image.LANCZOS)
        parts += [np.asarray(img), np.full((height, GAP, 3), 255, np.uint8)]
    return np.concatenate(parts[:-1], axis=1)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    parser.add_argument(
        "--out", type=Path, default=ROOT / "assets" / "charts" / "hidden_surface.png"
    )
    args = parser.parse_args(argv)
    strips = [_strip(generated_row(), 240)]
    photo = photo_row(args.data)
    if photo is not None:
        strips.append(_strip(photo, 360))
    width = max(s.shape[1] for s in strips)
    rows = []
    for s in strips:
        pad = np.full((s.shape[0], width - s.shape[1], 3), 255, np.uint8)
        rows += [np.concatenate([s, pad], axis=1), np.full((GAP, width, 3), 255, np.uint8)]
    Image.fromarray(np.concatenate(rows[:-1], axis=0)).save(args.out, optimize=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
