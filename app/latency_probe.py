"""The browser side of the latency bench: a headless Chromium page that uploads, clicks and drags
like a user and reads when each result is on screen.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from app.latency_server import BenchError, Server, start_app, wait_idle

CHROMIUM = "/usr/bin/chromium"


#: Launch flags that work with Debian's Chromium as root (no sandbox, nothing online).
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]


#: The status line of a full-resolution render, and every "<n> ms" figure in it.
FULL_RENDER_RE = r"\bfull render \d+ ms"


MS_RE = re.compile(r"(\d+(?:\.\d+)?) ms\b")


#: Click-to-focus points as fractions of the photo: the motorcycle, the wall behind it, the
#: floor in front, the right edge; consecutive points lie at different depths.
CLICK_POINTS = ((0.5, 0.55), (0.08, 0.1), (0.35, 0.92), (0.93, 0.35))


#: The "Advanced" accordion's toggle over the status line (``#info``), closed on a new page:
#: the status line is in the page only while it is open.
DETAILS_TOGGLE = "#details > button.label-wrap"


def show_details(page) -> None:
    """Open the "Advanced" accordion of a new page, so that its status line can be read, and
    scroll back to the top, where the click scrolled from."""
    page.locator(DETAILS_TOGGLE).click()
    page.wait_for_selector("#info textarea")
    page.evaluate("() => window.scrollTo(0, 0)")


#: Size (W, H) of the thumbnails of the result picture that tell whether an action changed
#: it: the mean absolute difference of the grey levels is ``picture_diff``.
THUMB_SIZE = (64, 48)


#: One drag step moves the mouse this fraction of the slider track (at least 6 px).
STEP_FRACTION = 0.03


#: Records, in the page, the input events, every picture loaded in ``#result`` and every
#: change of the status line, each with ``performance.now()``.
PAGE_PROBE = """
(() => {
    const b = (window.__bench = {events: [], loads: [], status: []});
    const owner = (el) => (el && el.closest ? el.closest("#input, #focus, #blur, #result") : null);
    const info = () => {
        const el = document.querySelector("#info textarea");
        return el ? el.value : null;
    };
    for (const type of ["pointerdown", "pointermove", "pointerup", "click", "change"]) {
        document.addEventListener(type, (e) => {
            const host = owner(e.target);
            b.events.push({type, t: performance.now(), id: host ? host.id : ""});
        }, true);
    }
    document.addEventListener("load", (e) => {
        const img = e.target;
        if (img.tagName === "IMG" && img.closest("#result")) {
            b.loads.push({t: performance.now(), src: img.getAttribute("src"),
                          w: img.naturalWidth, status: info()});
        }
    }, true);
    let last = null;
    setInterval(() => {
        const v = info();
        if (v !== last) { last = v; b.status.push({t: performance.now(), value: v}); }
    }, 5);
})();
"""


#: True once ``#result`` shows a new picture loaded after ``since`` (and the status matches
#: ``pattern`` when given), or the status changed to an error, or (``sameOk``) the status
#: changed while the same picture stayed for 0.5 s: the event ended without a new picture.
WAIT_JS = """
([since, old, oldStatus, pattern, sameOk]) => {
    const b = window.__bench;
    const el = document.querySelector("#info textarea");
    const now = el ? el.value : "";
    const img = document.querySelector("#result img");
    const src = img ? img.getAttribute("src") : null;
    if (now !== oldStatus && now.startsWith("Error")) return true;
    if (!pattern || new RegExp(pattern).test(now)) {
        if (b.loads.some((l) => l.t >= since && l.src !== old && l.w > 0 && l.src === src))
            return true;
    }
    return sameOk && src === old && b.status.some(
        (s) => s.t >= since && s.value !== oldStatus && performance.now() - s.t > 500);
}
"""


def photo_point(page, fx: float, fy: float) -> tuple[float, float]:
    """Where fraction ``(fx, fy)`` of the photo's pixels is on ``#input img``, relative to the
    element (the panel letterboxes the photo and scales it down, never up)."""
    box = page.evaluate(
        """() => {
            const img = document.querySelector('#input img');
            const r = img.getBoundingClientRect();
            return {w: r.width, h: r.height, nw: img.naturalWidth, nh: img.naturalHeight};
        }"""
    )
    scale = min(box["w"] / box["nw"], box["h"] / box["nh"], 1.0)
    x = (box["w"] - box["nw"] * scale) / 2 + fx * box["nw"] * scale
    y = (box["h"] - box["nh"] * scale) / 2 + fy * box["nh"] * scale
    return x, y


class Probe:
    """The page with :data:`PAGE_PROBE` installed: actions, and the times the page saw."""

    def __init__(self, page, server: Server, timeout_ms: float):
        self.page = page
        self.server = server
        self.timeout_ms = timeout_ms
        #: thumbnail of the picture the last action showed
        self.last: np.ndarray | None = None

    def state(self) -> tuple[str | None, str]:
        return self.page.evaluate(
            """() => [document.querySelector('#result img')?.getAttribute('src') ?? null,
                      document.querySelector('#info textarea')?.value ?? '']"""
        )

    def event_count(self) -> int:
        return self.page.evaluate("() => window.__bench.events.length")

    def event_time(self, start: int, kind: str, owner: str) -> float:
        """``performance.now()`` of the first ``kind`` event on ``#owner`` from index
        ``start`` of the recorded events."""
        t = self.page.evaluate(
            """([start, kind, owner]) => {
                const e = window.__bench.events.slice(start)
                    .find((e) => e.type === kind && e.id === owner);
                return e ? e.t : null;
            }""",
            [start, kind, owner],
        )
        if t is None:
            raise BenchError(f"the page saw no {kind} on #{owner}")
        return float(t)

    def wait_result(
        self,
        since: float,
        old: tuple[str | None, str],
        what: str,
        pattern: str | None = None,
        same_ok: bool = False,
        timeout_ms: float | None = None,
    ) -> dict[str, Any]:
        """Wait for the picture after an action at page time ``since``; return ``{"ms",
        "new_src", "picture_diff", "status", "server_ms"}``: ``picture_diff`` is the mean
        absolute grey-level difference of the picture's thumbnail from the one shown after
        the previous action (None for the first). ``old`` is :meth:`state` before it."""
        old_src, old_status = old
        timeout = timeout_ms or self.timeout_ms
        try:
            self.page.wait_for_function(
                WAIT_JS,
                arg=[since, old_src, old_status, pattern, same_ok],
                timeout=timeout,
                polling=20,
            )
        except Exception as err:  # playwright's TimeoutError, or the page gone
            src, status = self.state()
            raise BenchError(
                f"{what}: no new picture within {timeout / 1000:.0f} s "
                f"(status {status!r}, src changed: {src != old_src}); "
                f"app log:\n{self.server.log.read_text()[-2000:]}"
            ) from err
        src, status = self.state()
        if status != old_status and status.startswith("Error"):
            raise BenchError(f"{what}: the app says {status!r}")
        end = self.page.evaluate(
            """([since, old, src]) => {
                const b = window.__bench;
                const l = b.loads.find((l) => l.t >= since && l.src !== old && l.src === src
                                              && l.w > 0);
                if (l) return l.t;
                const s = b.status.find((s) => s.t >= since);
                return s ? s.t : null;
            }""",
            [since, old_src, src],
        )
        thumb = self.thumbnail()
        diff = None if self.last is None else float(np.abs(thumb - self.last).mean())
        self.last = thumb
        return {
            "ms": float(end) - since,
            "new_src": src != old_src,
            "picture_diff": diff,
            "status": status,
            "server_ms": sum(float(v) for v in MS_RE.findall(status)) or None,
        }

    def thumbnail(self) -> np.ndarray:
        """The result picture at :data:`THUMB_SIZE`, grey levels 0-255 (read in the page,
        after the timing, so whatever URL the app gives it)."""
        grey = self.page.evaluate(
            """([w, h]) => {
                const img = document.querySelector('#result img');
                const c = document.createElement('canvas');
                c.width = w;
                c.height = h;
                const g = c.getContext('2d');
                g.drawImage(img, 0, 0, w, h);
                const d = g.getImageData(0, 0, w, h).data;
                const out = [];
                for (let i = 0; i < d.length; i += 4) out.push((d[i] + d[i + 1] + d[i + 2]) / 3);
                return out;
            }""",
            list(THUMB_SIZE),
        )
        return np.asarray(grey, np.float32)

    # ------------------------------------------------------------------ actions
    def upload(self, path: Path, timeout_ms: float) -> dict[str, Any]:
        """Upload ``path``; :meth:`wait_result`'s figures of its full render, and
        ``first_ms``: the time to the first picture (a large photo's first look)."""
        old = self.state()
        start = self.event_count()
        self.page.set_input_files("#input input[type=file]", str(path))
        since = self.event_time(start, "change", "input")
        out = self.wait_result(since, old, f"upload of {path.name}", FULL_RENDER_RE,
                               timeout_ms=timeout_ms)  # fmt: skip
        out["first_ms"] = self.first_picture_ms(since, old[0], out["ms"])
        # the photo panel's picture is what the next click lands on
        self.page.wait_for_function(
            "() => { const i = document.querySelector('#input img');"
            " return i && i.complete && i.naturalWidth > 0; }",
            timeout=self.timeout_ms,
        )
        return out

    def click_photo(self, fx: float, fy: float) -> dict[str, Any]:
        """Click the photo at fraction ``(fx, fy)`` of its pixels (:func:`photo_point`)."""
        x, y = photo_point(self.page, fx, fy)
        old = self.state()
        start = self.event_count()
        self.page.locator("#input img").click(position={"x": x, "y": y})
        since = self.event_time(start, "click", "input")
        out = self.wait_result(since, old, "click on the photo", FULL_RENDER_RE, same_ok=True)
        out["first_ms"] = self.first_picture_ms(since, old[0], out["ms"])
        return out

    def first_picture_ms(self, since: float, old_src: str | None, full_ms: float) -> float:
        """Time from ``since`` to the first new picture the result panel loaded (a large
        photo's first look), read from the page's records; ``full_ms`` when there was none
        before the full render."""
        t = self.page.evaluate(
            """([since, old]) => window.__bench.loads.find(
                (l) => l.t >= since && l.src !== old && l.w > 0)?.t ?? null""",
            [since, old_src],
        )
        return full_ms if t is None else min(float(t) - since, full_ms)

    def track(self) -> dict[str, float]:
        """The ``#blur`` track: its box and the thumb's place as a fraction of it."""
        return self.page.evaluate(
            """() => {
                const el = document.querySelector('#blur input[type=range]');
                const r = el.getBoundingClientRect();
                const lo = parseFloat(el.min), hi = parseFloat(el.max);
                return {x: r.x, y: r.y, w: r.width, h: r.height, value: el.value,
                        frac: (parseFloat(el.value) - lo) / (hi - lo)};
            }"""
        )

    def slider_value(self) -> str:
        return self.page.evaluate("() => document.querySelector('#blur input[type=range]').value")

    def drag(self, steps: int, direction: int) -> tuple[list[dict[str, Any]], dict[str, Any]]:
        """Press the ``#blur`` thumb, move ``steps`` steps (``direction`` +1 right, -1 left),
        each timed to its preview, and let go, timed to the full render."""
        mouse = self.page.mouse
        t = self.track()
        y = t["y"] + t["h"] / 2
        x = t["x"] + t["w"] * t["frac"]
        mouse.move(x, y)
        self.settle()
        old = self.state()
        start = self.event_count()
        mouse.down()
        if self.slider_value() != t["value"]:  # the press moved the thumb: let it render
            since = self.event_time(start, "pointerdown", "blur")
            self.wait_result(since, old, "press on the slider")
        self.settle()
        step_px = max(6.0, STEP_FRACTION * t["w"])
        moves = []
        for k in range(1, steps + 1):
            before = self.slider_value()
            old = self.state()
            start = self.event_count()
            mouse.move(x + direction * k * step_px, y)
            if self.slider_value() == before:
                raise BenchError(f"drag step {k} did not move the slider (value {before})")
            since = self.event_time(start, "pointermove", "blur")
            moves.append(self.wait_result(since, old, f"drag step {k}"))
            self.settle()
        old = self.state()
        start = self.event_count()
        mouse.up()
        since = self.event_time(start, "pointerup", "blur")
        release = self.wait_result(since, old, "slider release", FULL_RENDER_RE)
        self.settle()
        return moves, release

    def settle(self) -> None:
        wait_idle(self.server.process.pid)


@contextlib.contextmanager
def app_in_browser(
    folder: Path, threads: int, weights: str | None = None, chromium: str = CHROMIUM
) -> Iterator[SimpleNamespace]:
    """The real app (``python -m app``, its files in ``folder``) and a headless Chromium:
    yields ``run`` with ``run.server`` and ``run.browser``; both are closed afterwards, and
    ``run.tracebacks`` then counts the tracebacks in the app's log."""
    from playwright.sync_api import sync_playwright

    run = SimpleNamespace(server=start_app(folder, threads, weights), browser=None, tracebacks=0)
    try:
        with sync_playwright() as p:
            run.browser = p.chromium.launch(
                executable_path=chromium, headless=True, args=list(CHROMIUM_ARGS)
            )
            try:
                yield run
            finally:
                run.browser.close()
    finally:
        run.server.stop()
        run.tracebacks = run.server.log.read_text().count("Traceback")
