"""Handler-level tests of what a session shows when events overlap (a render of an older
value finishing late) and of the cap on open photos (the least recently used one closed)."""

from __future__ import annotations

import threading

import gradio as gr
import pytest

from app.cache import SceneCache
from app.handlers import RefocusApp
from app.reporting import SKIP4

APERTURE = 0.5


class SlowFirst:
    """The model, whose full render of ``slow_focus`` waits until :attr:`go` is set."""

    def __init__(self, model, slow_focus: float) -> None:
        self.model = model
        self.slow_focus = slow_focus
        self.started = threading.Event()
        self.go = threading.Event()

    def __getattr__(self, name):
        return getattr(self.model, name)

    def render(self, scene, focus, blur, **options):
        if "max_side" not in options and focus == pytest.approx(self.slow_focus):
            self.started.set()
            assert self.go.wait(60)
        return self.model.render(scene, focus, blur, **options)


def is_skip(update) -> bool:
    return update == {"__type__": "update"}


@pytest.fixture
def slow(tiny_model, tmp_path, two_plane_scene):
    """(logic, session, model) with the photo loaded; the full render of slider 0.397 is slow."""
    model = SlowFirst(tiny_model, slow_focus=1 - 0.397)
    logic = RefocusApp(model, SceneCache(256 << 20), download_root=tmp_path / "dl")
    session = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)[0]
    yield logic, session, model
    model.go.set()  # a failed test leaves no thread waiting


def render_in_thread(fn, *args):
    out = {}
    thread = threading.Thread(target=lambda: out.setdefault("value", fn(*args)))
    thread.start()
    return thread, out


class TestLateRenderDropped:
    def test_full_render_of_an_older_value_after_a_newer_preview(self, slow):
        # the slider released at 0.397; its full render is slow (a loaded server); the user
        # moves on to 0.706, whose preview is shown first; the late 0.397 must not replace it
        logic, session, model = slow
        thread, late = render_in_thread(logic.render_full, session, 0.397, APERTURE)
        assert model.started.wait(60)
        preview = logic.render_preview(session, 0.706, APERTURE)
        assert "focus 0.706" in preview[3] and "preview" in preview[3]
        model.go.set()
        thread.join(60)
        assert late["value"] == SKIP4  # dropped: the picture stays the 0.706 preview
        # the release at 0.706 renders it in full, and the status names it
        full = logic.render_full(session, 0.706, APERTURE)
        assert "focus 0.706" in full[3] and "full render" in full[3]
        assert session.last_full_params.position == pytest.approx(0.706)

    def test_full_render_of_an_older_value_after_a_newer_full_render(self, slow):
        logic, session, model = slow
        thread, late = render_in_thread(logic.render_full, session, 0.397, APERTURE)
        assert model.started.wait(60)
        newer = logic.render_full(session, 0.706, APERTURE)
        assert "focus 0.706" in newer[3]
        model.go.set()
        thread.join(60)
        assert all(is_skip(u) for u in late["value"])
        assert session.last_full_params.position == pytest.approx(0.706)

    def test_the_same_value_set_again_is_not_dropped(self, slow):
        # 0.397 released, dragged to 0.706 and back to 0.397: the running render is the
        # last value set, and is shown
        logic, session, model = slow
        thread, late = render_in_thread(logic.render_full, session, 0.397, APERTURE)
        assert model.started.wait(60)
        logic.render_preview(session, 0.706, APERTURE)
        logic.render_preview(session, 0.397, APERTURE)
        model.go.set()
        thread.join(60)
        assert "focus 0.397" in late["value"][3]
        assert session.last_full_params.position == pytest.approx(0.397)


class TestRoomForANewPhoto:
    def test_least_recently_used_photo_is_closed(self, tiny_model, tmp_path, two_plane_scene):
        logic = RefocusApp(
            tiny_model, SceneCache(64 << 20), download_root=tmp_path / "dl", max_sessions=2
        )
        args = (str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        a = logic.load(*args)[0]
        b = logic.load(*args)[0]
        logic.render_full(a, 0.3, APERTURE)  # a used since b: b is the least recently used
        c = logic.load(*args)[0]
        assert b.closed and not a.closed and not c.closed and logic.live_sessions == 2
        # b's user comes back: told why, and what to do
        with pytest.raises(gr.Error, match="closed to make room.*upload it again"):
            logic.render_full(b, 0.4, APERTURE)
        with pytest.raises(gr.Error, match="closed to make room"):
            logic.click(b, [10, 10], APERTURE)

    def test_photos_in_use_are_not_closed(self, tiny_model, tmp_path, two_plane_scene):
        logic = RefocusApp(
            tiny_model, SceneCache(64 << 20), download_root=tmp_path / "dl", max_sessions=1
        )
        args = (str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        a = logic.load(*args)[0]
        a.hold()  # an event is rendering it
        with pytest.raises(gr.Error, match="in use"):
            logic.load(*args)
        assert not a.closed
        a.let_go()
        assert logic.load(*args)[0] is not None and a.closed
