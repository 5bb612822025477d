"""The files that ship inside the package: the trained weights and the sample photos.

They live in the checkout's top-level ``assets/`` folder, which ``pyproject.toml`` maps to
the package ``d2f_core.assets``, so a wheel carries them as package data and an editable
install finds them in the checkout. They are found with :mod:`importlib.resources`, never
through a path relative to this file, so an installed ``d2f`` works from any directory.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

import numpy as np

__all__ = [
    "ASSETS_PACKAGE",
    "SAMPLE_SUFFIXES",
    "assets_dir",
    "coffee_cup_mask",
    "sample_photos",
    "shipped_weights",
]

#: The package the top-level ``assets/`` folder is installed as.
ASSETS_PACKAGE = "d2f_core.assets"
#: File types listed as sample photos.
SAMPLE_SUFFIXES = (".jpg", ".jpeg", ".png")


def assets_dir() -> Path:
    """The installed ``assets`` folder (``weights/``, ``samples/``) as a filesystem path.

    Raises:
        FileNotFoundError: the package was installed without its data (an editable install
            made before ``assets/`` was mapped into the package needs ``pip install -e .``
            again), or it is imported from a zip archive.
    """
    try:
        root = importlib.resources.files(ASSETS_PACKAGE)
    except ModuleNotFoundError as e:
        raise FileNotFoundError(
            f"the bundled assets ({ASSETS_PACKAGE}) are not installed; "
            "reinstall d2f (from a checkout: pip install -e .)"
        ) from e
    if not isinstance(root, Path):
        raise FileNotFoundError(
            f"the bundled assets ({ASSETS_PACKAGE}) are not plain files ({root!r}); "
            "install d2f into a folder rather than importing it from an archive"
        )
    return root


def shipped_weights() -> Path:
    """The trained weights that ship with d2f (``assets/weights/d2f_lite.pt``)."""
    return assets_dir() / "weights" / "d2f_lite.pt"


def sample_photos() -> list[Path]:
    """The bundled sample photos (``assets/samples/``), sorted by name."""
    folder = assets_dir() / "samples"
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in SAMPLE_SUFFIXES)


def coffee_cup_mask(width: int = 600, height: int = 400) -> np.ndarray:
    """The cup of the sample ``coffee.jpg`` (600x400; its rim, body and handle, by
    ellipses placed by hand), ``height x width`` uint8, 255 on the cup: the README's
    ``--sharp-mask`` example and ``d2f-bench standing``'s cup seen from above."""
    sy, sx = height / 400, width / 600
    yy, xx = np.mgrid[0:height, 0:width]
    yy, xx = yy / sy, xx / sx

    def ellipse(cx: float, cy: float, rx: float, ry: float) -> np.ndarray:
        return ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1.0

    rim = ellipse(291, 112, 121, 96)
    body = ellipse(291, 190, 112, 95) & (yy >= 112)
    handle = ellipse(228, 268, 36, 40)
    return ((rim | body | handle) * 255).astype(np.uint8)
