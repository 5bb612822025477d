"""Handler-level tests of photos the browser cannot show (HEIC): the photo panel gets a JPEG
of the decoded photo, clicks on it are mapped to the photo, and the focus goes to the subject
as for any upload."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from app.cache import SceneCache
from app.handlers import RefocusApp

APERTURE = 0.5
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def write_heic(path: Path, image: np.ndarray) -> Path:
    pillow_heif = pytest.importorskip("pillow_heif")
    pillow_heif.register_heif_opener()
    Image.fromarray(image).save(path, format="HEIF", quality=95)
    return path


@pytest.fixture
def logic(tiny_model, tmp_path):
    return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "dl")


def test_heic_upload_gets_a_panel_picture_and_the_subject_focus(logic, two_plane_scene, tmp_path):
    heic = write_heic(tmp_path / "IMG_0001.HEIC", two_plane_scene.image)
    out = logic.load(str(heic), None, "disparity", None, 0.5, APERTURE)
    session = out[0]
    panel = logic.photo_panel(session)
    assert panel.get("value") == str(session.panel)
    shown = np.asarray(Image.open(session.panel))  # a JPEG a browser shows
    assert Image.open(session.panel).format == "JPEG"
    assert shown.shape == two_plane_scene.image.shape
    assert np.abs(shown.astype(int) - two_plane_scene.image).mean() < 12
    assert session.shown_size == session.size == (320, 240)
    # the subject search ran (no depth in the file): the slider moves, the status says where
    assert isinstance(out[1], float) and "focus on the subject at" in out[-1]
    # a click on the panel refocuses
    clicked = logic.click(session, list(two_plane_scene.near_point), APERTURE)
    assert "focused on the click at" in clicked[-1]


def test_browser_formats_keep_their_upload_in_the_panel(logic, two_plane_scene):
    session = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)[0]
    assert session.panel is None  # a PNG: the browser shows the upload itself


@pytest.mark.shared_data
def test_iphone_heic_with_depth_focuses_on_its_subject(logic):
    pug = SHARED / "apple_heic_depth_pillow_heif" / "pug.heic"
    if not pug.is_file():
        pytest.skip(f"{pug} is absent (../shared/data is not part of the repository)")
    pytest.importorskip("pillow_heif")
    out = logic.load(str(pug), None, "disparity", None, 0.5, APERTURE)
    session = out[0]
    assert session.panel is not None and Image.open(session.panel).format == "JPEG"
    assert max(session.shown_size) <= 1600
    # the phone's depth, recorded without a focal plane: the subject is searched in it
    assert "depth embedded in the photo" in out[-1] and "focus on the subject at" in out[-1]
    assert isinstance(out[1], float) and out[1] != 0.5
