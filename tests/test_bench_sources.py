"""``d2f-bench sources``: each depth source's prepare time beside its accuracy."""

from __future__ import annotations

import json

import pytest

from d2f_core.bench import sources as bs


@pytest.mark.slow
def test_times_every_source_in_turns(tiny_model):
    rows = bs.time_sources(tiny_model, ["d2f", "scene"], sizes=[(48, 64), (64, 48)], repeat=2)
    assert [(r["size"], r["source"]) for r in rows] == [
        ("48x64", "d2f"),
        ("48x64", "scene"),
        ("64x48", "d2f"),
        ("64x48", "scene"),
    ]
    for r in rows:
        assert len(r["times_ms"]) == 2 and min(r["times_ms"]) == r["best_ms"] > 0
    assert rows[0]["ratio"] == 1.0 and rows[2]["ratio"] == 1.0
    assert rows[1]["ratio"] == pytest.approx(rows[1]["median_ms"] / rows[0]["median_ms"])
    assert rows[0]["output"] == "D2F network disparity"
    assert rows[1]["output"].startswith("scene teachers' map (parse")
    table = bs.format_times(rows)
    assert table.count("\n") == 5 and "| 48x64 | scene |" in table


def test_accuracy_from_the_benches_files_and_the_chart(tmp_path):
    depth = tmp_path / "depth.json"
    depth.write_text(
        json.dumps(
            {
                "summary": {
                    "ramp": {"mean_spearman": 0.6},
                    "source d2f": {"mean_spearman": 0.66},
                    "source scene": {"mean_spearman": 0.76},
                }
            }
        )
    )
    csv = tmp_path / "eval_all.csv"
    csv.write_text("id,psnr,ssim,ms\na,27.0,0.9,10\nb,28.0,0.9,12\n")
    acc = bs.accuracy_of(depth, {"scene": str(csv)})
    assert acc == {"d2f": {"spearman": 0.66}, "scene": {"spearman": 0.76, "psnr": 27.5}}
    bad = tmp_path / "bad.csv"
    bad.write_text("id,ssim\na,0.9\n")
    with pytest.raises(ValueError, match="no psnr column"):
        bs.accuracy_of(None, {"scene": str(bad)})
    rows = [
        {"size": "768x1024", "source": "d2f", "median_ms": 100.0},
        {"size": "768x1024", "source": "scene", "median_ms": 400.0},
    ]
    pytest.importorskip("matplotlib")
    out = bs.draw_chart(rows, acc, tmp_path / "chart.png")
    assert out.stat().st_size > 10_000
    with pytest.raises(ValueError, match="no accuracy figures"):
        bs.draw_chart(rows, {}, tmp_path / "none.png")


def test_cli_refuses_an_unknown_source(capsys):
    assert bs.main(["--sources", "d2f", "nowhere"]) == 1
    assert "unknown depth source 'nowhere'" in capsys.readouterr().err
