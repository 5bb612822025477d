"""Browser latency benchmark of the app: ``python -m app.latency_bench``.

Starts the real app (``python -m app``) on a free localhost port, opens it in headless
Chromium (Debian's ``/usr/bin/chromium`` through Playwright) and times what a photographer
waits for: from the action in the page to the new picture loaded in the result panel
(``#result img`` with another ``src``, ``naturalWidth > 0``):

* ``upload``: the photo file given to ``#input``'s file input -> the first bokeh shown (a
  large photo's first look at the render pass's size). Each repeat uploads another file (one
  corner block differs), so no upload hits the scene cache.
* ``upload_full``: the same upload -> its full-resolution render shown.
* ``click``: a click on the photo (click-to-focus) -> the first refocused picture (a large
  photo's first look).
* ``click_full``: the same click -> its full-resolution render shown.
* ``release``: the mouse let go at the end of a drag of the ``#blur`` slider -> the
  full-resolution picture (the status line ``#info`` names a full render).
* ``drag_step``: one mouse move along the held ``#blur`` slider -> the preview picture. Each
  step waits for its picture before the next, so every step is timed on its own.

Both ends are taken in the page, as ``performance.now()`` of the input event (listeners on the
document in the capture phase) and of the result image's ``load`` event, so Playwright's
round trips are not counted. The page is driven by element ids only (``#input``, ``#blur``,
``#result``, ``#info``) and by the slider track's own min / max, never by what the slider
values mean. After the timing, a 64x48 thumbnail of each picture is compared with the one
before (``picture_diff``), which tells a refocused picture from the same one again. Between
actions the bench waits until the app's process is idle (the download file written after a
full render, for one), so that one action's work does not fall on the next one's time.

The photo is the Middlebury 'motorcycle' (bundled with scikit-image) cropped to 4:3 and
resized to each size, written as JPEG (quality 92) into a temporary folder. The status
line's own figures (``... render 812 ms | decode 40 ms ...``) are summed as the server's ms.
Targets at 12 MP (from the issue) are printed beside the figures; nothing here asserts a
time.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from app.latency_probe import (
    CHROMIUM,
    CLICK_POINTS,
    PAGE_PROBE,
    Probe,
    app_in_browser,
    show_details,
)
from app.latency_server import BenchError, commit, loadavg, write_photos

#: Named photo sizes, width x height.
SIZES = {"small": (800, 600), "1mp": (1152, 864), "12mp": (4000, 3000)}

#: The actions whose 12 MP / 1 MP ratio is printed, and the most each may take: the picture
#: on screen is rendered at the screen's size, so a large photo is as live as a small one.
RATIO_ROWS = ("release", "click", "drag_step")
RATIO_TARGET = 1.5


#: Rows of the table: key -> what is timed.
ROWS = {
    "upload": "upload -> first bokeh",
    "upload_full": "upload -> full-resolution bokeh",
    "click": "click on photo -> refocused",
    "click_full": "click on photo -> full-resolution",
    "release": "slider release -> full render",
    "drag_step": "drag step -> preview",
}


#: Targets at 12 MP in ms on a quiet machine (the issues "The app, as a photographer uses
#: it" and "The clicked subject stays sharp"); the full renders after a first look have none.
TARGETS_MS = {"upload": 2500.0, "click": 1500.0, "release": 2000.0, "drag_step": 150.0}


#: Photos of at least this many pixels are held to :data:`TARGETS_MS`.
TARGET_PIXELS = 11_500_000


def parse_size(text: str) -> tuple[str, tuple[int, int]]:
    """``small``, ``12mp`` or ``WxH`` -> ``(name, (width, height))``."""
    key = text.strip().lower()
    if key in SIZES:
        return key, SIZES[key]
    try:
        w, h = (int(v) for v in key.split("x"))
    except ValueError:
        raise ValueError(f"size must be one of {', '.join(SIZES)} or WxH, got {text!r}") from None
    if w < 64 or h < 64:
        raise ValueError(f"size must be at least 64x64, got {text!r}")
    return key, (w, h)


def summarize(runs: list[float]) -> dict[str, Any]:
    return {
        "median_ms": statistics.median(runs),
        "min_ms": min(runs),
        "max_ms": max(runs),
        "n": len(runs),
        "runs_ms": runs,
    }


def bench_sizes(
    probes: dict[str, tuple[Probe, list[Path], float]], repeats: int, steps: int
) -> dict[str, dict[str, Any]]:
    """All figures of every size, one page per size, interleaved round by round (each
    round times every size in turn, so that the sizes share the machine's load): per page an
    untimed warm-up upload (``photos[0]``), then ``repeats`` rounds of uploads, ``repeats``
    rounds of clicks (after one untimed click each) and ``repeats`` rounds of drags of
    ``steps`` steps each. ``probes``: name -> ``(probe, photos, upload timeout in ms)``."""
    results = {name: {key: [] for key in ROWS} for name in probes}
    warmups = {}
    for name, (probe, photos, upload_ms) in probes.items():
        warmups[name] = probe.upload(photos[0], upload_ms)
        probe.settle()
    for i in range(repeats):
        for name, (probe, photos, upload_ms) in probes.items():
            out = probe.upload(photos[i + 1], upload_ms)
            results[name]["upload"].append({**out, "ms": out["first_ms"]})
            results[name]["upload_full"].append(out)
            probe.settle()
    for i in range(repeats + 1):
        for name, (probe, _, _) in probes.items():
            out = probe.click_photo(*CLICK_POINTS[i % len(CLICK_POINTS)])
            probe.settle()
            if i:  # the first click warms focus_at up
                results[name]["click"].append({**out, "ms": out["first_ms"]})
                results[name]["click_full"].append(out)
    for i in range(repeats):
        for name, (probe, _, _) in probes.items():
            # there and back again: the blur stays in the same range repeat after repeat
            moves, release = probe.drag(steps, 1 if i % 2 == 0 else -1)
            results[name]["drag_step"].extend(moves)
            results[name]["release"].append(release)
    entries = {}
    for name, by_key in results.items():
        rows = {}
        for key, outs in by_key.items():
            row = summarize([o["ms"] for o in outs])
            server = [o["server_ms"] for o in outs if o["server_ms"] is not None]
            row["server_median_ms"] = statistics.median(server) if server else None
            row["new_src"] = [o["new_src"] for o in outs]
            row["picture_diff"] = [o["picture_diff"] for o in outs]
            row["status"] = [o["status"] for o in outs]
            rows[key] = row
        warmup = warmups[name]
        entries[name] = {
            "rows": rows, "warmup_upload_ms": warmup["ms"], "warmup_status": warmup["status"]
        }  # fmt: skip
    return entries


def size_ratios(result: dict[str, Any], large: str, small: str) -> dict[str, float]:
    """Median ms of ``large`` over ``small`` for each of :data:`RATIO_ROWS`."""
    a, b = result["sizes"][large]["rows"], result["sizes"][small]["rows"]
    return {key: a[key]["median_ms"] / b[key]["median_ms"] for key in RATIO_ROWS}


def run_bench(
    sizes: list[str] | tuple[str, ...] = ("1mp", "12mp"),
    *,
    repeats: int = 3,
    steps: int = 5,
    threads: int | None = None,
    weights: str | None = None,
    chromium: str = CHROMIUM,
    timeout_s: float = 120.0,
) -> dict[str, Any]:
    """Run the bench; see the module's docstring.

    Args:
        sizes: ``small`` (800x600), ``1mp`` (1152x864), ``12mp`` (4000x3000) or ``WxH``;
            timed round by round, each round every size in turn.
        repeats: timed repeats of each figure (``drag_step`` has ``repeats * steps``).
        steps: mouse moves per drag.
        threads: the app's torch threads (default ``$D2F_APP_THREADS`` or 1, as the app).
        weights: checkpoint for the app (default: the app's, the shipped weights).
        chromium: the browser binary.
        timeout_s: the longest wait for one picture; an upload of a photo of N MP may take
            ``timeout_s + 10 * N`` s.

    Returns:
        ``{"commit", "chromium", "threads", "weights", "repeats", "steps",
        "loadavg_start", "loadavg_end", "targets_ms", "sizes": {name: {"size", "file_mb",
        "rows": {key: {"median_ms", "min_ms", "max_ms", "n", "runs_ms",
        "server_median_ms", "new_src", "picture_diff", "status"}}, "warmup_upload_ms", ...}}}``.
    """
    if repeats < 1 or steps < 1:
        raise ValueError(f"repeats and steps must be >= 1, got {repeats} and {steps}")
    parsed = [parse_size(s) for s in sizes]
    if threads is None:
        threads = int(os.environ.get("D2F_APP_THREADS", "1"))
    if not Path(chromium).exists():
        raise BenchError(f"{chromium} not found: install Debian's chromium (apt-get install -y "
                         "chromium)")  # fmt: skip
    try:
        import playwright.sync_api  # noqa: F401 (app_in_browser drives it)
    except ImportError as err:
        raise BenchError("playwright is not installed (pip install playwright)") from err

    result: dict[str, Any] = {
        "commit": commit(),
        "threads": threads,
        "weights": weights or "the app's default (assets/weights/d2f_lite.pt)",
        "repeats": repeats,
        "steps": steps,
        "loadavg_start": loadavg(),
        "targets_ms": dict(TARGETS_MS),
        "target_pixels": TARGET_PIXELS,
        "sizes": {},
    }
    with tempfile.TemporaryDirectory(prefix="d2f-latency-bench-") as tmp:
        folder = Path(tmp)
        with app_in_browser(folder, threads, weights, chromium) as app:
            server, browser = app.server, app.browser
            result["chromium"] = browser.version
            probes, files = {}, {}
            for name, (w, h) in parsed:
                photos = write_photos(folder / name, (w, h), repeats + 1)
                page = browser.new_page(viewport={"width": 1400, "height": 900})
                page.add_init_script(PAGE_PROBE)
                page.set_default_timeout(timeout_s * 1000)
                page.goto(server.url)
                page.wait_for_selector("#blur input[type=range]")
                show_details(page)
                upload_ms = (timeout_s + 10 * w * h / 1e6) * 1000
                probes[name] = (Probe(page, server, timeout_s * 1000), photos, upload_ms)
                files[name] = statistics.mean(p.stat().st_size for p in photos)
            for name, entry in bench_sizes(probes, repeats, steps).items():
                entry["size"] = list(dict(parsed)[name])
                entry["file_mb"] = files[name] / (1 << 20)
                result["sizes"][name] = entry
        result["server_log_tracebacks"] = app.tracebacks
    result["loadavg_end"] = loadavg()
    return result


def format_table(result: dict[str, Any]) -> str:
    """The figures as a Markdown table, with the run's conditions above it."""
    lines = [
        f"app latency in the browser: commit {result['commit']}, Chromium "
        f"{result.get('chromium', '?')}, app torch threads {result['threads']}, "
        f"{result['repeats']} repeats, {result['steps']} steps per drag",
        f"load average (1, 5, 15 min) at start {result['loadavg_start']}, "
        f"at end {result['loadavg_end']}",
        "",
        "| photo | action | median ms | min ms | max ms | n | server ms (status line) "
        "| target at 12 MP |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for name, entry in result["sizes"].items():
        w, h = entry["size"]
        held = w * h >= result["target_pixels"]
        for key, label in ROWS.items():
            row = entry["rows"][key]
            server = row["server_median_ms"]
            target = result["targets_ms"].get(key)
            if target is None:
                mark = "none"
            elif held:
                mark = f"<= {target:.0f} ms: {'ok' if row['median_ms'] <= target else 'MISSED'}"
            else:
                mark = f"(<= {target:.0f} ms)"
            lines.append(
                f"| {name} {w}x{h} | {label} | {row['median_ms']:.0f} | {row['min_ms']:.0f} "
                f"| {row['max_ms']:.0f} | {row['n']} | "
                f"{'-' if server is None else f'{server:.0f}'} | {mark} |"
            )
    for name, entry in result["sizes"].items():
        lines.append(
            f"{name}: untimed first upload {entry['warmup_upload_ms']:.0f} ms, "
            f"JPEG {entry['file_mb']:.2f} MB"
        )
    if {"12mp", "1mp"} <= set(result["sizes"]):
        lines += ["", "| action | 12 MP / 1 MP (medians, same run, interleaved) | target |",
                  "| --- | ---: | --- |"]  # fmt: skip
        for key, ratio in size_ratios(result, "12mp", "1mp").items():
            verdict = "ok" if ratio <= RATIO_TARGET else "MISSED"
            lines.append(f"| {ROWS[key]} | {ratio:.2f}x | <= {RATIO_TARGET}x: {verdict} |")
        lines.append(f"load average (1, 5, 15 min) at the end: {result['loadavg_end']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m app.latency_bench``."""
    parser = argparse.ArgumentParser(
        prog="python -m app.latency_bench", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--sizes",
        default="1mp,12mp",
        help="comma-separated: small, 1mp, 12mp or WxH (%(default)s); with 1mp and 12mp the "
        "ratios of the two are printed",
    )
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats (%(default)s)")
    parser.add_argument("--steps", type=int, default=5, help="mouse moves per drag (%(default)s)")
    parser.add_argument(
        "--threads", type=int, default=None, help="the app's torch threads ($D2F_APP_THREADS or 1)"
    )
    parser.add_argument("--weights", default=None, help="checkpoint (default: the app's)")
    parser.add_argument("--chromium", default=CHROMIUM, help="browser binary (%(default)s)")
    parser.add_argument(
        "--timeout", type=float, default=120.0, help="seconds to wait for a picture (%(default)s)"
    )
    parser.add_argument("--json", help="also write the result to this JSON file")
    args = parser.parse_args(argv)
    sizes = [s for s in args.sizes.split(",") if s.strip()]
    try:
        for s in sizes:
            parse_size(s)
        if args.threads is not None and args.threads < 1:
            raise ValueError(f"--threads must be >= 1, got {args.threads}")
        if args.repeats < 1 or args.steps < 1:
            raise ValueError("--repeats and --steps must be >= 1")
    except ValueError as err:
        parser.error(str(err))
    try:
        result = run_bench(
            sizes,
            repeats=args.repeats,
            steps=args.steps,
            threads=args.threads,
            weights=args.weights,
            chromium=args.chromium,
            timeout_s=args.timeout,
        )
    except BenchError as err:
        print(f"latency bench: {err}", file=sys.stderr)
        return 1
    print(format_table(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
