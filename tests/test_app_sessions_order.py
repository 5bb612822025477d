"""Handler-level tests of what a session shows when events overlap (a render of an older
value finishing late) and of the cap on open photos (the least recently used one closed)."""

from __future__ import annotations

import threading

import gradio as gr
import numpy as np
import pytest
from PIL import Image

from app.cache import SceneCache
from app.handlers import RefocusApp
from app.render_events import SKIP6
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


def pixels(update) -> np.ndarray:
    """The picture of an image update (a file path)."""
    return np.asarray(Image.open(update["value"]))


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


#: what settle returns when the page is left as it is
SETTLED = (*SKIP4, gr.skip())


def page(
    focus: float,
    f_number: float = APERTURE,
    view: str = "Bokeh",
    focal_range: float = 0.0,
    blades: int = 0,
) -> tuple:
    """The controls' values as the page sends them to :meth:`RenderEvents.settle` (the
    render events' inputs after the session), before the status line."""
    return (focus, f_number, blades, 0.0, True, True, view, "balanced", True, focal_range)


class TestPageBroughtInLine:
    """:meth:`RenderEvents.settle`, which runs on the page after each preview and full
    render, with the controls' values and the status line that the page then shows."""

    def test_full_render_sent_again_after_a_preview_that_came_before_it(self, slow):
        # the preview and the full render of 0.706 ran side by side; the preview's picture
        # reached the page second
        logic, session, _ = slow
        preview = logic.render_preview(session, 0.706, APERTURE)
        assert "preview" in preview[3]
        full = logic.render_full(session, 0.706, APERTURE)
        assert "full render" in full[3]
        # the full render's download finds the preview on the page: the button stays
        # disabled, as the preview left it
        assert is_skip(logic.download(session, "JPEG", preview[3]))
        again = logic.settle(session, *page(0.706), preview[3])
        assert again[3] == full[3]  # sent again, not rendered again: the same status line
        assert is_skip(again[4])  # Download as it is: enabled by the download that follows
        np.testing.assert_array_equal(pixels(again[0]), pixels(full[0]))
        saved = logic.download(session, "JPEG", again[3])
        assert saved["interactive"] is True and "_focus0.706_" in saved["value"]
        # the other order: the page shows the full render already (a click's with its note)
        assert logic.settle(session, *page(0.706), full[3]) == SETTLED
        assert logic.settle(session, *page(0.706), full[3] + " | focused on the click") == SETTLED

    def test_a_click_sent_again_keeps_its_note(self, slow):
        # a click's full render came before the first look it follows: sent again, its
        # status line still says where the photo was focused
        logic, session, _ = slow
        focus, span, *out = logic.click(session, [40, 30], APERTURE)
        assert "full render" in out[3] and "focused on the click" in out[3]
        again = logic.settle(session, *page(focus, focal_range=span), "first look")
        assert again[3] == out[3]
        assert logic.settle(session, *page(focus, focal_range=span), out[3]) == SETTLED

    def test_a_release_older_than_the_last_change_is_rendered_over(self, slow):
        # f/0.5 rendered in full; a click into the number box sends its release (f/0.5),
        # then f/2 is typed; the server gets the preview of f/2 first, then the old release
        logic, session, _ = slow
        logic.render_full(session, 0.3, APERTURE)
        logic.render_preview(session, 0.3, 2.0)
        old = logic.render_full(session, 0.3, APERTURE)
        assert "f/0.5" in old[3] and "full render" in old[3]
        # the page shows f/0.5 in full under f/2: f/2 is rendered in full
        fixed = logic.settle(session, *page(0.3, 2.0), old[3])
        assert "f/2, " in fixed[3] and "full render" in fixed[3]
        assert fixed[4] == {"__type__": "update", "interactive": False}  # until its file
        assert session.last_full_params.f_number == 2.0
        assert "_f2_K" in logic.download(session, "JPEG")["value"]
        # in line now: nothing more
        assert logic.settle(session, *page(0.3, 2.0), fixed[3]) == SETTLED

    def test_a_release_older_than_an_option_is_rendered_over(self, slow):
        # the focus slider let go at 0.3 (its release on its way), then 6 blades chosen:
        # the option's full render reaches the server first, and the release, with 0
        # blades, replaces it
        logic, session, _ = slow
        logic.render_full(session, 0.2, APERTURE)
        logic.render_full(session, 0.3, APERTURE, 6)
        old = logic.render_full(session, 0.3, APERTURE, 0)
        assert "full render" in old[3] and session.last_full_params.blades == 0
        fixed = logic.settle(session, *page(0.3, blades=6), old[3])
        assert "full render" in fixed[3] and fixed[3] != old[3]
        assert session.last_full_params.blades == 6
        assert logic.download(session, "JPEG")["interactive"] is True
        assert session.download_file[0].blades == 6  # the file is the 6-blade render
        assert logic.settle(session, *page(0.3, blades=6), fixed[3]) == SETTLED
        # values asked for long before are not the page's last change: left alone
        logic.render_full(session, 0.5, APERTURE)
        late = logic.render_full(session, 0.6, APERTURE)
        assert logic.settle(session, *page(0.3, blades=6), late[3]) == SETTLED

    def test_a_drag_just_started_is_left_to_its_previews(self, slow):
        # the page shows the full render of 0.3, and its slider has moved on to 0.4 whose
        # preview has not reached the server yet: no full render in the middle of a drag
        logic, session, _ = slow
        full = logic.render_full(session, 0.3, APERTURE)
        assert logic.settle(session, *page(0.4), full[3]) == SETTLED
        assert session.last_full_params.position == pytest.approx(0.3)

    def test_nothing_while_a_preview_waits_for_its_release(self, slow):
        logic, session, _ = slow
        logic.render_full(session, 0.2, APERTURE)
        shown = logic.render_preview(session, 0.3, APERTURE)[3]
        assert logic.settle(session, *page(0.3), shown) == SETTLED  # the release of 0.3 is to come
        # the page's controls already moved on (a drag): still only previews
        assert logic.settle(session, *page(0.35), shown) == SETTLED
        # the slider came back to 0.2 (its full render is stored) while the preview of 0.3
        # is on screen: only the release of 0.2 shows it again
        shown = logic.render_preview(session, 0.2, APERTURE)[3]
        assert "preview" in shown and logic.settle(session, *page(0.2), shown) == SETTLED
        assert logic.settle(None, *page(0.2), shown) == SETTLED
        # values the render events refuse: they say so, settle stays silent
        assert logic.settle(session, *page(7.0), shown) == SETTLED

    def test_waits_for_the_full_render_on_its_way(self, slow):
        logic, session, model = slow
        shown = logic.render_preview(session, 0.397, APERTURE)[3]
        thread, full = render_in_thread(logic.render_full, session, 0.397, APERTURE)
        assert model.started.wait(60)
        # still rendering: its own picture will reach the page after the preview's
        assert logic.settle(session, *page(0.397), shown) == SETTLED
        model.go.set()
        thread.join(60)
        assert "full render" in full["value"][3]
        # had its picture come before the preview's, a later settle sends it again, in the
        # view the page shows
        again = logic.settle(session, *page(0.397, view="Disparity"), shown)
        assert again[3] == full["value"][3] and "Disparity" in again[2]["value"]


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


