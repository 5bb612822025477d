"""Handler-level tests of the web app (no browser, no server): app.imaging, app.cache,
app.handlers and the event wiring of app.main.build_demo."""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import gradio as gr
import numpy as np
import pytest
from _io_writers import apple_mpo, lensblur_jpeg
from PIL import Image

from app import imaging
from app.cache import SceneCache, content_key, scene_nbytes
from app.handlers import RefocusApp
from app.sessions import Session, delete_session
from app.settings import (
    DEFAULT_F_NUMBER,
    PREVIEW_MAX_SIDE,
    VIEWS,
    RenderParams,
    blur_px,
    disparity_of,
    position_of,
)
from d2f_core import io as d2f_io
from d2f_core.lens import f_number_for

#: f/0.5, the widest aperture the handlers take (the page's slider starts at f/1): K = 44.4 px
#: on the 320 px wide test photo (d2f_core.lens.blur_px), both planes far out of focus when
#: the other is focused. (The tiny random model's fusion keeps much of the sharp input where
#: a blur is under about 30 px: at f/1, 22 px, the far plane kept 60 % of its sharpness.)
APERTURE = 0.5


def pixels(update) -> np.ndarray:
    """The picture an image update sends to the browser (a JPEG file the app wrote)."""
    return np.asarray(Image.open(update["value"]))


def assert_shows(update, expected: np.ndarray) -> None:
    """The browser's JPEG is ``expected`` up to compression (the test photo's 2x2 random
    texture is JPEG's worst case: 5.3 levels mean error at quality 90)."""
    shown = pixels(update).astype(np.int16)
    assert shown.shape == expected.shape
    assert np.abs(shown - expected.astype(np.int16)).mean() < 8


def is_skip(update) -> bool:
    """``gr.skip()`` is an update that changes nothing."""
    return update == {"__type__": "update"}


@pytest.fixture
def logic(tiny_model, tmp_path):
    return RefocusApp(tiny_model, SceneCache(256 << 20), download_root=tmp_path / "downloads")


@pytest.fixture
def loaded(logic, two_plane_scene):
    """(logic, session, scene) after uploading the two-plane photo with its disparity map."""
    out = logic.load(
        str(two_plane_scene.photo), str(two_plane_scene.disparity), "disparity", None, 0.5, APERTURE
    )
    return logic, out[0], two_plane_scene


def write_exif_rotated(path: Path, image: np.ndarray, orientation: int = 6) -> None:
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(image).save(path, exif=exif, quality=95)


# ------------------------------------------------------------------------- imaging


