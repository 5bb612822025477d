"""The brushes, the loupe and the aperture note given what a page or an API caller can send:
a photo far wider than tall, paint layers of two sizes, a click at NaN, an f-number past the
lens's range (handlers called directly, the tiny model)."""

from __future__ import annotations

from pathlib import Path

import gradio as gr
import numpy as np
import pytest
from PIL import Image

from app.cache import SceneCache
from app.handlers import RefocusApp
from d2f_core.io.depth import check_aspect


@pytest.fixture
def logic(tiny_model, tmp_path):
    return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "downloads")


def _load(logic, tmp_path, h: int, w: int):
    rng = np.random.default_rng(0)
    path = tmp_path / f"photo_{w}x{h}.png"
    Image.fromarray((rng.random((h, w, 3)) * 255).astype(np.uint8)).save(path)
    session = logic.load(str(path), None, "disparity", None, 0.5, 2.8)[0]
    assert session is not None and session.size == (w, h)
    return session


def _controls(session) -> tuple:
    """The page's render inputs after the session, in order, the photo's id last."""
    return (0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", True, 0.0, session.token)


def _paint(canvas: np.ndarray, green: bool) -> np.ndarray:
    """An RGBA layer the size of ``canvas`` with its left half painted."""
    layer = np.zeros((*canvas.shape[:2], 4), np.uint8)
    layer[:, : canvas.shape[1] // 2] = (40, 200, 40, 150) if green else (200, 40, 40, 150)
    return layer


def test_paint_on_the_canvas_of_a_photo_250_times_wider_than_tall(logic, tmp_path):
    session = _load(logic, tmp_path, 16, 4000)
    canvas = logic.paint_canvas(session)["background"]
    assert canvas.shape[:2] == (4, 1024)  # 4.1 px tall, rounded: 2.4 % off the photo's aspect
    editor = {"background": canvas, "layers": [_paint(canvas, green=True)], "composite": None}
    out = logic.apply_paint(session, editor, True, *_controls(session))
    assert session.paint_id and "sharp" in session.paint_files
    assert len(out) == 4
    with Image.open(session.paint_files["sharp"]) as mask:
        assert mask.size == (1024, 4)


def test_paint_of_another_shape_is_still_refused(logic, tmp_path):
    session = _load(logic, tmp_path, 16, 4000)
    layer = _paint(np.zeros((12, 1600, 3)), green=False)  # 12 px tall: twice the photo's
    editor = {"background": None, "layers": [layer], "composite": None}
    with pytest.raises(gr.Error, match=r"painted blur mask is 1600x12, not the photo's shape"):
        logic.apply_paint(session, editor, True, *_controls(session))
    assert not session.paint_id


def test_paint_layers_of_two_sizes_are_named(logic, tmp_path):
    session = _load(logic, tmp_path, 240, 320)
    big, small = np.zeros((240, 320, 3)), np.zeros((120, 160, 3))
    editor = {"layers": [_paint(big, True), _paint(small, False)], "composite": None}
    with pytest.raises(gr.Error, match=r"paint layers differ in size \(320x240 and 160x120\)"):
        logic.apply_paint(session, editor, True, *_controls(session))


def test_a_loupe_click_at_nan_is_named(logic, tmp_path):
    session = _load(logic, tmp_path, 48, 64)
    logic.render_full(session, *_controls(session))
    for point in ([float("nan"), 5.0], [5.0, float("inf")]):
        with pytest.raises(gr.Error, match="x and y must be finite"):
            logic.loupe(session, point, *_controls(session))


@pytest.mark.parametrize("f_number", [float("inf"), 1e9, 0.1, -2, float("nan"), "f/2", None])
def test_the_aperture_note_never_raises(logic, f_number):
    note = logic.blur_note(None, f_number)
    assert note.startswith("50 mm lens on full frame") and "blur K" not in note
    assert logic.blur_note(None, 2.8).startswith("f/2.8: blur K = ")


def test_a_downscaled_side_rounded_to_a_pixel_keeps_the_aspect():
    check_aspect((6, 1600), (16, 4000), "m")  # 6.4 rounded
    check_aspect((4000, 16), (1600, 6), "m")  # either way round
    check_aspect((1, 250), (3, 1000), "m")  # 0.75 px rounded up
    # rounding cannot make these: a 33 % stretch, twice the aspect, and again at 1-2 px
    for shape, photo in (((3, 4000), (4, 4000)), ((2, 2), (3, 6)), ((557, 2), (4452, 8))):
        with pytest.raises(ValueError, match="aspect ratios differ"):
            check_aspect(shape, photo, "m")
    for shape in ((12, 1600), (6, 1000), (1600, 6)):
        with pytest.raises(ValueError, match="aspect ratios differ"):
            check_aspect(shape, (16, 4000), "m")


def test_apply_with_nothing_painted_says_so(logic, tmp_path):
    session = _load(logic, tmp_path, 48, 64)
    canvas = logic.paint_canvas(session)["background"]
    empty = np.zeros((*canvas.shape[:2], 4), np.uint8)
    for layers in ([], [empty]):
        editor = {"background": canvas, "layers": layers, "composite": None}
        with pytest.warns(UserWarning, match="Nothing is painted"):
            out = logic.apply_paint(session, editor, True, *_controls(session))
        assert all(isinstance(o, dict) and o.get("__type__") == "update" for o in out), out
        assert session.paint_id == ""
    # with paint applied before, an empty canvas clears it (and renders)
    painted = {"background": canvas, "layers": [_paint(canvas, True)], "composite": None}
    logic.apply_paint(session, painted, True, *_controls(session))
    assert session.paint_id
    editor = {"background": canvas, "layers": [empty], "composite": None}
    logic.apply_paint(session, editor, True, *_controls(session))
    assert session.paint_id == "" and session.brushes is None


def test_the_canvas_is_at_most_its_side(logic, tmp_path):
    session = _load(logic, tmp_path, 1200, 1800)
    canvas = logic.paint_canvas(session)["background"]
    assert canvas.shape[:2] == (683, 1024) and max(session.before.shape[:2]) == 1600


def test_the_command_runs_after_the_tab_is_closed(logic, tmp_path, tiny_checkpoint):
    import re
    import shlex

    from app.sessions import delete_session
    from d2f_core import cli

    rng = np.random.default_rng(3)
    photo = tmp_path / "holiday.png"
    Image.fromarray((rng.random((96, 128, 3)) * 255).astype(np.uint8)).save(photo)
    session = logic.load(str(photo), None, "disparity", None, 0.5, 2.8)[0]
    canvas = logic.paint_canvas(session)["background"]
    editor = {"background": canvas, "layers": [_paint(canvas, True)], "composite": None}
    info = logic.apply_paint(session, editor, True, *_controls(session))[3]
    download = np.asarray(Image.open(logic.download(session, "PNG")["value"]).convert("RGB"))
    words = shlex.split(re.search(r"reproduce: (d2f render .*?)(?: \| |$)", info).group(1))
    assert words[2] == "holiday.png" and "--sharp-mask" in words
    mask = Path(words[words.index("--sharp-mask") + 1])
    folder = Path(session.folder)
    delete_session(session)  # the tab closed: its folder goes
    assert not folder.exists() and mask.is_file()
    argv = words[2:]
    argv[0] = str(photo)
    argv[argv.index("-o") + 1] = str(tmp_path / "cli.png")
    assert cli.main(["render", *argv, "--weights", str(tiny_checkpoint), "-q"]) == 0
    cli_out = np.asarray(Image.open(tmp_path / "cli.png").convert("RGB"))
    np.testing.assert_array_equal(cli_out, download)


def test_the_photo_keeps_its_name_when_the_panel_sends_it_back(logic, tmp_path):
    rng = np.random.default_rng(4)
    photo = tmp_path / "holiday.png"
    Image.fromarray((rng.random((48, 64, 3)) * 255).astype(np.uint8)).save(photo)
    session = logic.load(str(photo), None, "disparity", None, 0.5, 2.8)[0]
    assert session.upload.name == "holiday.png"
    # after a failed upload the panel shows the kept copy; a depth source switched then
    # sends that copy back, under its own name
    again = logic.load(str(session.upload), None, "disparity", session, 0.5, 2.8)[0]
    assert again.name == "holiday" and again.upload_name == "holiday.png"