class Tab:
    """The request Gradio gives a browser tab's events (its session hash)."""

    session_hash = "tab-1"


class PausedRender:
    """The model, whose next full render waits until :attr:`go` is set once :meth:`pause`
    is called."""

    def __init__(self, model) -> None:
        self.model = model
        self.paused = False
        self.started = threading.Event()
        self.go = threading.Event()

    def __getattr__(self, name):
        return getattr(self.model, name)

    def pause(self) -> None:
        self.paused = True

    def render(self, scene, focus, blur, **options):
        if self.paused and "max_side" not in options:
            self.paused = False
            self.started.set()
            assert self.go.wait(60)
        return self.model.render(scene, focus, blur, **options)


class TestEventsOfThePhotoBefore:
    """A tab that uploads photo B while events of photo A are on their way: none of them
    shows A's picture or sets A's values on B's page, and none tells the user that a photo
    was closed. Gradio hands an event the session its tab holds when the event runs: B's,
    once B's load has set it, A's (closed) while B is being loaded."""

    @pytest.fixture
    def two_photos(self, tiny_model, tmp_path, scene_factory):
        model = PausedRender(tiny_model)
        logic = RefocusApp(model, SceneCache(256 << 20), download_root=tmp_path / "dl")
        a = scene_factory(320, 240, seed=1, stem="a")
        b = scene_factory(360, 240, seed=2, stem="b")

        def load(scene, replacing):
            return logic.load(str(scene.photo), None, "disparity", replacing, 0.5, APERTURE,
                              request=Tab())[0]  # fmt: skip

        yield logic, model, load, a, b
        model.go.set()  # a failed test leaves no thread waiting

    def test_events_sent_for_the_photo_before_are_dropped(self, two_photos):
        logic, _, load, a_photo, b_photo = two_photos
        a = load(a_photo, None)
        a_id = logic.photo_id(a)
        b = load(b_photo, a)
        assert a.closed and logic.photo_id(b) not in ("", a_id)
        shown, full = b.last_full_info, b.last_full_params
        # sent from A's page, run with B's session
        assert logic.render_preview(b, 0.2, APERTURE, photo_id=a_id) == SETTLED
        assert logic.render_full(b, 0.2, APERTURE, photo_id=a_id) == SKIP4
        assert logic.click(b, [10, 10], APERTURE, photo_id=a_id) == SKIP6
        assert logic.settle(b, *page(0.2), a_id, shown) == SETTLED
        assert b.last_full_info == shown and b.full_params == full == b.last_full_params
        # B's own events render
        out = logic.render_full(b, 0.2, APERTURE, photo_id=logic.photo_id(b))
        assert out[3].startswith("360x240 px | focus 0.200 (")
        assert logic.render_preview(b, 0.3, APERTURE, photo_id=logic.photo_id(b))[3].startswith(
            "360x240 px | focus 0.300 ("
        )

    def test_a_click_whose_photo_is_replaced_while_it_renders(self, two_photos):
        # the click's full render of A is running when B's upload replaces A: neither its
        # picture nor the focus and range it found reach the page
        logic, model, load, a_photo, b_photo = two_photos
        a = load(a_photo, None)
        model.pause()
        thread, out = render_in_thread(logic.click, a, [40, 30], APERTURE)
        assert model.started.wait(60)
        b = load(b_photo, a)
        model.go.set()
        thread.join(60)
        assert out["value"] == SKIP6
        # B keeps the range its own load gave it (its subject's), not the click's on A
        assert not b.closed and b.last_full_params.focal_range == b.auto_range

    def test_a_preview_whose_photo_is_replaced_while_it_renders(self, two_photos):
        logic, model, load, a_photo, b_photo = two_photos
        a = load(a_photo, None)
        model.pause()
        thread, out = render_in_thread(logic.render_full, a, 0.3, APERTURE)
        assert model.started.wait(60)
        load(b_photo, a)
        model.go.set()
        thread.join(60)
        assert out["value"] == SKIP4

    def test_events_that_reach_the_closed_photo_are_silent(self, two_photos):
        # B is being loaded (A closed, the tab's state still A's): A's events are dropped,
        # with no message that the photo was closed to free memory
        logic, _, load, a_photo, b_photo = two_photos
        a = load(a_photo, None)
        load(b_photo, a)
        assert logic.render_full(a, 0.3, APERTURE) == SKIP4
        assert logic.render_preview(a, 0.3, APERTURE) == SETTLED
        assert logic.click(a, [10, 10], APERTURE) == SKIP6
        assert logic.settle(a, *page(0.3), "") == SETTLED

    def test_a_photo_closed_while_idle_still_says_so(self, two_photos):
        logic, _, load, a_photo, _ = two_photos
        a = load(a_photo, None)
        a.close()  # idle, or closed to make room: no other photo in its tab
        with pytest.raises(gr.Error, match="upload it again"):
            logic.render_full(a, 0.3, APERTURE)
        with pytest.raises(gr.Error, match="upload it again"):
            logic.click(a, [10, 10], APERTURE)
