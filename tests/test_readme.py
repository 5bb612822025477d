"""Every code example of the README runs as written.

The Python blocks run in a folder holding ``photo.jpg`` (a Google Lens Blur file: Google's
blurred picture with the original photo and the phone's depth inside) with the tiny test
checkpoint standing in for the shipped weights; the ``d2f`` command lines run through the CLI
on the same files. The library path must keep the phone's depth and the original photo.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
from _io_writers import lensblur_jpeg
from PIL import Image

from d2f_core import D2F, load_photo
from d2f_core.cli import main as cli_main

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(lang: str) -> list[str]:
    text = README.read_text()
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


@pytest.fixture
def folder(tmp_path, monkeypatch, tiny_checkpoint):
    """``photo.jpg`` (Lens Blur: a sharp original whose left half is near, a blurred
    picture shown in its place), ``depth.png`` and ``photos/`` in the current folder."""
    rng = np.random.default_rng(0)
    h, w = 288, 384  # the README clicks at (300, 250)
    sharp = (rng.random((h, w, 3)) * 255).astype(np.uint8)
    shown = np.full_like(sharp, 128)  # Google's rendering: nothing like the original
    z = np.full((h, w), 5.0, np.float32)
    z[:, : w // 2] = 1.0  # the left half is near
    (tmp_path / "photo.jpg").write_bytes(lensblur_jpeg(sharp, shown, z, near=1.0, far=5.0))
    Image.fromarray((255 - z * 40).astype(np.uint8)).save(tmp_path / "depth.png")
    (tmp_path / "photos").mkdir()
    Image.fromarray(sharp).save(tmp_path / "photos" / "a.png")
    monkeypatch.chdir(tmp_path)
    # the shipped weights are large to run here: the tiny checkpoint stands in for them
    monkeypatch.setattr(D2F, "from_pretrained", classmethod(lambda cls, *a, **k:
                        D2F.from_checkpoint(tiny_checkpoint)))  # fmt: skip
    return tmp_path, sharp


def test_python_examples_run(folder):
    tmp, sharp = folder
    blocks = _blocks("python")
    assert blocks, "the README has no Python example"
    for code in blocks:
        env: dict = {}
        exec(compile(code, str(README), "exec"), env)  # noqa: S102
    assert (tmp / "out" / "bokeh.jpg").is_file() and (tmp / "out" / "bokeh2.jpg").is_file()
    # the examples write into out/ only
    assert sorted(p.name for p in tmp.iterdir()) == ["depth.png", "out", "photo.jpg", "photos"]
    assert env["small"].bokeh.shape == (150, 200, 3)  # 288x384 at a 200 px screen
    assert env["loupe"].bokeh.shape == (150, 200, 3)
    painted = np.asarray(Image.open(tmp / "out" / "painted.jpg"), np.float32)  # the painted square
    original = env["photo"].image[60:140, 60:140] * 255
    assert np.abs(painted[60:140, 60:140] - original).mean() < 8.0  # sharp (JPEG's noise)
    # the example works on the original photo, not on Google's blurred picture
    assert env["photo"].image.std() > 0.2
    # and with the phone's depth: its map has the near left half nearer than the right
    disparity = env["scene"].disparity_full()
    assert disparity[:, :120].mean() > disparity[:, -120:].mean() + 0.5
    assert env["scene"].disparity_source == "embedded"


def test_prepare_takes_the_phone_depth_of_a_loaded_photo(folder, tiny_checkpoint):
    model = D2F.from_checkpoint(tiny_checkpoint)
    photo = load_photo("photo.jpg")
    assert photo.disparity is not None
    assert model.prepare(photo).disparity_source == "embedded"
    assert model.prepare(photo, depth="d2f").disparity_source != "embedded"
    assert model.prepare(photo.image).disparity_source != "embedded"  # a bare array


@pytest.mark.slow
def test_command_lines_run(folder, capsys, tiny_checkpoint):
    tmp, _ = folder
    lines = [ln.split("#")[0].strip() for b in _blocks("bash") for ln in b.splitlines()]
    commands = [shlex.split(ln) for ln in lines if ln.startswith("d2f ")]
    assert len(commands) >= 4
    assert "mkdir -p out" in lines  # before the first line that writes there
    Path("out").mkdir()
    # as written, from the checkout: the shipped samples and what earlier lines wrote
    samples = Path(__file__).resolve().parents[1] / "assets" / "samples"
    docs = Path(__file__).resolve().parents[1] / "docs"
    for argv in commands:
        argv = [a.replace("assets/samples", str(samples), 1) for a in argv[1:]]
        argv = [a.replace("docs/", f"{docs}/", 1) if a.startswith("docs/") else a for a in argv]
        code = cli_main([*argv, "--weights", str(tiny_checkpoint)])
        assert code == 0, (argv, capsys.readouterr().err)
    # every output in out/, nothing beside the photos the folder held
    for name in ("coffee_bokeh.png", "coffee_cup.jpg", "coffee_own.jpg", "coffee_cup_sharp.jpg"):
        assert (tmp / "out" / name).is_file(), name
    assert (tmp / "out" / "maps" / "coffee_bokeh_disparity.png").is_file()
    assert sorted(p.name for p in tmp.iterdir()) == ["depth.png", "out", "photo.jpg", "photos"]
    rendered = sorted(p.name for p in (tmp / "out" / "batch").iterdir() if p.suffix != ".jsonl")
    assert rendered == sorted(f"{p.stem}_bokeh{p.suffix}" for p in samples.iterdir()), rendered


def test_the_two_commands_come_first():
    lines = README.read_text().splitlines()
    app = next(i for i, ln in enumerate(lines) if ln.endswith('pip install -e ".[app]" && d2f-app'))
    tests = next(i for i, ln in enumerate(lines) if ln.endswith("&& python -m pytest"))
    assert app < 40 and tests < 40, (app + 1, tests + 1)


def test_the_before_after_picture_is_rewritten_only_when_asked():
    import importlib.util

    path = README.parent / "docs" / "before_after.py"
    spec = importlib.util.spec_from_file_location("before_after", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    tracked = README.parent / "assets" / "charts" / "before_after.jpg"
    assert module.output_path(module.parser().parse_args([])) != tracked
    assert module.output_path(module.parser().parse_args([])).parts[-2] == "out"
    assert module.output_path(module.parser().parse_args(["--readme"])) == tracked
