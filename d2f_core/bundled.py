"""The files that ship inside the package: the trained weights and the sample photos.

They live in the checkout's top-level ``assets/`` folder, which ``pyproject.toml`` maps to
the package ``d2f_core.assets``, so a wheel carries them as package data and an editable
install finds them in the checkout. They are found with :mod:`importlib.resources`, never
through a path relative to this file, so an installed ``d2f`` works from any directory.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path

__all__ = ["ASSETS_PACKAGE", "SAMPLE_SUFFIXES", "assets_dir", "sample_photos", "shipped_weights"]

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
