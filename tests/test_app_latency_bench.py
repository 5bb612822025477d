"""``python -m app.latency_bench``: the browser latency bench of the app.

The browser test runs the bench through ``main`` at the small size (800x600, the shipped
weights, two repeats, two steps per drag) against the real app in headless Chromium, and
checks the table and the JSON: every row there with positive, finite times, each action gave
a new picture (each click a refocused one), the release a full render and the drag steps
previews. The
other tests check the size names and the table's target marks on made-up figures. No test
asserts a time.
"""

from __future__ import annotations

import json
import math
import re

import pytest

from app import latency_bench
from app.latency_bench import ROWS, format_table, parse_size
from app.latency_probe import FULL_RENDER_RE


def test_parse_size():
    assert parse_size("small") == ("small", (800, 600))
    assert parse_size("12MP") == ("12mp", (4000, 3000))
    assert parse_size("640x480") == ("640x480", (640, 480))
    for bad in ("huge", "640", "32x32", "axb"):
        with pytest.raises(ValueError, match="size must"):
            parse_size(bad)


def test_main_refuses_bad_options(capsys):
    with pytest.raises(SystemExit) as exc:
        latency_bench.main(["--sizes", "small,huge"])
    assert exc.value.code == 2
    assert "'huge'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        latency_bench.main(["--repeats", "0"])


def _row(median: float) -> dict:
    return {"median_ms": median, "min_ms": median - 1, "max_ms": median + 1, "n": 3,
            "server_median_ms": median / 2}  # fmt: skip


def test_table_marks_targets_at_12mp_only():
    rows = {"upload": _row(2600), "upload_full": _row(9000), "click": _row(1400),
            "click_full": _row(2400), "release": _row(2100), "drag_step": _row(150)}  # fmt: skip
    entry = {"rows": rows, "warmup_upload_ms": 9500.0, "file_mb": 1.3}
    result = {
        "commit": "abc1234",
        "chromium": "156",
        "threads": 1,
        "repeats": 3,
        "steps": 5,
        "loadavg_start": "1.00 0.50 0.25",
        "loadavg_end": "2.00 1.00 0.50",
        "targets_ms": dict(latency_bench.TARGETS_MS),
        "target_pixels": latency_bench.TARGET_PIXELS,
        "sizes": {"small": {**entry, "size": [800, 600]}, "12mp": {**entry, "size": [4000, 3000]}},
    }
    lines = format_table(result).splitlines()
    big = {line.split(" | ")[1]: line for line in lines if line.startswith("| 12mp 4000x3000 |")}
    small = [line for line in lines if line.startswith("| small 800x600 |")]
    assert big[ROWS["click"]].endswith("| <= 1500 ms: ok |")
    assert big[ROWS["release"]].endswith("| <= 2000 ms: MISSED |")
    assert big[ROWS["drag_step"]].endswith("| <= 150 ms: ok |")  # at the target is on it
    assert big[ROWS["upload"]].endswith("| <= 2500 ms: MISSED |")
    assert big[ROWS["upload_full"]].endswith("| none |")
    assert big[ROWS["click_full"]].endswith("| none |")
    assert len(small) == 6 and not any(": ok" in line or "MISSED" in line for line in small)
    assert "at start 1.00 0.50 0.25, at end 2.00 1.00 0.50" in lines[1]


def test_table_gives_the_12mp_over_1mp_ratios():
    def rows(release, click, step):
        same = {"upload": _row(900), "upload_full": _row(900), "click_full": _row(click)}
        return {**same, "click": _row(click), "release": _row(release), "drag_step": _row(step)}

    result = {
        "commit": "abc1234", "chromium": "156", "threads": 1, "repeats": 3, "steps": 5,
        "loadavg_start": "1.00 0.50 0.25", "loadavg_end": "2.00 1.00 0.50",
        "targets_ms": dict(latency_bench.TARGETS_MS),
        "target_pixels": latency_bench.TARGET_PIXELS,
        "sizes": {
            "1mp": {"rows": rows(200, 300, 100), "warmup_upload_ms": 1.0, "file_mb": 0.2,
                    "size": [1152, 864]},
            "12mp": {"rows": rows(280, 480, 140), "warmup_upload_ms": 1.0, "file_mb": 2.0,
                     "size": [4000, 3000]},
        },
    }  # fmt: skip
    lines = format_table(result).splitlines()
    ratios = {line.split(" | ")[0][2:]: line for line in lines if "x | <= 1.5x" in line}
    assert ratios[ROWS["release"]] == f"| {ROWS['release']} | 1.40x | <= 1.5x: ok |"
    assert ratios[ROWS["click"]] == f"| {ROWS['click']} | 1.60x | <= 1.5x: MISSED |"
    assert ratios[ROWS["drag_step"]] == f"| {ROWS['drag_step']} | 1.40x | <= 1.5x: ok |"
    assert lines[-1] == "load average (1, 5, 15 min) at the end: 2.00 1.00 0.50"


