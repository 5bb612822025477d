"""``d2f-train port-teachers`` and the notice that ships beside the teachers' weights."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from d2f_core.train import two_stage

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "assets" / "weights"
TEACHERS = ROOT.parent / "shared" / "datasets" / "teachers"


def test_notice_names_every_shipped_teacher_and_its_licence_text():
    notice = (WEIGHTS / "TEACHERS.md").read_text()
    shipped = sorted(p.name for p in WEIGHTS.glob("teacher_*.pt"))
    assert shipped == [
        "teacher_deeplab_ade20k.pt",
        "teacher_deeplab_voc.pt",
        "teacher_fastdepth.pt",
        "teacher_u2netp.pt",
    ]
    for name in shipped:
        row = next(line for line in notice.splitlines() if line.startswith(f"| `{name}`"))
        licences = re.findall(r"`(LICENSE-[^`]+)`", row)
        assert licences, name
        for lic in licences:
            text = (WEIGHTS / lic).read_text()
            assert "Permission is hereby granted" in text or "Apache License" in text, lic
    assert "pydnet" not in " ".join(p.name.lower() for p in WEIGHTS.iterdir())


def test_port_teachers_refuses_a_missing_folder(tmp_path, capsys):
    rc = two_stage.main(["port-teachers", str(tmp_path / "nowhere"), str(tmp_path / "out")])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    missing = tmp_path / "nowhere"
    assert err == [f"d2f-train port-teachers: {missing}: not a folder of teacher files"]
    assert not (tmp_path / "out").exists()


@pytest.mark.shared_data
def test_port_teachers_writes_the_shipped_files(tmp_path, capsys):
    if not TEACHERS.is_dir():
        pytest.skip(f"the original teacher files are not at {TEACHERS}")
    pytest.importorskip("ai_edge_litert", reason="the teach extra reads the TFLite files")
    pytest.importorskip("onnx", reason="the teach extra reads the ONNX file")
    assert two_stage.main(["port-teachers", str(TEACHERS), str(tmp_path)]) == 0
    written = sorted(p.name for p in tmp_path.glob("*.pt"))
    assert written == sorted(p.name for p in WEIGHTS.glob("teacher_*.pt"))
    for name in written:  # the conversion is deterministic: byte for byte the shipped file
        assert (tmp_path / name).read_bytes() == (WEIGHTS / name).read_bytes(), name
    assert len(capsys.readouterr().out.strip().splitlines()) == 4
