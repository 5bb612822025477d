"""Live at any size: the app renders the result panel's picture of a large photo at the
screen's size, the full resolution for the download and, region by region, for the 100 %
loupe; the picture shown is the download downscaled, and the loupe is the download's crop."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from app.cache import SceneCache
from app.handlers import RefocusApp
from app.loupe import loupe_box
from app.settings import LOUPE_SIZE, SCREEN_SIDE
from app.summary import summary_line
from d2f_core import cli
from d2f_core.metrics import psnr
from d2f_core.pipeline import D2F
from d2f_core.sizing import resize

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def shipped() -> D2F:
    return D2F.from_pretrained()


@pytest.fixture
def logic(shipped, tmp_path):
    return RefocusApp(shipped, SceneCache(512 << 20), download_root=tmp_path / "downloads")


def _down(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    t = torch.from_numpy(image.astype(np.float32) / 255.0).permute(2, 0, 1)[None]
    return resize(t, size)[0].permute(1, 2, 0).numpy()


def _controls(focus: float, f_number: float = 2.0, focal_range: float = 0.0) -> tuple:
    # focus, f-number, blades, rotation, boost, fusion, view, quality, blur on, range, id
    return (focus, f_number, 0, 0.0, True, True, "Bokeh", "balanced", True, focal_range, None)


@pytest.mark.slow
def test_large_photo_is_shown_at_the_screens_size(logic, scene_factory, tmp_path):
    s = scene_factory(width=2400, height=1800)
    session = logic.load(str(s.photo), None, "disparity", None, 0.5, 2.0)[0]
    info = logic.render_full(session, *_controls(0.2))[3]
    shown = session.views["Bokeh"]
    assert shown.shape == (1200, 1600, 3) and SCREEN_SIDE == 1600
    assert "shown at 1600x1200, the download at full resolution" in info
    assert session.last_full is None  # the full resolution waits for the download
    download = Path(logic.download(session, "PNG")["value"])
    full = np.asarray(Image.open(download).convert("RGB"))
    assert full.shape == (1800, 2400, 3)
    assert psnr(shown.astype(np.float32) / 255.0, _down(full, (1200, 1600))) >= 40.0
    # the status line's command gives the download, pixel for pixel
    words = shlex.split(re.search(r"reproduce: (d2f render .*?)(?: \| |$)", info).group(1))
    argv = words[2:]
    argv[0] = str(s.photo)
    argv[argv.index("-o") + 1] = str(tmp_path / "cli.png")
    assert cli.main(["render", *argv, "-q"]) == 0
    assert np.array_equal(np.asarray(Image.open(tmp_path / "cli.png").convert("RGB")), full)


@pytest.mark.slow
def test_loupe_is_the_downloads_crop(logic, scene_factory):
    s = scene_factory(width=2400, height=1800, seed=2)
    session = logic.load(str(s.photo), None, "disparity", None, 0.5, 2.0)[0]
    controls = _controls(0.1, 1.4, 0.05)
    logic.render_full(session, *controls)
    full = np.asarray(Image.open(logic.download(session, "PNG")["value"]).convert("RGB"))
    # a click at (1000, 450) of the 1600x1200 picture: (1500, 675) of the photo
    update = logic.loupe(session, [1000, 450], *controls)
    loupe = np.asarray(Image.open(update["value"]).convert("RGB"))
    x0, y0, x1, y1 = loupe_box(session.loupe_point, session.size)
    assert (x1 - x0, y1 - y0) == LOUPE_SIZE and abs((x0 + x1) / 2 - 1500) <= 1
    assert "100 % view: 480x360 px" in update["label"]
    assert loupe.shape == (y1 - y0, x1 - x0, 3)
    crop = full[y0:y1, x0:x1]
    assert psnr(loupe.astype(np.float32) / 255.0, crop.astype(np.float32) / 255.0) >= 40.0
    # a new value: the loupe follows it
    again = logic.refresh_loupe(session, *_controls(0.9, 1.4, 0.0))
    moved = np.asarray(Image.open(again["value"]).convert("RGB"))
    assert np.abs(moved.astype(int) - loupe).mean() > 1.0
    # near a corner the region is moved inside the photo
    logic.loupe(session, [1599, 1199], *controls)
    assert loupe_box(session.loupe_point, session.size) == (1920, 1440, 2400, 1800)
    # no photo: nothing to show
    assert logic.loupe(None, [1, 1], *controls).__class__.__name__ != "Error"


def test_summary_line_in_a_photographers_words(logic, scene_factory):
    """Focus, aperture and what is sharp: the depth whose blur stays under a pixel, the
    focal range and 1/K on each side (slider units: 0 % the nearest, 100 % the farthest)."""
    from d2f_core.lens import blur_px

    s = scene_factory(width=320, height=240)
    assert summary_line(None, "x") == ""
    session = logic.load(str(s.photo), None, "disparity", None, 0.5, 2.0)[0]
    info = logic.render_full(session, *_controls(0.3, 2.0, 0.1))[3]
    k = blur_px(2.0, 320)
    half = 0.05 + 1.0 / k
    near, far = round(100 * (0.3 - half)), round(100 * (0.3 + half))
    assert summary_line(session, info) == (
        f"**Focus** 30 % of the way back · **aperture** f/2 · **sharp** from {near} % to "
        f"{far} % of the way back (0 % the nearest thing, 100 % the farthest)"
    )
    assert (near, far) == (16, 44)
    off = logic.render_full(session, 0.3, 2.0, 0, 0.0, True, True, "Bokeh", "balanced", False)[3]
    assert summary_line(session, off) == (
        "**Focus** 30 % of the way back · **no blur**: the photo as it is"
    )
    # an error is said in the summary too: the status line waits closed behind "Advanced"
    error = "Error: notes.jpg: not an image file. Still showing a.png."
    assert summary_line(session, error) == (
        "**Error**: notes.jpg: not an image file. Still showing a.png."
    )
    assert summary_line(None, "Error: notes.jpg: not an image file") == (
        "**Error**: notes.jpg: not an image file"
    )