class TestLoadPhoto:
    def test_png_roundtrip(self, two_plane_scene):
        photo = imaging.load_photo(two_plane_scene.photo, "scene.png")
        assert photo.image.dtype == np.float32
        assert photo.image.shape == (240, 320, 3)
        assert photo.shown_size == photo.size == (320, 240)
        assert photo.notice is None
        np.testing.assert_allclose(photo.image * 255, two_plane_scene.image, atol=0.5)

    def test_exif_orientation_applied(self, tmp_path):
        image = np.zeros((40, 80, 3), np.uint8)
        image[:, :10] = 255  # a white band on the left of the stored pixels
        path = tmp_path / "rot.jpg"
        write_exif_rotated(path, image, orientation=6)  # "rotate 90 CW to display"
        photo = imaging.load_photo(path)
        assert photo.image.shape == (80, 40, 3)
        assert photo.shown_size == (40, 80)
        # after a 90 degree clockwise turn the left band is at the top
        assert photo.image[:10].mean() > 0.9 and photo.image[-20:].mean() < 0.1

    @pytest.mark.parametrize(
        ("content", "match"),
        [
            (b"", "empty"),
            (b"this is not an image at all\n" * 20, "not an image"),
        ],
    )
    def test_bad_files(self, tmp_path, content, match):
        path = tmp_path / "upload.jpg"
        path.write_bytes(content)
        with pytest.raises(ValueError, match=match) as err:
            imaging.load_photo(path, "holiday.jpg")
        assert str(tmp_path) not in str(err.value)  # the user sees their file name only
        assert "holiday.jpg" in str(err.value)

    def test_truncated_jpeg(self, tmp_path, two_plane_scene):
        full = tmp_path / "full.jpg"
        Image.fromarray(two_plane_scene.image).save(full, quality=90)
        cut = tmp_path / "cut.jpg"
        cut.write_bytes(full.read_bytes()[: full.stat().st_size // 3])
        with pytest.raises(ValueError, match="truncated|corrupt"):
            imaging.load_photo(cut, "cut.jpg")

    def test_one_pixel_refused(self, tmp_path):
        path = tmp_path / "dot.png"
        Image.new("RGB", (1, 1), (10, 20, 30)).save(path)
        with pytest.raises(ValueError, match=r"only 1x1 pixels"):
            imaging.load_photo(path, "dot.png")

    @pytest.mark.slow
    def test_40_megapixel_is_downscaled_with_notice(self, tmp_path):
        path = tmp_path / "big.jpg"
        rng = np.random.default_rng(0)
        small = rng.integers(0, 255, (125, 200, 3), dtype=np.uint8)
        Image.fromarray(small).resize((8000, 5000), Image.Resampling.NEAREST).save(path, quality=80)
        t0 = time.perf_counter()
        photo = imaging.load_photo(path, "big.jpg")
        elapsed = time.perf_counter() - t0
        w, h = photo.size
        assert w * h <= imaging.MAX_PIXELS
        assert abs(w / h - 1.6) < 0.01
        assert photo.shown_size == (8000, 5000)
        assert "8000x5000" in photo.notice and "resized" in photo.notice
        assert elapsed < 20

    def test_rgba_on_white(self, tmp_path):
        path = tmp_path / "alpha.png"
        a = np.zeros((32, 32, 4), np.uint8)
        a[..., 0] = 255
        a[:, 16:, 3] = 255  # left half transparent, right half opaque red
        Image.fromarray(a, "RGBA").save(path)
        img = imaging.load_photo(path).image
        np.testing.assert_allclose(img[:, :16], 1.0, atol=1 / 255)
        np.testing.assert_allclose(
            img[:, 16:], np.broadcast_to([1.0, 0.0, 0.0], (32, 16, 3)), atol=1 / 255
        )


class TestLoadDepth:
    def test_disparity_png_resized_to_photo(self, two_plane_scene):
        d, stored = imaging.load_depth_map(two_plane_scene.disparity, (640, 480), "disparity")
        assert stored == (320, 240)
        assert d.shape == (480, 640) and d.dtype == np.float32
        assert d.min() >= 0 and d.max() <= 1
        x0, y0, x1, y1 = (2 * v for v in two_plane_scene.box)
        assert d[(y0 + y1) // 2, (x0 + x1) // 2] > 0.9  # near box = 1 after normalising
        assert d[5, -5] < 0.1

    def test_depth_kind_inverts_order(self, tmp_path):
        depth = np.full((20, 30), 4000, np.uint16)  # mm
        depth[5:15, 5:15] = 1000  # a nearer square
        path = tmp_path / "depth16.png"
        Image.fromarray(depth).save(path)
        d, _ = imaging.load_depth_map(path, (30, 20), "depth")
        assert d[10, 10] > 0.9 and d[1, 25] < 0.1

    def test_npy(self, tmp_path):
        path = tmp_path / "d.npy"
        np.save(path, np.linspace(1, 3, 12 * 16, dtype=np.float32).reshape(12, 16))
        d, stored = imaging.load_depth_map(path, (16, 12))
        assert stored == (16, 12)
        assert d[0, 0] < 0.05 and d[-1, -1] > 0.95

    def test_wrong_type_and_aspect_are_errors(self, tmp_path):
        text = tmp_path / "notes.txt"
        text.write_text("depth? no")
        with pytest.raises(ValueError, match="notes.txt"):
            imaging.load_depth_map(text, (32, 32), name="notes.txt")
        tall = tmp_path / "tall.png"
        Image.fromarray(np.zeros((64, 16), np.uint8) + 3).save(tall)
        with pytest.raises(ValueError, match="aspect"):
            imaging.load_depth_map(tall, (64, 16))


class TestDepthNotes:
    """A map's holes and a map of one value are said to the user, not only to the log."""

    def test_holes_and_one_value(self, tmp_path):
        holed = np.linspace(1, 3, 12 * 16, dtype=np.float32).reshape(12, 16)
        holed[:3] = np.nan
        np.save(tmp_path / "holed.npy", holed)
        notes: list[str] = []
        d, _ = imaging.load_depth_map(
            tmp_path / "holed.npy", (16, 12), name="holed.npy", notes=notes
        )
        assert np.isfinite(d).all()
        assert notes == [
            "holed.npy: 48 of its 192 pixels (25.0 %) hold no depth (NaN or infinite); "
            "they were filled from the depth around them."
        ]
        flat = np.full((12, 16), 2.0)
        flat[:, :4] = 0.0  # zero is no distance: holes of a depth map
        np.save(tmp_path / "flat.npy", flat)
        notes = []
        imaging.load_depth_map(tmp_path / "flat.npy", (16, 12), "depth", "flat.npy", notes)
        assert len(notes) == 2 and "(NaN, infinite, zero or negative)" in notes[0]
        assert notes[1].startswith("flat.npy holds one value nearly everywhere")
        almost = np.full((100, 100), 0.3, np.float32)
        almost[:5, :5] = 0.9  # 0.25 % of the map: outside the range the library stretches
        np.save(tmp_path / "almost.npy", almost)
        notes = []
        imaging.load_depth_map(
            tmp_path / "almost.npy", (100, 100), "disparity", "almost.npy", notes
        )
        assert len(notes) == 1 and notes[0].startswith("almost.npy holds one value nearly")
        almost[:10, :10] = 0.9  # 1 %: a subject the render sets apart
        np.save(tmp_path / "almost.npy", almost)
        notes = []
        imaging.load_depth_map(
            tmp_path / "almost.npy", (100, 100), "disparity", "almost.npy", notes
        )
        assert notes == []
        notes = []  # a map with depth in it says nothing
        imaging.load_depth_map(tmp_path / "holed.npy", (16, 12), "disparity", "x", None)
        np.save(tmp_path / "ramp.npy", np.linspace(1, 3, 192).reshape(12, 16))
        imaging.load_depth_map(tmp_path / "ramp.npy", (16, 12), notes=notes)
        assert notes == []

    def test_an_upload_with_a_flat_map_warns(self, logic, two_plane_scene, tmp_path):
        np.save(tmp_path / "flat.npy", np.full((240, 320), 0.7, np.float32))
        with pytest.warns(UserWarning, match="flat.npy holds one value nearly everywhere"):
            out = logic.load(
                str(two_plane_scene.photo), str(tmp_path / "flat.npy"), "disparity", None, 0.5, 1.0
            )
        assert out[0] is not None


class TestDisplayHelpers:
    def test_colorize_known_stops(self):
        v = np.array([[0.0, 0.5, 1.0, -3.0, 7.0]], np.float32)
        out = imaging.colorize(v, "viridis")
        stops = imaging.COLORMAPS["viridis"]
        np.testing.assert_array_equal(out[0, 0], stops[0])
        np.testing.assert_array_equal(out[0, 1], stops[4])
        np.testing.assert_array_equal(out[0, 2], stops[-1])
        np.testing.assert_array_equal(out[0, 3], stops[0])  # clipped
        np.testing.assert_array_equal(out[0, 4], stops[-1])
        grey = imaging.colorize(np.array([[0.0, 0.5, 1.0]]), "gray")
        np.testing.assert_array_equal(grey[0, :, 0], [0, 128, 255])

    def test_legend_mentions_labels(self):
        html = imaging.legend_html("magma", "0 sharp", "1 <blurry>", "Defocus")
        assert "linear-gradient" in html and "0 sharp" in html and "&lt;blurry&gt;" in html

    def test_fit_display_and_to_uint8(self):
        a = np.zeros((100, 3200, 3), np.uint8)
        assert imaging.fit_display(a, 1600).shape == (50, 1600, 3)
        assert imaging.fit_display(a[:, :100], 1600) is not None
        np.testing.assert_array_equal(
            imaging.to_uint8(np.array([0.0, 0.5, 1.0, 2.0])), [0, 128, 255, 255]
        )
        # a shrink by whole cells first keeps the picture: a 4000x3000 gradient at 1600x1200
        ramp = np.broadcast_to(np.linspace(0, 255, 4000, dtype=np.float32), (3000, 4000))
        big = np.repeat(ramp[..., None], 3, axis=2).round().astype(np.uint8)
        small = imaging.fit_display(big, 1600).astype(int)
        expected = np.linspace(0, 255, 1600)
        assert small.shape == (1200, 1600, 3) and np.abs(small[600, :, 1] - expected).max() <= 2

    def test_steady_page_faults_turns_numpy_huge_pages_off(self):
        """The app's start asks NumPy for no huge-page advice on its arrays (their on-demand
        compaction stalled a 12 MP picture's conversion for up to 1.7 s)."""
        multiarray = getattr(np, "_core", None) or np.core  # NumPy 2 / NumPy 1
        multiarray = multiarray.multiarray
        before = multiarray._set_madvise_hugepage(True)  # returns the previous setting
        try:
            assert imaging.steady_page_faults() is True
            assert multiarray._set_madvise_hugepage(False) is False  # it was off
        finally:
            multiarray._set_madvise_hugepage(before)

    def test_display_views(self):
        # maps to bytes, NaN as 0, the same bytes as the gray colour table at their own size
        bokeh = np.zeros((2, 2, 3), np.uint8)
        m = np.array([[0.0, 0.5], [1.0, np.nan]], np.float32)
        views = imaging.DisplayViews(bokeh, {"Disparity": m})
        assert views["Bokeh"] is bokeh and len(views) == 2 and "Disparity" in views
        np.testing.assert_array_equal(views["Disparity"], [[0, 128], [255, 0]])
        assert views.get("Defocus") is None and "Defocus" not in views
        with pytest.raises(KeyError):
            views["Defocus"]
        values = np.random.default_rng(0).random((30, 40)).astype(np.float32)
        views = imaging.DisplayViews(np.zeros((30, 40, 3), np.uint8), {"Defocus": values})
        np.testing.assert_array_equal(views["Defocus"], imaging.colorize(values, "gray")[..., 0])
        # a 12 MP map shown at 1600x1200: its mean kept (the box means first, then bilinear);
        # a pass's 800x600 map enlarged to the picture's size
        full = np.random.default_rng(1).random((3000, 4000)).astype(np.float32)
        ramp = np.tile(np.linspace(0, 1, 800, dtype=np.float32), (600, 1))
        views = imaging.DisplayViews(
            np.zeros((1200, 1600, 3), np.uint8), {"Fusion mask": full, "Disparity": ramp}
        )
        shown, enlarged = views["Fusion mask"], views.get("Disparity")
        assert shown.shape == (1200, 1600) and abs(shown.mean() / 255 - full.mean()) < 0.01
        assert enlarged.shape == (1200, 1600) and views["Disparity"] is enlarged
        assert np.abs(enlarged[::2, ::2].astype(int) - np.round(ramp * 255)).max() <= 2
        assert [v.shape for v in views.values()] == [(1200, 1600, 3), (1200, 1600), (1200, 1600)]
        # two events of a session showing one view at once: it is resized once, for both
        from concurrent.futures import ThreadPoolExecutor

        views = imaging.DisplayViews(np.zeros((1200, 1600, 3), np.uint8), {"Defocus": ramp})
        with ThreadPoolExecutor(8) as pool:
            got = list(pool.map(lambda _: views["Defocus"], range(32)))
        assert all(g is got[0] for g in got) and got[0].shape == (1200, 1600)


# --------------------------------------------------------------------------- cache


@dataclasses.dataclass
class FakeScene:
    """Stands in for a Scene only where the cache needs *something* with arrays inside."""

    pixels: np.ndarray
    cache: dict = dataclasses.field(default_factory=dict)


class TestSceneCache:
    def test_content_key(self):
        a = np.zeros((4, 4, 3), np.float32)
        b = a.copy()
        b[0, 0, 0] = 1e-3
        d = np.zeros((4, 4), np.float32)
        assert content_key(a) == content_key(a.copy())
        assert content_key(a) != content_key(b)
        assert content_key(a) != content_key(a, d)
        assert content_key(a, d) != content_key(a, d + 0.5)
        assert content_key(a.reshape(2, 8, 3)) != content_key(a)

    def test_scene_nbytes_counts_nested(self):
        import torch

        s = FakeScene(np.zeros(1000, np.float32), {"t": torch.zeros(10, dtype=torch.float64)})
        assert scene_nbytes(s) == 4000 + 80

    def test_lru_bound_in_bytes(self):
        model = object.__new__(type("M", (), {}))
        cache = SceneCache(max_bytes=10_000)
        for i in range(5):
            cache.put(model, f"k{i}", FakeScene(np.zeros(1000, np.float32)))  # 4000 B each
        assert len(cache) == 2 and cache.nbytes == 8000
        assert cache.get(model, "k0") is None and cache.get(model, "k4") is not None
        cache.get(model, "k3")  # k3 becomes most recent; k4 is evicted next
        cache.put(model, "k5", FakeScene(np.zeros(1000, np.float32)))
        assert cache.get(model, "k4") is None and cache.get(model, "k3") is not None
        cache.put(model, "huge", FakeScene(np.zeros(10_000, np.float32)))
        assert cache.get(model, "huge") is None  # larger than the bound: not kept

    def test_growth_after_put_is_counted(self):
        model = object.__new__(type("M", (), {}))
        cache = SceneCache(max_bytes=10_000)
        a = FakeScene(np.zeros(500, np.float32))
        cache.put(model, "a", a)
        cache.put(model, "b", FakeScene(np.zeros(500, np.float32)))
        a.cache["full"] = np.zeros(1500, np.float32)  # filled lazily by render
        cache.get(model, "a")
        assert cache.nbytes == 2000 + 8000
        cache.put(model, "c", FakeScene(np.zeros(10, np.float32)))
        assert cache.get(model, "b") is None  # LRU went first
        assert cache.nbytes <= 10_000

    def test_models_do_not_share_entries(self):
        m1 = object.__new__(type("M", (), {}))
        m2 = object.__new__(type("M", (), {}))
        cache = SceneCache()
        cache.put(m1, "k", FakeScene(np.zeros(1, np.float32)))
        assert cache.get(m2, "k") is None and cache.get(m1, "k") is not None

    def test_concurrent_prepare_runs_once(self):
        model = object.__new__(type("M", (), {}))
        cache = SceneCache()
        calls = []

        def prepare():
            calls.append(1)
            time.sleep(0.05)
            return FakeScene(np.zeros(8, np.float32))

        results = []
        threads = [
            threading.Thread(
                target=lambda: results.append(cache.get_or_prepare(model, "k", prepare))
            )
            for _ in range(8)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(calls) == 1
        assert len({id(s) for s, _ in results}) == 1
        assert sorted(c for _, c in results) == [False] + [True] * 7

    def test_bad_bound(self):
        with pytest.raises(ValueError, match="max_bytes"):
            SceneCache(-1)


# ------------------------------------------------------------------------ handlers


class TestRenderParams:
    def test_rounding_and_types(self):
        p = RenderParams.from_inputs("0.43721", "2.8", "6", 30, 1, 0, size=(4000, 3000))
        # the focus slider's 0.437 (near 0, far 1) is the library's disparity 0.563
        assert p == RenderParams(0.563, 99.2, 6, 30.0, True, False, f_number=2.8)
        assert p.position == 0.437
        assert p.render_options() == {
            "fusion": False,
            "blades": 6,
            "rotation": 30.0,
            "highlight_boost": True,
            "budget": "balanced",
            "focal_range": 0.0,
        }
        fast = RenderParams.from_inputs(0.5, 10, quality="fast", size=(320, 240))
        assert fast.render_options()["budget"] == "fast"

    def test_focus_slider_reads_near_to_far(self):
        near = RenderParams.from_inputs(0.0, 2.8, size=(320, 240))
        far = RenderParams.from_inputs(1.0, 2.8, size=(320, 240))
        assert (near.focus, far.focus) == (1.0, 0.0)  # the library's disparity, 1 = near
        # every slider value comes back from its disparity unchanged (3 decimals)
        for k in range(1001):
            assert position_of(disparity_of(k / 1000)) == round(k / 1000, 3)

    @pytest.mark.parametrize(
        ("f_number", "size", "k"),
        [
            # K = 50^2 / (1000 * 36) * long side / N (a 50 mm lens, full frame, nearest 1 m)
            (1.4, (4000, 3000), 198.4),
            (16, (4000, 3000), 17.4),
            (2.8, (4000, 3000), 99.2),
            (22, (4000, 3000), 12.6),
            (1.0, (4000, 3000), 277.8),
            (2.8, (3000, 4000), 99.2),  # portrait: the long side spans the 36 mm
            (1.4, (320, 240), 15.9),
            (1.0, (6000, 2000), 300.0),  # capped
        ],
    )
    def test_f_number_to_blur_px(self, f_number, size, k):
        assert blur_px(f_number, max(size)) == k
        p = RenderParams.from_inputs(0.5, f_number, size=size)
        assert p.blur == k and p.f_number == f_number
        assert p.blur_text() == f"f/{f_number:g}, blur {k:g} px"
        if k < 300:  # the f-number that gives K px gives it back (app.bench uses it)
            assert blur_px(f_number_for(k, max(size)), max(size)) == k

    def test_blur_off_and_size_later(self):
        off = RenderParams.from_inputs(0.5, 2.8, 0, 0, True, True, "balanced", False, size=(40, 30))
        assert off.blur == 0.0 and off.f_number is None and off.blur_text() == "no blur"
        early = RenderParams.from_inputs(0.5, 2.8, size=None)  # checked before the photo
        assert early.blur == 0.0 and early.sized((4000, 3000)).blur == 99.2

    @pytest.mark.parametrize(
        "args",
        [(1.5, 10), (-0.1, 10), (0.5, 0.2), (0.5, 2000), (0.5, "nan"), (0.5, 10, 2),
         ("x", 10), (None, 10), (0.5, None)],
    )  # fmt: skip
    def test_invalid(self, args):
        with pytest.raises(gr.Error):
            RenderParams.from_inputs(*args, size=(320, 240))


class TestLoad:
    def test_upload_with_disparity(self, logic, two_plane_scene, sharpness, monkeypatch):
        from d2f_core import lens

        # a lens whose f/1 blurs the 320 px photo by K = 120 px
        monkeypatch.setattr(lens, "BLUR_PER_PX_AT_F1", 120 / 320)
        scene = two_plane_scene
        out = logic.load(str(scene.photo), str(scene.disparity), "disparity", None, 0.5, 1.0)
        session = out[0]
        assert isinstance(session, Session)
        assert session.size == session.shown_size == (320, 240)
        assert session.name == "scene"
        assert session.last_full.shape == (240, 320, 3)
        assert "f/1, blur 120 px" in out[-1]
        # focus 0.5 with K = 120 px: both planes are |d - f| = 0.5 away, both blurred
        assert sharpness(session.last_full) < 0.5 * sharpness(scene.image)

    def test_outputs_and_info(self, logic, two_plane_scene):
        out = logic.load(
            {"path": str(two_plane_scene.photo), "orig_name": "my photo.png"},
            {"path": str(two_plane_scene.disparity), "orig_name": "d.png"},
            "disparity (bright = near)",
            None,
            0.5,
            APERTURE,
        )
        session, focus, result, compare, legend, info = out
        assert session.name == "my_photo"
        assert is_skip(focus)  # no focal plane recorded in the file
        assert result["visible"] is True and pixels(result).shape == (240, 320, 3)
        assert compare["visible"] is False and legend["visible"] is False
        assert "320x240 px" in info and "prepare" in info and "your disparity map" in info

    def test_no_depth_focuses_on_the_subject(self, logic, tiny_model, two_plane_scene):
        out = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        session, focus, *_, info = out
        expected, (x, y) = tiny_model.subject_focus(session.scene)
        # the slider reads near (0) to far (1): the subject's disparity d is at 1 - d
        assert not is_skip(focus) and focus == round(1.0 - expected, 3)
        assert session.full_params.focus == round(expected, 3)
        assert f"focus on the subject at ({x:.0f}, {y:.0f})" in info
        assert f"focus {focus:.3f}" in info  # the image was rendered at that focus
        # with a depth map but no focal plane from the camera, the slider keeps its value
        given = logic.load(
            str(two_plane_scene.photo), str(two_plane_scene.disparity), "disparity", None, 0.5,
            APERTURE,
        )  # fmt: skip
        assert is_skip(given[1])

    def test_same_pixels_hit_the_cache(self, logic, two_plane_scene):
        args = (str(two_plane_scene.disparity), "disparity", None, 0.5, APERTURE)
        first = logic.load(str(two_plane_scene.photo), *args)
        again = logic.load(str(two_plane_scene.photo), *args)
        assert "cached scene" in again[-1] and "cached scene" not in first[-1]
        assert again[0].scene is first[0].scene
        other = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        assert other[0].scene is not first[0].scene  # network map: a different key

    def test_depth_resize_notice(self, logic, two_plane_scene, tmp_path, capsys):
        small = tmp_path / "small_disp.png"
        Image.open(two_plane_scene.disparity).resize((160, 120), Image.Resampling.NEAREST).save(
            small
        )
        logic.load(str(two_plane_scene.photo), str(small), "disparity", None, 0.5, APERTURE)
        assert "160x120" in capsys.readouterr().out  # gr.Info outside a request prints

    def test_depth_kind(self, logic, two_plane_scene):
        out = logic.load(
            str(two_plane_scene.photo), str(two_plane_scene.disparity), "depth (bright = far)",
            None, 0.5, APERTURE,
        )  # fmt: skip
        x, y = two_plane_scene.near_point
        # read as depth, the bright box is now the far plane
        assert out[0].scene.disparity_full()[y, x] < 0.1

    @pytest.mark.parametrize(
        ("content", "message"),
        [
            (b"", "empty"),
            (b"GIF89a-not-really", "not an image|corrupt"),
            (b"%PDF-1.4 hello", "not an image"),
        ],
    )
    def test_bad_upload_is_gr_error_and_keeps_session(self, loaded, tmp_path, content, message):
        logic, session, _ = loaded
        bad = tmp_path / "bad.jpg"
        bad.write_bytes(content)
        with pytest.raises(gr.Error, match=message):
            logic.load(str(bad), None, "disparity", session, 0.5, APERTURE)
        # the previous photo still renders
        out = logic.render_full(session, 0.9, APERTURE)
        assert pixels(out[0]).shape == (240, 320, 3)

    def test_bad_depth_is_gr_error(self, logic, two_plane_scene, tmp_path):
        text = tmp_path / "depth.txt"
        text.write_text("not a map")
        with pytest.raises(gr.Error, match="depth.txt"):
            logic.load(
                str(two_plane_scene.photo), {"path": str(text), "orig_name": "depth.txt"},
                "disparity", None, 0.5, APERTURE,
            )  # fmt: skip

    def test_cleared_input(self, loaded):
        logic, session, _ = loaded
        folder = session.folder
        assert folder is not None and folder.exists()
        out = logic.load(None, None, "disparity", session, 0.5, APERTURE)
        assert out[0] is None and out[-1] == ""
        assert not folder.exists()

    def test_exif_rotated_upload_and_click(self, logic, tmp_path, scene_factory):
        scene = scene_factory(width=200, height=120)
        stored = np.rot90(scene.image, k=1)  # displayed after a 90 degree CW turn
        path = tmp_path / "rotated.jpg"
        write_exif_rotated(path, np.ascontiguousarray(stored), orientation=6)
        out = logic.load(str(path), str(scene.disparity), "disparity", None, 0.5, APERTURE)
        session = out[0]
        assert session.size == session.shown_size == (200, 120)
        focus = logic.click(session, list(scene.near_point), APERTURE)[0]
        assert focus == pytest.approx(0.0, abs=0.02)  # the slider's near end


class TestRender:
    def test_click_near_then_far(self, loaded, sharpness):
        logic, session, scene = loaded
        near = logic.click(session, list(scene.near_point), APERTURE)
        # the map is min-max normalised: the near box is disparity 1, the background 0; the
        # focus slider reads near (0) to far (1)
        assert near[0] == pytest.approx(0.0, abs=0.01)
        assert session.full_params.focus == pytest.approx(1.0, abs=0.01)
        img_near = session.last_full.copy()
        far = logic.click(session, list(scene.far_point), APERTURE)
        assert far[0] == pytest.approx(1.0, abs=0.01)
        assert session.full_params.focus == pytest.approx(0.0, abs=0.01)
        img_far = session.last_full
        x0, y0, x1, y1 = scene.box
        inner = (x0 + 12, y0 + 12, x1 - 12, y1 - 12)
        background = (x1 + 12, 12, 320 - 4, 240 - 4)
        assert sharpness(img_near, inner) > 2 * sharpness(img_far, inner)
        assert sharpness(img_far, background) > 2 * sharpness(img_near, background)
        # in focus is exactly the input (fusion keeps sub-pixel CoC sharp)
        np.testing.assert_allclose(
            img_near[inner[1] : inner[3], inner[0] : inner[2]].astype(int),
            scene.image[inner[1] : inner[3], inner[0] : inner[2]].astype(int),
            atol=2,
        )
        assert "focused on the click at" in far[-1]
        assert f"focus {far[0]:.3f} (0 = near, 1 = far; disparity " in far[-1]

    def test_click_coordinates_scale_to_a_downscaled_scene(self, loaded):
        logic, session, scene = loaded
        session.shown_size = (640, 480)  # as if the upload had been twice as large
        x, y = scene.near_point
        assert logic.click(session, [2 * x, 2 * y], APERTURE)[0] == pytest.approx(0.0, abs=0.01)
        # clicks past the edge clamp into the photo (the far background)
        assert logic.click(session, [10_000, 10_000], APERTURE)[0] == pytest.approx(1.0, abs=0.01)

    def test_click_without_photo_and_bad_index(self, logic, loaded):
        with pytest.warns(UserWarning, match="Upload a photo"):
            out = logic.click(None, [1, 2], APERTURE)
        assert all(is_skip(o) for o in out)
        _, session, _ = loaded
        with pytest.raises(gr.Error, match="Click position"):
            logic.click(session, "middle", APERTURE)

    def test_preview_is_small_and_skipped_after_full(self, loaded):
        logic, session, _ = loaded
        out = logic.render_preview(session, 0.3, APERTURE)
        assert max(pixels(out[0]).shape[:2]) <= PREVIEW_MAX_SIDE
        assert "preview" in out[3]
        logic.render_full(session, 0.3, APERTURE)
        assert all(is_skip(o) for o in logic.render_preview(session, 0.3, APERTURE))
        # the same params again at full resolution: nothing new to do
        assert all(is_skip(o) for o in logic.render_full(session, 0.3, APERTURE))
        assert not is_skip(logic.render_preview(session, 0.31, APERTURE)[0])

    def test_download_follows_what_is_shown(self, loaded):
        """A preview disables Download (it would save another picture); the full render of
        the value shown enables it with that value's file, also when a drag returns to the
        value of the last full render."""
        logic, session, _ = loaded
        first = logic.download(session, "JPEG")
        assert first["interactive"] is True and "_focus0.500_f0.5_K44.4.jpg" in first["value"]
        # asked again (each render event asks): the same file, not written again
        assert logic.download(session, "JPEG")["value"] == first["value"]
        out = logic.render_preview(session, 0.7, 2.0)
        assert out[4] == {"__type__": "update", "interactive": False}
        assert is_skip(logic.download(session, "JPEG"))  # nothing full to save yet
        # the slider comes back to the full render's value and is released there: the
        # preview on screen is replaced by the full render again, and Download saves it
        back = logic.render_full(session, 0.5, APERTURE)
        assert not is_skip(back[0]) and "full render" in back[3]
        again = logic.download(session, "JPEG")
        assert again["interactive"] is True and "_focus0.500_f0.5_K44.4.jpg" in again["value"]
        logic.render_preview(session, 0.7, 2.0)
        logic.render_full(session, 0.7, 2.0)
        saved = logic.download(session, "PNG")
        assert "_focus0.700_f2_K11.1.png" in saved["value"]
        np.testing.assert_array_equal(np.asarray(Image.open(saved["value"])), session.last_full)

    def test_info_names_the_adaptive_settings(self, loaded):
        logic, session, scene = loaded
        out = logic.render_full(session, 0.5, APERTURE, blur_on=False)
        assert "balanced quality: every blur under 1 px" in out[-1]
        np.testing.assert_array_equal(session.last_full, np.asarray(Image.open(scene.photo)))
        assert_shows(out[0], np.asarray(Image.open(scene.photo)))
        out = logic.render_full(session, 0.5, APERTURE)
        # the user's word for the setting, not the renderer's preset name
        assert "balanced quality: 15 blur layers" in out[-1] and "preset" not in out[-1]
        assert "layers" in logic.render_preview(session, 0.45, APERTURE)[3]

    def test_quality_option_sets_the_budget(self, loaded, monkeypatch):
        from d2f_core import lens

        logic, session, _ = loaded
        # a lens whose f/1 reaches the 300 px cap on the 320 px photo
        monkeypatch.setattr(lens, "BLUR_PER_PX_AT_F1", 1.0)
        info = {}
        for quality in ("high", "fast"):
            info[quality] = logic.render_full(session, 0.0, 1.0, quality=quality)[-1]
        assert "f/1, blur 300 px" in info["high"]
        # CoCs far over 64 px: only the 30 dB budget affords fewer than 15 layers
        assert "high quality: 15 blur layers" in info["high"]
        # the quality, then the command that reproduces the picture
        assert info["fast"].split(" | ")[-2].startswith("fast quality: ")
        assert "15 blur layers" not in info["fast"] and " blur layers" in info["fast"]
        with pytest.raises(gr.Error, match="quality"):
            logic.render_full(session, 0.5, APERTURE, quality="ultra")

    def test_preview_dropped_when_full_render_overtakes_it(self, loaded):
        logic, session, _ = loaded
        model = logic.model
        started, release = threading.Event(), threading.Event()

        class SlowPreview:
            """Delegates to the real model; holds preview renders until released."""

            def __getattr__(self, name):
                return getattr(model, name)

            def render(self, *args, **kwargs):
                if kwargs.get("max_side"):
                    started.set()
                    release.wait(10)
                return model.render(*args, **kwargs)

        logic.model = SlowPreview()
        box = {}
        t = threading.Thread(
            target=lambda: box.setdefault("out", logic.render_preview(session, 0.2, APERTURE))
        )
        t.start()
        assert started.wait(10)
        full = logic.render_full(session, 0.25, APERTURE)
        release.set()
        t.join(10)
        assert not is_skip(full[0])
        assert all(is_skip(o) for o in box["out"])
        assert "full" in full[-1] and session.full_params.position == 0.25

    def test_advanced_options_change_the_picture(self, loaded):
        logic, session, _ = loaded
        base = pixels(logic.render_full(session, 0.0, APERTURE)[0])
        for kwargs in (
            {"blades": 6, "rotation": 20},
            {"highlight_boost": False},
            {"fusion": False},
        ):
            out = logic.render_full(session, 0.0, APERTURE, **kwargs)
            assert pixels(out[0]).shape == base.shape
        no_blur = logic.render_full(session, 0.0, APERTURE, blur_on=False)[0]
        np.testing.assert_allclose(
            session.last_full.astype(int), session.before.astype(int), atol=1
        )
        assert_shows(no_blur, session.before)

    def test_views(self, loaded):
        logic, session, _ = loaded
        for view in VIEWS:
            result, compare, legend = logic.show_view(session, view)
            if view == "Before / after":
                assert result["visible"] is False and compare["visible"] is True
                before, after = (np.asarray(Image.open(p)) for p in compare["value"])
                assert before.shape == after.shape
            else:
                assert result["visible"] is True and compare["visible"] is False
                assert pixels(result).shape == (240, 320, 3)
                assert legend["visible"] is (view != "Bokeh")
        disp = pixels(logic.show_view(session, "Disparity")[0])
        x, y = session.size[0] - 5, 5  # far background: disparity 0 -> first viridis stop
        np.testing.assert_allclose(disp[y, x], imaging.COLORMAPS["viridis"][0], atol=4)
        # the defocus legend's top end in full-resolution pixels: 69 px at the render pass
        legend = logic.show_view(session, "Defocus")[2]["value"]
        scale = session.size[0] / session.scene.image_lr.shape[-1]
        assert f"1 = a blur of {round(69 * scale)} px or more across" in legend
        assert "render pass" not in legend
        # a preview's map is at its own pass: the legend follows it
        out = logic.render_preview(session, 0.2, APERTURE, view="Defocus")
        pass_w = logic.model.render(session.scene, 0.8, 10.0, max_side=PREVIEW_MAX_SIDE)
        scale = session.size[0] / pass_w.defocus.shape[1]
        assert f"1 = a blur of {round(69 * scale)} px or more across" in out[2]["value"]
        with pytest.raises(gr.Error, match="Unknown view"):
            logic.show_view(session, "X-ray")
        assert logic.show_view(None, "Bokeh")[0]["value"] is None

    def test_display_files_are_pruned_only_when_old(self, loaded):
        """Gradio copies an event's picture into its cache after the event returns, while
        other events of the session may write theirs: a young file is never removed."""
        import os

        from app.sessions import DISPLAY_FILES_KEPT, FILE_MIN_AGE_S

        logic, session, _ = loaded
        sent = [logic.render_preview(session, 0.1 + 0.01 * k, APERTURE)[0]["value"]
                for k in range(DISPLAY_FILES_KEPT + 4)]  # fmt: skip
        assert all(Path(p).exists() for p in sent)
        folder = session.folder / "display"
        old = time.time() - FILE_MIN_AGE_S - 5
        for f in folder.iterdir():
            os.utime(f, (old, old))
        newest = logic.render_preview(session, 0.9, APERTURE)[0]["value"]
        kept = sorted(folder.iterdir())
        assert len(kept) == DISPLAY_FILES_KEPT and Path(newest) == kept[-1]

    def test_display_file_survives_a_clock_rollover(self, loaded, monkeypatch):
        """Display files were named by time.monotonic_ns() and pruned by name: once the
        clock gained a digit (10**12 ns is 16.7 min after boot, 10**13 ns 2.8 h), every new
        file sorted before the older ones and was deleted as soon as written, so Gradio
        could not copy it and the browser got 403 for every picture of that session."""
        from app import sessions

        logic, session, _ = loaded
        ticks = [10**12 - 100 + k for k in range(10)] + [10**12 + k for k in range(10)]
        clock = iter(ticks)
        monkeypatch.setattr(sessions.time, "monotonic_ns", lambda: next(clock))
        for k in range(10):  # 12-digit times
            logic.render_preview(session, 0.1 + 0.01 * k, APERTURE)
        for k in range(3):  # the clock has rolled over to 13 digits
            path = logic.render_preview(session, 0.6 + 0.01 * k, APERTURE)[0]["value"]
            assert Path(path).exists()

    def test_render_without_session(self, logic):
        # the release (or an API call) says what is missing; the drag's previews stay silent
        with pytest.raises(gr.Error, match="Upload a photo first"):
            logic.render_full(None, 0.5, 10)
        assert all(is_skip(o) for o in logic.render_preview(None, 0.5, 10))
        assert len(logic.render_preview(None, 0.5, 10)) == 5

    def test_blur_note_under_the_slider(self, loaded):
        """The aperture slider's info line: K in px at full resolution for the f-number on
        this photo (50 mm full frame, nearest 1 m: 0.0694 px per px of the long side at
        f/1), a 4000x3000 photo's before an upload."""
        logic, session, _ = loaded
        assert "f/1.4: blur K = 15.9 px on this 320x240 photo" in logic.blur_note(session, 1.4)
        assert "K = 15.9 px" in logic.blur_note(session, "1.4")
        assert "K = 198.4 px on a 4000x3000 photo" in logic.blur_note(None, 1.4)
        assert "K = 17.4 px" in logic.blur_note(None, 16)
        assert "50 mm lens on full frame" in logic.blur_note(None, 16)
        assert "300 px (the most the app renders)" in logic.blur_note(None, 0.9)
        assert "Blur is off" in logic.blur_note(session, 1.4, False)
        assert "px" not in logic.blur_note(session, "x") + logic.blur_note(session, -2)

    def test_core_value_error_becomes_gr_error(self, loaded):
        logic, session, _ = loaded
        with pytest.raises(gr.Error, match="f-number"):
            logic.render_full(session, 0.5, 20_000)


def write_lensblur(path: Path, scene, main_size: tuple[int, int]) -> np.ndarray:
    """A Google Lens Blur JPEG at ``path``: the all-in-focus original is ``scene``'s photo,
    the main picture (``main_size``) its negative, so the two cannot be mistaken; the depth
    map puts the scene's box at 1 m and the rest at 4 m. Returns the main picture."""
    w, h = main_size
    original = scene.image
    main = 255 - np.asarray(Image.fromarray(original).resize(main_size, Image.Resampling.BILINEAR))
    sx, sy = w / original.shape[1], h / original.shape[0]
    x0, y0, x1, y1 = scene.box
    z = np.full((h, w), 4.0, np.float32)
    z[round(y0 * sy) : round(y1 * sy), round(x0 * sx) : round(x1 * sx)] = 1.0
    path.write_bytes(lensblur_jpeg(original, main, z, near=1.0, far=4.0))
    return main


def mean_gap(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


class TestLensBlurPanel:
    """A Lens Blur file's main picture is the phone's blurred rendering; the app renders from
    the all-in-focus original in it, and the photo panel shows that original."""

    def test_panel_shows_the_original_not_the_main_picture(self, logic, two_plane_scene, tmp_path):
        path = tmp_path / "lensblur.jpg"
        main = write_lensblur(path, two_plane_scene, (320, 240))
        out = logic.load(str(path), None, "disparity", None, 0.5, APERTURE)
        session = out[0]
        assert "depth embedded in the photo" in out[-1]
        panel = logic.photo_panel(session)
        assert not is_skip(panel) and Path(panel["value"]) == session.panel
        shown = pixels(panel)
        rendered_from = imaging.to_uint8(d2f_io.load_photo(path).image)  # the original
        assert shown.shape == main.shape == rendered_from.shape
        assert mean_gap(shown, rendered_from) < 8  # the original, up to the display JPEG
        assert mean_gap(shown, main) > 60  # not the file's main picture (its negative)
        assert session.shown_size == session.size == (320, 240)

    def test_click_maps_from_the_panel_picture(self, logic, scene_factory, tmp_path, monkeypatch):
        # the original is 640x480, the main picture 320x240 (the scene's size), and the
        # panel is drawn at most 160 px wide: a click on the panel lands on the scene
        scene = scene_factory(width=640, height=480)
        path = tmp_path / "lensblur.jpg"
        write_lensblur(path, scene, (320, 240))
        fit = imaging.fit_display
        monkeypatch.setattr(imaging, "fit_display", lambda im, max_side=160: fit(im, 160))
        session = logic.load(str(path), None, "disparity", None, 0.5, APERTURE)[0]
        assert session.size == (320, 240)
        assert session.shown_size == (160, 120) == Image.open(session.panel).size
        near = [v // 4 for v in scene.near_point]
        far = [v // 4 for v in scene.far_point]
        assert logic.click(session, near, APERTURE)[0] == pytest.approx(0.0, abs=0.02)
        assert logic.click(session, far, APERTURE)[0] == pytest.approx(1.0, abs=0.02)

    def test_panel_picture_sent_back_loads_the_upload(self, logic, two_plane_scene, tmp_path):
        path = tmp_path / "lensblur.jpg"
        write_lensblur(path, two_plane_scene, (320, 240))
        first = logic.load(
            {"path": str(path), "orig_name": "PXL 1.jpg"}, None, "disparity", None, 0.5, APERTURE
        )[0]
        # Gradio hands the panel's picture back from its cache, under the same file name
        cached = tmp_path / "gradio-cache" / first.panel.name
        cached.parent.mkdir()
        cached.write_bytes(first.panel.read_bytes())
        # a new depth source re-loads with the photo input holding the panel's picture
        out = logic.load({"path": str(cached)}, None, "disparity", first, 0.5, APERTURE, 0, 0.0,
                         True, True, "Bokeh", "balanced", "embedded", "")  # fmt: skip
        again = out[0]
        assert first.closed and again.name == "PXL_1" and again.upload_name == "PXL 1.jpg"
        assert "depth embedded in the photo" in out[-1]  # the file, not the display JPEG
        assert again.panel is not None and again.panel.name != first.panel.name
        assert again.scene is first.get_scene()  # same pixels and depth: the cached scene
        # once the session is closed the panel's picture stands for nothing: a clear refusal
        again.close()
        with pytest.raises(gr.Error, match="closed"):
            logic.load({"path": str(cached)}, None, "disparity", again, 0.5, APERTURE)

    def test_failed_upload_shows_the_original_again(self, logic, two_plane_scene, tmp_path):
        path = tmp_path / "lensblur.jpg"
        write_lensblur(path, two_plane_scene, (320, 240))
        session = logic.load(str(path), None, "disparity", None, 0.5, APERTURE)[0]
        bad = tmp_path / "bad.jpg"
        bad.write_bytes(b"")
        with pytest.raises(gr.Error):
            logic.load(str(bad), None, "disparity", session, 0.5, APERTURE)
        photo, _, _, _, info, _ = logic.after_failed_load(session, {"path": str(bad)})
        assert photo["value"] == str(session.panel)  # the original, not the blurred file
        assert "Still showing lensblur" in info
        # a bad depth map: the photo input still holds the panel's picture, left as it is
        photo = logic.after_failed_load(session, {"path": f"/cache/x/{session.panel.name}"})[0]
        assert is_skip(photo)

    def test_other_photos_keep_their_upload_in_the_panel(self, loaded, tmp_path):
        logic, session, scene = loaded
        assert is_skip(logic.photo_panel(session)) and session.panel is None
        # an Apple portrait renders from its main picture: nothing to replace either
        disp = np.full(scene.image.shape[:2], 40, np.uint8)
        mpo = tmp_path / "portrait.jpg"
        mpo.write_bytes(apple_mpo(scene.image, disp, float_min=0.2, float_max=2.0))
        apple = logic.load(str(mpo), None, "disparity", session, 0.5, APERTURE)[0]
        assert is_skip(logic.photo_panel(apple)) and apple.shown_size == (320, 240)
        assert is_skip(logic.photo_panel(None))


class TestSessions:
    """Sessions hold a key into the one scene cache, are capped, and free everything when
    they end."""

    def test_scene_dropped_from_the_cache_is_prepared_again(self, loaded):
        logic, session, scene = loaded
        logic.cache.clear()
        out = logic.render_full(session, 0.5, APERTURE, blur_on=False)  # the photo itself
        np.testing.assert_array_equal(session.last_full, scene.image)
        assert_shows(out[0], scene.image)
        assert len(logic.cache) == 1  # prepared again from the session's copy, and cached
        assert session.scene is logic.cache.get(logic.model, session.key)

    def test_session_holds_no_scene_and_no_full_frame(self, loaded):
        logic, session, _ = loaded
        held = {f.name: getattr(session, f.name) for f in dataclasses.fields(session)}
        assert not any(type(v).__name__ == "Scene" for v in held.values())
        big = sum(v.nbytes for v in [session.before, *session.views.values()])
        assert big <= 320 * 240 * (3 + 3 + 3)  # display pictures, maps in one byte a pixel
        assert (session.folder / "last_full.npy").exists()

    def test_cap_on_live_sessions(self, tiny_model, tmp_path, two_plane_scene):
        logic = RefocusApp(
            tiny_model, SceneCache(64 << 20), download_root=tmp_path / "dl", max_sessions=2
        )
        args = (str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        a = logic.load(*args)[0]
        b = logic.load(*args)[0]
        # the same user uploading again replaces their own session: nothing else is closed
        b2 = logic.load(str(two_plane_scene.photo), None, "disparity", b, 0.5, APERTURE)[0]
        assert b.closed and not b2.closed and not a.closed and logic.live_sessions == 2
        a.close()
        assert logic.live_sessions == 1
        assert logic.load(*args)[0] is not None
        # a third photo closes the least recently used one (tests/test_app_sessions_order.py)
        assert logic.load(*args)[0] is not None and b2.closed and logic.live_sessions == 2

    def test_idle_sessions_are_closed_with_their_files(self, tiny_model, tmp_path, two_plane_scene):
        logic = RefocusApp(
            tiny_model, SceneCache(64 << 20), download_root=tmp_path / "dl", session_idle_s=60
        )
        session = logic.load(str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)[0]
        folder = session.folder
        assert folder.exists() and logic.live_sessions == 1
        assert logic.expire_idle() == 0
        session.last_used -= 61
        assert logic.expire_idle() == 1
        assert logic.live_sessions == 0 and not folder.exists() and not session.views
        with pytest.raises(gr.Error, match="upload it again"):
            logic.render_full(session, 0.3, APERTURE)

    def test_closed_tab_ends_its_sessions(self, tiny_model, tmp_path, two_plane_scene):
        logic = RefocusApp(tiny_model, SceneCache(64 << 20), download_root=tmp_path / "dl")

        class Request:
            session_hash = "tab-1"

        args = (str(two_plane_scene.photo), None, "disparity", None, 0.5, APERTURE)
        mine = logic.load(*args, request=Request())[0]
        other = logic.load(*args)[0]
        assert logic.end_sessions("tab-1") == 1
        assert mine.closed and not other.closed and logic.live_sessions == 1


class TestDownload:
    @pytest.mark.parametrize("when", ["before the write", "while PIL writes"])
    def test_tab_closed_while_the_file_is_written(self, loaded, monkeypatch, caplog, when):
        """A tab closed while its download is written removes the session's folder under
        the writer: the event ends with the closed-photo message and one log line, not an
        "unexpected failure" with a traceback (CI's browser test met this once)."""
        logic, session, _ = loaded
        logic.click(session, [5, 5], APERTURE)
        if when == "before the write":  # the folder is gone: save_image refuses the path
            write = imaging.save_image

            def close_then_write(image, path, **kw):
                session.close()  # what the page's unload event does meanwhile
                return write(image, path, **kw)

            monkeypatch.setattr(imaging, "save_image", close_then_write)
        else:  # the temp file is open: the rename after it fails
            pil_save = Image.Image.save

            def close_then_save(img, fp, *a, **kw):
                session.close()
                return pil_save(img, fp, *a, **kw)

            monkeypatch.setattr(Image.Image, "save", close_then_save)
        with caplog.at_level("INFO", logger="app.handlers"):
            with pytest.raises(gr.Error, match="upload it again"):
                logic.download(session, "PNG")
        assert session.closed and session.folder is None
        assert "stopped: the session was closed" in caplog.text
        assert "unexpected failure" not in caplog.text and "Traceback" not in caplog.text
        assert not any(r.exc_info for r in caplog.records)

    def test_png_is_the_full_render(self, loaded):
        logic, session, _ = loaded
        logic.click(session, [5, 5], APERTURE)
        up = logic.download(session, "PNG")
        path = Path(up["value"])
        assert path.suffix == ".png" and path.name.startswith("scene_bokeh_f")
        assert "320x240" in up["label"] and up["interactive"] is True  # enabled with a file
        np.testing.assert_array_equal(np.asarray(Image.open(path)), session.last_full)

    def test_display_is_jpeg_and_download_full_resolution(self, logic, scene_factory):
        """The browser gets a JPEG at display size (not a PNG); Download keeps every pixel
        of the full-resolution render."""
        scene = scene_factory(2000, 1200, seed=3, stem="wide")
        out = logic.load(str(scene.photo), None, "disparity", None, 0.5, 2.8, blur_on=False)
        session = out[0]
        with Image.open(out[2]["value"]) as shown:
            assert shown.format == "JPEG" and shown.size == (1600, 960)
        assert Path(out[2]["value"]).suffix == ".jpg"
        compare = logic.show_view(session, "Before / after")[1]["value"]
        assert all(Image.open(p).format == "JPEG" for p in compare)
        up = logic.download(session, "PNG")
        assert "2000x1200" in up["label"]
        with Image.open(up["value"]) as saved:
            assert saved.format == "PNG" and saved.size == (2000, 1200)
            np.testing.assert_array_equal(np.asarray(saved), scene.image)  # zero blur

    def test_jpeg_replaces_png(self, loaded):
        logic, session, _ = loaded
        png = Path(logic.download(session, "PNG")["value"])
        jpg = Path(logic.download(session, "JPEG")["value"])
        assert jpg.suffix == ".jpg" and png.exists()  # young: Gradio may still copy it
        with Image.open(jpg) as im:
            assert im.format == "JPEG" and im.size == (320, 240)

    def test_bad_format_and_no_session(self, loaded):
        logic, session, _ = loaded
        with pytest.raises(gr.Error, match="PNG or JPEG"):
            logic.download(session, "GIF")
        none = logic.download(None, "PNG")
        assert none["value"] is None and none["interactive"] is False  # nothing to save

    def test_session_delete_removes_files(self, loaded):
        logic, session, _ = loaded
        path = Path(logic.download(session, "PNG")["value"])
        assert path.exists()
        delete_session(session)
        assert not path.exists()
        delete_session(None)  # no-op


# -------------------------------------------------------------------------- wiring


@pytest.fixture(scope="module")
def demo_config(tiny_model):
    from app.main import build_demo

    demo = build_demo(tiny_model, cache=SceneCache(1 << 20))
    return demo.get_config_file()


class TestBuildDemo:
    @pytest.fixture
    def config(self, demo_config):
        return demo_config

    def test_elements_present(self, config):
        ids = {c["props"].get("elem_id") for c in config["components"]}
        wanted = "input focus blur view result compare legend info download format depth"
        wanted += " blades rotation hdr fusion"
        assert set(wanted.split()) <= ids

    def test_slider_events(self, config):
        by_elem = {c["props"].get("elem_id"): c["id"] for c in config["components"]}
        for name in ("focus", "blur", "rotation"):
            sid = by_elem[name]
            renders = [d for d in config["dependencies"] if by_elem["result"] in d["outputs"]]
            events = {t[1] for d in renders for t in d["targets"] if t[0] == sid}
            # the user's moves only (a value set by an event is rendered by it), and never
            # .change next to .input
            assert events == {"input", "release"}, name
            for d in config["dependencies"]:
                events = {t[1] for t in d["targets"] if t[0] == sid}
                if events:
                    assert d["trigger_mode"] == "always_last"
                if "input" in events:  # the drag's previews: no overlay, no timer
                    assert d["show_progress"] == "hidden"
                if "release" in events:  # the full render: its running time on the result
                    assert d["show_progress"] == "minimal"
                    assert d["show_progress_on"] == [by_elem["result"], by_elem["compare"]]
        select = [
            d
            for d in config["dependencies"]
            if [by_elem["input"], "select"] in map(list, d["targets"])
        ]
        assert len(select) == 1 and by_elem["focus"] in select[0]["outputs"]
        # the click is followed by a full render of the page's values (a release in flight
        # with the old focus may have overtaken the click's render)
        sid = select[0]["id"]
        after = [d for d in config["dependencies"]
                 if d["trigger_after"] == sid and d["trigger_only_on_success"]]  # fmt: skip
        assert len(after) == 1
        assert {by_elem[k] for k in ("focus", "blur", "blur_on")} <= set(after[0]["inputs"])
        assert by_elem["result"] in after[0]["outputs"]
        photo_events = {t[1] for d in config["dependencies"] for t in d["targets"]
                        if t[0] == by_elem["input"]}  # fmt: skip
        # an upload fires .change twice in Gradio 6; the app listens to .upload instead
        assert photo_events == {"upload", "clear", "select"}

    def test_render_events_name_their_photo(self, config):
        """The load sets the page's photo id (and the thin lens it renders with) with its
        first picture; every event that renders sends it back, so that one sent for the
        photo before is dropped (tests/test_app_sessions_order.py)."""
        by_elem = {c["props"].get("elem_id"): c["id"] for c in config["components"]}
        loads = [d for d in config["dependencies"] if d["api_name"] == "load"]
        assert len(loads) == 1
        assert loads[0]["outputs"][-2:] == [by_elem["focal_range"], by_elem["photo_id"]]
        renders = [d for d in config["dependencies"]
                   if by_elem["result"] in d["outputs"] and d["api_name"] != "view"
                   and d["trigger_after"] is None and d["api_name"] != "load"]  # fmt: skip
        assert len(renders) >= 10  # 4 previews, 4 releases, the options, the click
        for d in renders:
            assert d["inputs"][-1] == by_elem["photo_id"], d["api_name"]

    def test_one_download_after_each_release(self, config):
        """A release or an option runs the download once: after the step that brings the
        page in line (it ran right after the render as well, and again after that step,
        handing out the same file)."""
        by_elem = {c["props"].get("elem_id"): c["id"] for c in config["components"]}
        deps = config["dependencies"]

        def chain(dep_id: int) -> list[dict]:
            after = [d for d in deps if d["trigger_after"] == dep_id]
            return [x for d in after for x in [d, *chain(d["id"])]]

        releases = [d for d in deps if any(t[1] == "release" for t in d["targets"])]
        options = [d for d in deps if d["api_name"] == "render"]
        assert len(releases) == 5 and len(options) == 1  # focus, aperture, rotation, range, Boost
        for d in releases + options:
            downloads = [x for x in chain(d["id"]) if x["outputs"] == [by_elem["download"]]]
            assert len(downloads) == 1, d["api_name"]

    def test_slow_events_show_progress(self, config):
        """An upload (decode, prepare, render: seconds at 12 MP) and a click (focus and a
        full render) show a spinner over the result; nothing else covers it."""
        by_elem = {c["props"].get("elem_id"): c["id"] for c in config["components"]}
        shown_on = [by_elem["result"], by_elem["compare"]]
        full = {
            (t[0], t[1]) for d in config["dependencies"] if d["show_progress"] == "full"
            for t in d["targets"]
        }  # fmt: skip
        assert (by_elem["input"], "upload") in full and (by_elem["input"], "select") in full
        controls = "focus blur rotation blades hdr fusion quality blur_on view format".split()
        assert not {by_elem[c] for c in controls} & {t[0] for t in full}
        for d in config["dependencies"]:
            if d["show_progress"] != "hidden":
                assert d["show_progress_on"] == shown_on

    def test_controls_speak_a_photographers_language(self, config):
        props = {c["props"].get("elem_id"): c["props"] for c in config["components"]}
        label = props["focus"]["label"]
        assert label.index("near") < label.index("far")  # left to right, as the slider reads
        assert (props["focus"]["minimum"], props["focus"]["maximum"]) == (0, 1)
        blur = props["blur"]
        assert "f-number" in blur["label"] and "50 mm" in blur["info"]
        assert (blur["minimum"], blur["maximum"], blur["value"]) == (1, 22, DEFAULT_F_NUMBER)
        assert props["blades"]["label"] == "Aperture shape (blades)"
        assert props["blur_on"]["value"] is True
        assert "f/1.4: blur K = 198.4 px on a 4000x3000 photo" in blur["info"]
        by_elem = {k: c["id"] for c in config["components"] for k in [c["props"].get("elem_id")]}
        # the blur switch renders again and updates the note under the slider
        on = [d for d in config["dependencies"]
              if [by_elem["blur_on"], "change"] in map(list, d["targets"])]  # fmt: skip
        assert {d["api_name"] for d in on} == {"render", "blur_note_ui_2"}
        # the note sets the slider's info line only: no value, so no .change or .release
        assert all(d["outputs"] == [by_elem["blur"]] for d in on if d["api_name"] != "render")

    def test_examples_from_assets(self):
        from app.panels import sample_paths

        names = {Path(p).name for p in sample_paths()}
        assert {"astronaut.jpg", "coffee.jpg", "chelsea.jpg", "rocket.jpg"} <= names
        for p in sample_paths():
            assert Path(p).stat().st_size < 300_000


def test_main_reports_missing_weights(tmp_path, capsys):
    from app.main import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--weights", str(tmp_path / "nope.pt"), "--port", "0"])
    assert exit_info.value.code == 2
    assert "nope.pt" in capsys.readouterr().err


def test_app_extra_reads_heic():
    """``pip install -e ".[app]"`` must read the iPhone HEIC photos the app accepts (their
    depth too): the HEIF plugin is part of the app extra, not only of the dev one."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    meta = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    app_extra = meta["project"]["optional-dependencies"]["app"]
    assert any(req.startswith("pillow-heif") for req in app_extra)
    assert any(req.startswith("gradio") for req in app_extra)


def test_disparity_legend_names_the_maps_source():
    """The disparity view's legend says where its map came from: the phone's depth, the
    user's map, the scene teachers, the network or a hub model."""
    from types import SimpleNamespace

    from app.render_events import RenderEvents

    def title(key: str) -> str:
        return RenderEvents._legend(SimpleNamespace(key=key), "Disparity")[3]

    assert title("abc|embedded") == "Disparity (the photo's own phone depth)"
    assert title("abc|file") == "Disparity (your depth map)"
    assert title("abc|scene") == "Disparity (scene teachers and network)"
    assert title("abc|d2f") == "Disparity (network map)"
    assert title("abc|transformers:org/m") == "Disparity (Hugging Face model org/m)"
