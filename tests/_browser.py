"""Helpers for the browser tests: wait for and read the result picture the real page shows
(as int16, so that differences of two pictures do not wrap)."""

from __future__ import annotations

import io
import urllib.request

import numpy as np
from PIL import Image

from app.latency_probe import show_details

TIMEOUT_MS = 30_000
#: The status line (``#info``) as the page holds it, a JavaScript expression.
STATUS = "(document.querySelector('#info textarea')?.value ?? '')"


def result_src(page, picture: str = "#result img") -> str | None:
    return page.evaluate("(sel) => document.querySelector(sel)?.getAttribute('src')", picture)


def wait_new_result(page, old: str | None, picture: str = "#result img") -> str:
    """Wait until ``picture`` (the result's ``#result img`` by default) shows a different,
    fully loaded file; return its src."""
    page.wait_for_function(
        """([old, sel]) => {
            const img = document.querySelector(sel);
            return img && img.getAttribute('src') && img.getAttribute('src') !== old
                && img.complete && img.naturalWidth > 0;
        }""",
        arg=[old, picture],
        timeout=TIMEOUT_MS,
    )
    return result_src(page, picture)


def changed_result(page, old: str | None) -> str:
    """The src of ``#result img`` once it is not ``old`` (it may have changed already)."""
    src = result_src(page)
    return wait_new_result(page, old) if src == old else src


def wait_full_result(page, old: str | None) -> str:
    """Wait until ``#result img`` shows a different, fully loaded file that is a full render
    at the focus the focus slider now shows (the status line says so), and return its src.

    Checked in one step in the page, so the src belongs to that status line: a render of
    older values that lands in between (e.g. the release of a slider whose number box had
    the keyboard focus when the photo was clicked, which the app follows with a render of
    the values on the page) is not taken for it."""
    handle = page.wait_for_function(
        r"""(old) => {
            const img = document.querySelector('#result img');
            const info = document.querySelector('#info textarea');
            const box = document.querySelector('#focus input[data-testid=number-input]');
            if (!img || !info || !box) return false;
            const src = img.getAttribute('src');
            if (!src || src === old || !img.complete || img.naturalWidth === 0) return false;
            const m = info.value.match(/focus (\d+\.\d+)/);
            if (!m || !info.value.includes('full render')) return false;
            return Math.abs(parseFloat(m[1]) - parseFloat(box.value)) < 0.002 ? src : false;
        }""",
        arg=old,
        timeout=TIMEOUT_MS,
    )
    return handle.json_value()


def fetch_image(page, src: str) -> np.ndarray:
    url = src if src.startswith("http") else page.url.rstrip("/") + "/" + src.lstrip("/")
    with urllib.request.urlopen(url, timeout=10) as r:
        return np.asarray(Image.open(io.BytesIO(r.read())).convert("RGB"), np.int16)


def open_app(
    browser,
    url: str,
    *,
    height: int = 900,
    errors: list | None = None,
    details: bool = True,
    **options,
):
    """A new page, 1400 x ``height``, on the app at ``url`` once its sliders are there, with
    the "Advanced" details (the status line ``#info``) opened unless ``details`` is false; the
    page's script errors are appended to ``errors`` when given. ``options`` go to
    ``browser.new_page``."""
    page = browser.new_page(viewport={"width": 1400, "height": height}, **options)
    if errors is not None:
        page.on("pageerror", lambda e: errors.append(str(e)))
    page.set_default_timeout(TIMEOUT_MS)
    page.goto(url)
    page.wait_for_selector("#focus input[type=range]")
    if details:
        show_details(page)
    return page


def click_photo_at(page, x: int, y: int) -> None:
    """Click photo pixel (x, y) of ``#input img``, undoing its letterboxed, scaled display."""
    box = page.evaluate(
        """() => {
            const img = document.querySelector('#input img');
            const r = img.getBoundingClientRect();
            return {w: r.width, h: r.height, nw: img.naturalWidth, nh: img.naturalHeight};
        }"""
    )
    scale = min(box["w"] / box["nw"], box["h"] / box["nh"], 1.0)
    ox = (box["w"] - box["nw"] * scale) / 2
    oy = (box["h"] - box["nh"] * scale) / 2
    pos = {"x": ox + (x + 0.5) * scale, "y": oy + (y + 0.5) * scale}
    page.locator("#input img").click(position=pos)


def type_value(page, elem: str, value: str) -> None:
    """Type ``value`` into slider ``#elem``'s number box and press Enter (its release)."""
    box = page.locator(f"#{elem} input[data-testid=number-input]")
    box.click()
    box.fill(value)
    box.press("Enter")


def wait_status(page, *parts: str, absent: str | None = None, old: str | None = None) -> str:
    """Wait until the status line holds every one of ``parts``, not ``absent`` and is not
    ``old``; return it."""
    page.wait_for_function(
        f"""([parts, absent, old]) => {{
            const s = {STATUS};
            return s !== old && parts.every(p => s.includes(p))
                && (absent === null || !s.includes(absent));
        }}""",
        arg=[list(parts), absent, old],
        timeout=TIMEOUT_MS,
    )
    return page.locator("#info textarea").input_value()
