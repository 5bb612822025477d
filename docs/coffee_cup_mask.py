"""Write ``docs/coffee_cup_mask.png``: the cup of ``assets/samples/coffee.jpg`` painted white
(its rim, body and handle, by hand-placed ellipses), for the README's ``--sharp-mask`` example.

Run from the checkout: ``python docs/coffee_cup_mask.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

HERE = Path(__file__).resolve().parent


def cup_mask(width: int = 600, height: int = 400) -> np.ndarray:
    """``height x width`` uint8, 255 on the cup."""
    yy, xx = np.mgrid[0:height, 0:width]

    def ellipse(cx: float, cy: float, rx: float, ry: float) -> np.ndarray:
        return ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1.0

    rim = ellipse(291, 112, 121, 96)
    body = ellipse(291, 190, 112, 95) & (yy >= 112)
    handle = ellipse(228, 268, 36, 40)
    return ((rim | body | handle) * 255).astype(np.uint8)


if __name__ == "__main__":
    Image.fromarray(cup_mask()).save(HERE / "coffee_cup_mask.png", optimize=True)
