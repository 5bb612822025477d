"""Write ``docs/coffee_cup_mask.png``: the cup of ``assets/samples/coffee.jpg`` painted white
(its rim, body and handle, by hand-placed ellipses), for the README's ``--sharp-mask`` example.

Run from the checkout: ``python docs/coffee_cup_mask.py``.
"""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from d2f_core.bundled import coffee_cup_mask

HERE = Path(__file__).resolve().parent


if __name__ == "__main__":
    Image.fromarray(coffee_cup_mask()).save(HERE / "coffee_cup_mask.png", optimize=True)
