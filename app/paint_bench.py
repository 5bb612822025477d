"""The brushes' Apply against a click, in the browser: ``python -m app.paint_bench``.

Starts the real app (``python -m app``), opens it in headless Chromium (Playwright, Debian's
``/usr/bin/chromium``), uploads one photo (``--photo``; by default a generated 4000x3000
JPEG of the motorcycle) and then, round by round, in turns:

* ``click``: a click on the photo (click-to-focus) -> its full-resolution picture shown;
* ``apply``: two strokes of the keep-sharp brush on the brushes' canvas, then **Apply paint**
  -> the painted full-resolution picture shown. The time runs from the click on Apply; the
  strokes themselves are not counted.

Both ends are read in the page (``performance.now()`` of the click and of the result image's
``load``). While an action runs, the bench makes a script call into the page every 0.25 s and
times its answer: a call that waits is the page frozen (its main thread busy). The longest
wait of each action is printed as ``page pause``, and each action's phases from the page's own
requests: the time before its first request (for Apply, the editor exporting its layers), the
uploads and their size, the time they were done. The load average is printed before and after;
nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from app.latency_probe import (
    FULL_RENDER_RE,
    PAGE_PROBE,
    app_in_browser,
    photo_point,
    show_details,
)
from app.latency_server import BenchError, commit, loadavg, wait_idle, write_photos

#: Records clicks on the Apply button with their page time (PAGE_PROBE records the others),
#: and every request the page makes with ``fetch``: its start and end, URL and body size.
APPLY_PROBE = """
(() => {
    window.__applies = [];
    window.__fetches = [];
    document.addEventListener("click", (e) => {
        if (e.target.closest && e.target.closest("#paint_apply"))
            window.__applies.push(performance.now());
    }, true);
    const plain = window.fetch;
    window.fetch = async function (input, init) {
        const url = typeof input === "string" ? input : (input && input.url) || String(input);
        const body = init && init.body;
        let bytes = 0;
        if (body instanceof FormData) {
            for (const [, v] of body.entries()) bytes += v.size || String(v).length;
        } else if (body) bytes = body.size || String(body).length;
        const r = {url, t0: performance.now(), t1: null, bytes};
        window.__fetches.push(r);
        const response = await plain.apply(this, arguments);
        r.t1 = performance.now();
        return response;
    };
})();
"""

#: The phases of an action, from the page's requests between its start and its picture:
#: the first request (what the page did before it: the editor's export of its layers), the
#: uploads (``/upload``), and the rest (the queue, the server's work, the picture's fetch).
PHASES_JS = """
([since, end]) => {
    const f = window.__fetches.filter((r) => r.t0 >= since && r.t0 <= end);
    const up = f.filter((r) => r.url.includes("/upload"));
    const first = f.length ? f[0].t0 - since : null;
    const upEnd = up.length ? Math.max(...up.map((r) => r.t1 || end)) - since : null;
    return {before_first_request_ms: first, uploads: up.length,
            upload_bytes: up.reduce((a, r) => a + r.bytes, 0),
            uploads_done_ms: upEnd};
}
"""

#: True once ``#result`` shows a new picture loaded after ``since`` with a full render named
#: in the status line (or the status line says Error).
DONE_JS = """
([since, old, pattern]) => {
    const el = document.querySelector("#info textarea");
    const now = el ? el.value : "";
    if (now.startsWith("Error")) return {error: now};
    const img = document.querySelector("#result img");
    const src = img ? img.getAttribute("src") : null;
    if (!new RegExp(pattern).test(now)) return null;
    const l = window.__bench.loads.find((l) => l.t >= since && l.src !== old && l.w > 0
                                        && l.src === src);
    return l ? {t: l.t} : null;
}
"""

#: Between two script calls of the poll, seconds.
POLL_S = 0.25


def _result_src(page) -> str | None:
    return page.evaluate("() => document.querySelector('#result img')?.getAttribute('src')")


def _wait(page, since: float, old: str | None, timeout_s: float) -> tuple[float, float, dict]:
    """``(ms, longest script call in s, phases)``: poll the page every :data:`POLL_S` until
    the full-resolution picture after page time ``since`` is shown (:data:`PHASES_JS`)."""
    longest = 0.0
    deadline = time.monotonic() + timeout_s
    while True:
        t0 = time.monotonic()
        done = page.evaluate(DONE_JS, [since, old, FULL_RENDER_RE])
        longest = max(longest, time.monotonic() - t0)
        if done is not None:
            if "error" in done:
                raise BenchError(f"the app says {done['error']!r}")
            phases = page.evaluate(PHASES_JS, [since, float(done["t"])])
            return float(done["t"]) - since, longest, phases
        if time.monotonic() > deadline:
            raise BenchError(f"no full render within {timeout_s:.0f} s")
        time.sleep(max(0.0, POLL_S - (time.monotonic() - t0)))


def _click(page, fx: float, fy: float, timeout_s: float) -> tuple[float, float, dict]:
    x, y = photo_point(page, fx, fy)
    old = _result_src(page)
    start = page.evaluate("() => window.__bench.events.length")
    page.locator("#input img").click(position={"x": x, "y": y})
    since = page.evaluate(
        """(start) => window.__bench.events.slice(start)
               .find((e) => e.type === 'click' && e.id === 'input').t""",
        start,
    )
    return _wait(page, since, old, timeout_s)


def _open_brushes(page) -> None:
    page.get_by_text("Brushes: keep sharp / blur").click()
    page.wait_for_selector("#paint canvas")
    page.locator("#paint canvas").first.scroll_into_view_if_needed()
    page.locator("#paint button[aria-label=Brush]").click()


def _apply(page, row: int, timeout_s: float) -> tuple[float, float, dict]:
    """Two strokes across the middle of the canvas (rows ``row`` and ``row + 1`` of twelve),
    then Apply."""
    box = page.locator("#paint canvas").first.bounding_box()
    for k in (row, row + 1):
        y = box["y"] + box["height"] * (0.2 + 0.05 * (k % 12))
        x0, x1 = box["x"] + box["width"] * 0.3, box["x"] + box["width"] * 0.7
        page.mouse.move(x0, y)
        page.mouse.down()
        page.mouse.move((x0 + x1) / 2, y)
        page.mouse.move(x1, y)
        page.mouse.up()
    old = _result_src(page)
    count = page.evaluate("() => window.__applies.length")
    page.locator("#paint_apply").click()
    since = page.evaluate("(n) => window.__applies[n]", count)
    return _wait(page, since, old, timeout_s)


def run(
    photo: Path | None,
    repeats: int,
    threads: int,
    timeout_s: float,
    weights: str | None = None,
) -> dict[str, Any]:
    """Run the bench (see the module's docstring); ``weights``: the app's checkpoint
    (default: the app's own, the shipped weights)."""
    result: dict[str, Any] = {"commit": commit(), "threads": threads, "load_start": loadavg()}
    with tempfile.TemporaryDirectory(prefix="d2f-paint-bench-") as tmp:
        folder = Path(tmp)
        if photo is None:
            photo = write_photos(folder / "photos", (4000, 3000), 1)[0]
        result["photo"] = str(photo)
        with app_in_browser(folder, threads, weights) as app:
            server, browser = app.server, app.browser
            page = browser.new_page(viewport={"width": 1400, "height": 1300})
            page.add_init_script(PAGE_PROBE)
            page.add_init_script(APPLY_PROBE)
            page.set_default_timeout(timeout_s * 1000)
            page.goto(server.url)
            page.wait_for_selector("#blur input[type=range]")
            show_details(page)
            old = _result_src(page)
            page.set_input_files("#input input[type=file]", str(photo))
            _wait(page, 0.0, old, timeout_s + 60)
            page.wait_for_function(
                "() => { const i = document.querySelector('#input img');"
                " return i && i.complete && i.naturalWidth > 0; }"
            )
            _open_brushes(page)
            wait_idle(server.process.pid)
            _click(page, 0.5, 0.55, timeout_s)  # untimed: the first click warms up
            wait_idle(server.process.pid)
            rows: dict[str, list[tuple[float, float, dict]]] = {"click": [], "apply": []}
            points = ((0.08, 0.1), (0.5, 0.55))
            for i in range(repeats):
                rows["click"].append(_click(page, *points[i % 2], timeout_s))
                wait_idle(server.process.pid)
                rows["apply"].append(_apply(page, 2 * i, timeout_s))
                wait_idle(server.process.pid)
            result["rows"] = rows
        result["tracebacks"] = app.tracebacks
    result["load_end"] = loadavg()
    return result


def format_result(result: dict[str, Any]) -> str:
    lines = [
        f"Apply against a click: commit {result['commit']}, app torch threads "
        f"{result['threads']}, photo {result['photo']}",
        f"load average (1, 5, 15 min) at start {result['load_start']}, at end {result['load_end']}",
        "",
        "| action | median ms | min ms | max ms | longest page pause (s) | runs ms |",
        "| --- | ---: | ---: | ---: | ---: | --- |",
    ]
    for key, runs in result["rows"].items():
        ms = [r[0] for r in runs]
        pause = max(r[1] for r in runs)
        lines.append(
            f"| {key} | {statistics.median(ms):.0f} | {min(ms):.0f} | {max(ms):.0f} | "
            f"{pause:.2f} | {', '.join(f'{m:.0f}' for m in ms)} |"
        )
    head = "| action | before its first request ms | uploads | uploaded KB | uploads done ms |"
    lines += ["", head,
              "| --- | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for key, runs in result["rows"].items():
        for r in runs:
            p = r[2]
            first = p["before_first_request_ms"]
            done = p["uploads_done_ms"]
            lines.append(
                f"| {key} | {'-' if first is None else f'{first:.0f}'} | {p['uploads']} | "
                f"{p['upload_bytes'] / 1024:.0f} | {'-' if done is None else f'{done:.0f}'} |"
            )
    click = statistics.median(r[0] for r in result["rows"]["click"])
    apply = statistics.median(r[0] for r in result["rows"]["apply"])
    lines.append(f"\nApply / click (medians, in turns): {apply / click:.2f}x")
    lines.append(f"tracebacks in the app's log: {result['tracebacks']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m app.paint_bench", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--photo", type=Path, help="the photo (default: a generated 12 MP JPEG)")
    parser.add_argument("--repeats", type=int, default=3, help="rounds (%(default)s)")
    parser.add_argument("--threads", type=int, default=1, help="the app's torch threads")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds per picture")
    parser.add_argument("--weights", default=None, help="checkpoint (default: the app's)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    if args.photo is not None and not args.photo.is_file():
        parser.error(f"--photo {args.photo}: no such file")
    try:
        result = run(args.photo, args.repeats, args.threads, args.timeout, args.weights)
    except BenchError as err:
        print(f"paint bench: {err}", file=sys.stderr)
        return 1
    print(format_result(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
