"""The focal range and the one vocabulary end to end: a click on the 12 MP matte portrait
keeps the face as sharp as the photo, and the ``d2f render`` command in the app's status line
gives the app's download, pixel for pixel."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from app.cache import SceneCache
from app.handlers import RefocusApp
from d2f_core import cli

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
PORTRAIT = SHARED / "apple_portrait_jpeg_depth" / "image-with-matte.jpg"
#: x0, y0, x1, y1 in the 3024x4032 portrait: the face region its XMP stores (Apple's face
#: detection: centre 0.5635, 0.1465, size 0.119 x 0.089 of the frame), and the lamps and
#: ceiling behind the man.
FACE = (1524, 411, 1884, 770)
BACKGROUND = (1980, 0, 3000, 720)


def _gradient(image: np.ndarray, box: tuple[int, int, int, int]) -> float:
    """Mean gradient magnitude of the luma in ``box``."""
    x0, y0, x1, y1 = box
    luma = image[y0:y1, x0:x1].astype(np.float64) @ [0.299, 0.587, 0.114]
    gx, gy = np.diff(luma, axis=1)[:-1], np.diff(luma, axis=0)[:, :-1]
    return float(np.hypot(gx, gy).mean())


@pytest.mark.shared_data
@pytest.mark.slow
def test_clicked_face_stays_sharp_at_100_percent(one_thread):
    if not PORTRAIT.is_file():
        pytest.skip(f"shared data not available: {PORTRAIT}")
    from d2f_core.io import load_photo
    from d2f_core.pipeline import D2F

    try:
        model = D2F.from_pretrained()
    except FileNotFoundError as exc:
        pytest.skip(str(exc))
    photo = load_photo(PORTRAIT, max_pixels=None)
    assert photo.image.shape[:2] == (4032, 3024)
    scene = model.prepare(photo)
    focus, span = model.focus_at(scene, 1704, 591, with_range=True)  # the face's centre
    thin = model.render(scene, focus, f_number=2.6).bokeh
    wide = model.render(scene, focus, f_number=2.6, focal_range=span).bokeh
    face, back = _gradient(photo.image, FACE), _gradient(photo.image, BACKGROUND)
    # measured: face 0.867 (thin lens) -> 1.000 (its range); background 0.353 -> 0.408
    assert _gradient(thin, FACE) / face < 0.95
    assert _gradient(wide, FACE) / face >= 0.95
    assert _gradient(wide, BACKGROUND) / back < 0.5


@pytest.fixture
def logic(tiny_model, tmp_path):
    return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "downloads")


def _command(info: str) -> list[str]:
    found = re.search(r"reproduce: (d2f render .*?)(?: \| |$)", info)
    assert found, info
    return shlex.split(found.group(1))


def test_status_command_gives_the_download(logic, two_plane_scene, tiny_checkpoint, tmp_path):
    session = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, 2.0)[0]
    focus, span, *_, info = logic.click(session, list(two_plane_scene.near_point), 2.0, 6, 20.0)
    words = _command(info)
    assert words[:2] == ["d2f", "render"]
    assert words[words.index("--focus-position") + 1] == f"{focus:g}"
    assert words[words.index("--focal-range") + 1] == f"{span:g}"
    assert words[words.index("--f-number") + 1] == "2"
    assert words[words.index("--aperture-blades") + 1] == "6"
    assert words[words.index("--depth-model") + 1] == "d2f"
    download = Path(logic.download(session, "PNG")["value"])

    argv = words[2:]
    argv[0] = str(two_plane_scene.photo)  # the photo by its path here
    out = tmp_path / "cli.png"
    argv[argv.index("-o") + 1] = str(out)
    # the app's own model: the test's weights
    assert cli.main(["render", *argv, "--weights", str(tiny_checkpoint), "-q"]) == 0
    app_pixels = np.asarray(Image.open(download).convert("RGB"))
    cli_pixels = np.asarray(Image.open(out).convert("RGB"))
    assert np.array_equal(app_pixels, cli_pixels)


def test_thin_lens_and_no_blur_commands(logic, two_plane_scene):
    session = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.3, 4.0)[0]
    info = logic.render_full(session, 0.3, 4.0, 0, 0.0, False, False, "Bokeh", "fast", False)[3]
    words = _command(info)
    assert "--blur" in words and words[words.index("--blur") + 1] == "0"
    assert words[words.index("--focal-range") + 1] == "0"
    assert "--no-highlight-boost" in words and "--no-fusion" in words
    assert words[words.index("--quality") + 1] == "fast"


def test_cli_focus_at_takes_the_subjects_range(two_plane_scene, tmp_path):
    photo, depth = str(two_plane_scene.photo), str(two_plane_scene.disparity)
    x, y = two_plane_scene.near_point
    common = ["render", photo, "--depth", depth, "--blur", "30", "--focus-at", f"{x},{y}", "-q"]
    assert cli.main([*common, "-o", str(tmp_path / "range.png")]) == 0
    assert cli.main([*common, "-o", str(tmp_path / "thin.png"), "--focal-range", "0"]) == 0
    thin = np.asarray(Image.open(tmp_path / "thin.png"))
    # the two-plane subject is flat: its range is tiny and the render nearly the thin lens
    wide = np.asarray(Image.open(tmp_path / "range.png"))
    assert np.abs(wide.astype(int) - thin).mean() < 1.0


@pytest.mark.parametrize(
    "option, message",
    [
        (["--focal-range", "2"], "--focal-range"),
        (["--focus-position", "-0.5"], "--focus-position"),
        (["--focus-position", "0.5", "--focus", "0.5"], "not allowed with"),
    ],
)
def test_cli_bad_vocabulary_is_one_line(two_plane_scene, tmp_path, capsys, option, message):
    argv = ["render", str(two_plane_scene.photo), "-o", str(tmp_path / "o.png"), "--blur", "5"]
    assert cli.main([*argv, *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("d2f: error:") and message in err[-1]
    assert not any("Traceback" in line for line in err)