@pytest.mark.browser
@pytest.mark.slow
def test_bench_in_browser_small(chromium_path, tmp_path, capsys):
    out = tmp_path / "latency.json"
    argv = ["--sizes", "small", "--repeats", "2", "--steps", "2", "--threads", "1",
            "--chromium", chromium_path, "--json", str(out)]  # fmt: skip
    assert latency_bench.main(argv) == 0
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())

    assert result["threads"] == 1
    assert result["server_log_tracebacks"] == 0
    for key in ("loadavg_start", "loadavg_end"):
        assert re.fullmatch(r"\d+\.\d+ \d+\.\d+ \d+\.\d+", result[key]), result[key]
    assert list(result["sizes"]) == ["small"]
    entry = result["sizes"]["small"]
    assert entry["size"] == [800, 600]
    rows = entry["rows"]
    assert list(rows) == list(ROWS)
    counts = {"upload": 2, "upload_full": 2, "click": 2, "click_full": 2, "release": 2,
              "drag_step": 4}  # fmt: skip
    for key, row in rows.items():
        runs = row["runs_ms"]
        assert row["n"] == len(runs) == counts[key], key
        assert all(math.isfinite(v) and v > 0 for v in runs), (key, runs)
        assert row["min_ms"] <= row["median_ms"] <= row["max_ms"], key
        assert row["server_median_ms"] > 0, key
        assert all(row["new_src"]), (key, row["status"])
    # the clicks refocused: not the same picture again (0.0 when two clicks land at one depth)
    assert all(d > 0.5 for d in rows["click"]["picture_diff"]), rows["click"]
    # a photo of 0.5 MP gets no first look: its first picture is the full render
    assert rows["upload"]["runs_ms"] == rows["upload_full"]["runs_ms"]
    assert rows["click"]["runs_ms"] == rows["click_full"]["runs_ms"]
    for status in rows["upload"]["status"] + rows["release"]["status"]:
        assert re.search(FULL_RENDER_RE, status), status
    for status in rows["drag_step"]["status"]:
        assert not re.search(FULL_RENDER_RE, status), status  # a preview
    assert math.isfinite(entry["warmup_upload_ms"]) and entry["warmup_upload_ms"] > 0

    table = [line for line in printed.splitlines() if line.startswith("| small 800x600 |")]
    assert [line.split(" | ")[1] for line in table] == list(ROWS.values())
    assert f"at start {result['loadavg_start']}" in printed


@pytest.mark.browser
@pytest.mark.slow
def test_paint_bench_in_browser_small(chromium_path, tmp_path, tiny_checkpoint):
    """``python -m app.paint_bench`` on an 800x600 photo: a click and an Apply, each timed to
    its full render, the page's longest pause and the requests behind each."""
    from app import paint_bench
    from app.latency_server import write_photos

    photo = write_photos(tmp_path / "photos", (800, 600), 1)[0]
    result = paint_bench.run(photo, 1, 1, 120.0, weights=str(tiny_checkpoint))
    assert result["tracebacks"] == 0
    assert list(result["rows"]) == ["click", "apply"]
    for key, runs in result["rows"].items():
        assert len(runs) == 1, key
        ms, pause, phases = runs[0]
        assert math.isfinite(ms) and ms > 0 and 0 <= pause < 60, (key, runs)
    # Apply sends the editor's images (its background, the paint and their composite)
    _, _, apply = result["rows"]["apply"][0]
    assert apply["uploads"] >= 3 and apply["upload_bytes"] > 0, apply
    text = paint_bench.format_result(result)
    assert "Apply / click (medians, in turns):" in text and "| apply |" in text
