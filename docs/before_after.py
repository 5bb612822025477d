"""Make the README's before/after picture from a bundled sample photo.

    python docs/before_after.py                     # -> out/before_after.jpg
    python docs/before_after.py --readme            # -> assets/charts/before_after.jpg
    python docs/before_after.py --photo chelsea.jpg --blur 40 --out /tmp/cat.jpg

The photo (left) and d2f's render (right) with the shipped weights and their own depth
estimate, focused on the subject the disparity map shows with the focal range that keeps it
sharp (``D2F.default_focus``), as the library, the CLI and the app do when no focus is given.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from d2f_core import D2F, load_image, save_image
from d2f_core.bundled import sample_photos

ROOT = Path(__file__).resolve().parents[1]
#: the regions of ``coffee.jpg`` whose detail the README gives: (x0, x1, y0, y1)
COFFEE_REGIONS = {"rim": (185, 395, 25, 75), "handle": (195, 260, 230, 305)}


def detail(out: np.ndarray, photo: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """The mean gradient (Sobel, of the grey image) of ``out`` inside ``box`` against the
    photo's: 1 keeps all the detail, 0 none."""
    from scipy.ndimage import sobel

    def gradient(a: np.ndarray) -> np.ndarray:
        g = a.mean(axis=-1)
        return np.hypot(sobel(g, 0), sobel(g, 1))

    x0, x1, y0, y1 = box
    return float(gradient(out)[y0:y1, x0:x1].mean() / gradient(photo)[y0:y1, x0:x1].mean())


#: The README's picture, tracked by git: written only with ``--readme``.
README_PICTURE = ROOT / "assets" / "charts" / "before_after.jpg"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--photo", default="coffee.jpg", help="a bundled sample's file name")
    p.add_argument("--blur", type=float, default=60.0, help="K, px at |d - focus| = 1")
    p.add_argument("--gap", type=int, default=6, help="white px between the two")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--out", type=Path, help="the picture (default: out/before_after.jpg)")
    where.add_argument("--readme", action="store_true", help=f"write {README_PICTURE.name} "
                       "in assets/charts/, the README's picture")  # fmt: skip
    return p


def output_path(args: argparse.Namespace) -> Path:
    """Where the picture goes: the README's only when asked (``--readme``)."""
    if args.readme:
        return README_PICTURE
    return args.out if args.out is not None else ROOT / "out" / "before_after.jpg"


def main(argv: list[str] | None = None) -> None:
    cli = parser()
    args = cli.parse_args(argv)
    args.out = output_path(args)
    args.out.parent.mkdir(parents=True, exist_ok=True)

    by_name = {p.name: p for p in sample_photos()}
    if args.photo not in by_name:
        cli.error(f"--photo must be one of {sorted(by_name)}, got {args.photo!r}")
    photo = load_image(by_name[args.photo])  # H x W x 3 float32 in [0, 1]
    model = D2F.from_pretrained()
    scene = model.prepare(photo)
    focus, focal_range, (x, y), _ = model.default_focus(scene)
    bokeh = model.render(scene, focus, args.blur, focal_range=focal_range).bokeh  # [0, 1]
    gap = np.ones((photo.shape[0], args.gap, 3), np.float32)
    save_image(args.out, np.concatenate([photo, gap, bokeh], axis=1), quality=88)
    print(
        f"{args.out}: {args.photo}, focus {focus:.3f} at ({x:.0f}, {y:.0f}), focal range "
        f"{focal_range:.3f}, K = {args.blur:g}"
    )
    if args.photo == "coffee.jpg":
        thin = model.render(scene, focus, args.blur, focal_range=0.0).bokeh
        for name, box in COFFEE_REGIONS.items():
            print(
                f"{name}'s detail against the photo's: {detail(bokeh, photo, box):.2f} "
                f"({detail(thin, photo, box):.2f} with no focal range)"
            )


if __name__ == "__main__":
    main()
