"""A large upload is shown first at the render pass's size, then at full resolution
(``LoadEvents.load_steps``); API clients and ``load`` get the full render only."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

import app.render_events
import app.settings
from app.cache import SceneCache
from app.handlers import RefocusApp

#: f/0.5 on the 320 px wide test photo: both planes far out of focus when the other is focused
APERTURE = 0.5


def pixels(update) -> np.ndarray:
    return np.asarray(Image.open(update["value"]), np.float32)


@pytest.fixture(scope="module")
def shipped_model():
    """The shipped weights: the first look is compared with the full render, and the tiny
    random model's fusion differs between sizes far more than a trained one's."""
    from d2f_core.pipeline import D2F

    return D2F.from_pretrained()


@pytest.fixture
def logic(shipped_model, tmp_path):
    return RefocusApp(shipped_model, SceneCache(256 << 20), download_root=tmp_path / "downloads")


@pytest.fixture
def small_threshold(monkeypatch):
    """The 320x240 test photo counts as large, and its first look is 160 px wide."""
    monkeypatch.setattr(app.settings, "FIRST_LOOK_PIXELS", 320 * 240 - 1)
    monkeypatch.setattr(app.render_events, "FIRST_LOOK_MAX_SIDE", 160)


def upload_args(scene) -> tuple:
    return (str(scene.photo), str(scene.disparity), "disparity", None, 0.5, APERTURE)


def test_large_upload_shows_a_first_look_then_the_full_render(
    logic, two_plane_scene, small_threshold
):
    steps = list(logic.load_steps(*upload_args(two_plane_scene)))
    assert len(steps) == 2
    (session, focus, first, _, _, first_info), last = steps
    assert "first look render" in first_info and "160x120, full resolution follows" in first_info
    assert "decode" in first_info and "depth: your disparity map" in first_info
    assert pixels(first).shape == (120, 160, 3)
    # the focus slider is set once, by the first look; the final picture is the full render
    assert isinstance(focus, float) or focus is not None
    assert last[0] is session and last[1] == {"__type__": "update"}
    full = pixels(last[2])
    assert full.shape == (240, 320, 3)
    assert "full render" in last[5] and "first look" not in last[5]
    # the first look is the same picture, smaller: the full one halved is within a few grey
    # levels of it, and far closer than the photo itself is (both planes are blurred)
    halved = np.asarray(Image.fromarray(full.astype(np.uint8)).resize((160, 120), Image.BOX))
    photo = np.asarray(Image.open(two_plane_scene.photo).convert("RGB").resize((160, 120)))
    gap = np.abs(pixels(first) - halved).mean()
    assert gap < 5.0
    assert gap < 0.25 * np.abs(pixels(first) - photo.astype(np.float32)).mean()
    # the download waits for the full render, which is what it saves
    assert session.last_full_params is not None
    assert session.last_full.shape == (240, 320, 3)


def test_load_and_small_uploads_render_once(logic, two_plane_scene, small_threshold):
    # load (the library's and the tests' entry) never shows a first look
    out = logic.load(*upload_args(two_plane_scene))
    assert len(out) == 6 and "full render" in out[5] and "first look" not in out[5]
    assert pixels(out[2]).shape == (240, 320, 3)


def test_photo_at_the_threshold_is_rendered_once(logic, two_plane_scene, monkeypatch):
    monkeypatch.setattr(app.settings, "FIRST_LOOK_PIXELS", 320 * 240)
    steps = list(logic.load_steps(*upload_args(two_plane_scene)))
    assert len(steps) == 1 and "full render" in steps[0][5]


def test_value_set_after_the_first_look_wins(logic, two_plane_scene, small_threshold):
    """A slider moved while the full render of the upload runs: that render's picture is
    dropped, the newer value's preview stays on screen."""
    steps = logic.load_steps(*upload_args(two_plane_scene))
    session, *_ = next(steps)
    preview = logic.render_preview(session, 0.9, APERTURE)
    assert "preview render" in preview[3]
    session_again, focus, *shown = next(steps)
    assert session_again is session and focus == {"__type__": "update"}
    assert all(update == {"__type__": "update"} for update in shown)
    with pytest.raises(StopIteration):
        next(steps)


def test_first_look_of_a_bad_file_is_an_error(logic, tmp_path, small_threshold):
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"\xff\xd8\xff not a jpeg")
    with pytest.raises(Exception) as err:
        list(logic.load_steps(str(bad), None, "disparity", None, 0.5, APERTURE))
    assert type(err.value).__name__ == "Error" and "broken.jpg" in str(err.value.message)


def test_click_on_a_large_photo_refocuses_a_first_look_then_in_full(
    logic, two_plane_scene, small_threshold
):
    session = logic.load(*upload_args(two_plane_scene))[0]
    steps = list(logic.click_steps(session, list(two_plane_scene.near_point), APERTURE))
    assert len(steps) == 2
    (focus, span, first, _, _, first_info), last = steps
    # the sliders are set once, by the first picture: the near plane, and a range
    assert isinstance(focus, float) and focus < 0.2 and isinstance(span, float)
    assert "first look render" in first_info and "focused on the click" in first_info
    assert pixels(first).shape == (120, 160, 3)
    assert last[0] == last[1] == {"__type__": "update"}
    assert pixels(last[2]).shape == (240, 320, 3)
    assert "full render" in last[5] and "focused on the click" in last[5]
    assert session.last_full_params.position == pytest.approx(focus, abs=1e-9)
    # click (the API's and the bench's) renders once, at full resolution
    out = logic.click(session, list(two_plane_scene.far_point), APERTURE)
    assert len(out) == 6 and "full render" in out[5] and "first look" not in out[5]
    assert out[0] > 0.5


def test_value_set_after_a_clicks_first_look_wins(logic, two_plane_scene, small_threshold):
    session = logic.load(*upload_args(two_plane_scene))[0]
    steps = logic.click_steps(session, list(two_plane_scene.near_point), APERTURE)
    next(steps)
    assert "preview render" in logic.render_preview(session, 0.7, APERTURE)[3]
    focus, span, *shown = next(steps)
    assert focus == span == {"__type__": "update"}
    assert all(update == {"__type__": "update"} for update in shown)
