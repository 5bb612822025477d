"""The library keeps a photo's colour profile and EXIF, as the CLI does, and refuses a float
image on another scale instead of saving it almost white.

``save_image(path, result)`` (a render of a scene prepared from a loaded photo) and
``save_image(path, array, like=photo)`` write the photo's ICC profile and its EXIF with the
orientation reset (the pixels are upright); without them an iPhone's Display P3 photo would
be read as sRGB by every viewer.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from PIL import Image, ImageCms

from d2f_core import load_photo, save_image

#: EXIF tags: Make, Model, Orientation, DateTime.
MAKE, MODEL, ORIENTATION, DATETIME = 0x010F, 0x0110, 0x0112, 0x0132


@functools.cache
def _profile() -> bytes:
    """An RGB ICC profile that is not sRGB's, as a phone's P3 would be (made once: its header
    holds the time it was made)."""
    profile = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB"))
    data = bytearray(profile.tobytes())
    data[44:48] = b"d2fT"  # a device manufacturer of its own: another profile's bytes
    return bytes(data)


@pytest.fixture
def phone_photo(tmp_path):
    rng = np.random.default_rng(0)
    pixels = (rng.random((40, 64, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[MAKE], exif[MODEL], exif[DATETIME] = "d2f-test", "Phone 1", "2026:12:08 10:00:00"
    exif[ORIENTATION] = 6  # stored sideways: shown turned a quarter
    path = tmp_path / "phone.jpg"
    Image.fromarray(pixels).save(path, quality=95, icc_profile=_profile(), exif=exif)
    return path


def _meta(path):
    with Image.open(path) as im:
        return im.info.get("icc_profile"), im.getexif(), im.size


def test_a_result_keeps_its_photos_profile_and_exif(phone_photo, tmp_path, tiny_model):
    photo = load_photo(phone_photo)
    assert photo.info.icc_profile == _profile() and photo.image.shape[:2] == (64, 40)
    scene = tiny_model.prepare(photo)
    result = tiny_model.render(scene, 0.5, blur=6.0)
    for name in ("bokeh.jpg", "bokeh.png", "bokeh.webp", "bokeh.tif"):
        out = save_image(tmp_path / name, result)
        icc, exif, size = _meta(out)
        assert icc == _profile(), name
        assert exif.get(MAKE) == "d2f-test" and exif.get(DATETIME) == "2026:12:08 10:00:00", name
        assert exif.get(ORIENTATION, 1) == 1, name  # upright pixels, nothing to turn
        assert size == (40, 64), name
    # a painted scene keeps it too
    painted = tiny_model.paint(scene, sharp=np.ones((64, 40)))
    icc, _, _ = _meta(save_image(tmp_path / "p.jpg", tiny_model.render(painted, 0.5, blur=6.0)))
    assert icc == _profile()


def test_an_array_like_the_photo(phone_photo, tmp_path, tiny_model):
    photo = load_photo(phone_photo)
    out = save_image(tmp_path / "like.jpg", photo.image[::-1].copy(), like=photo)
    icc, exif, _ = _meta(out)
    assert icc == _profile() and exif.get(MODEL) == "Phone 1"
    # explicit arguments win over like=
    out = save_image(tmp_path / "mine.png", photo.image, like=photo, icc_profile=b"", exif=b"")
    icc, exif, _ = _meta(out)
    assert icc is None and exif.get(MAKE) is None
    # a bare array has nothing to keep, as before
    icc, exif, _ = _meta(save_image(tmp_path / "bare.jpg", photo.image))
    assert icc is None and exif.get(MAKE) is None
    with pytest.raises(TypeError, match="like: expected a Photo"):
        save_image(tmp_path / "x.png", photo.image, like="phone.jpg")


def test_a_result_of_a_bare_array_writes_no_profile(tmp_path, tiny_model):
    image = np.random.default_rng(1).random((32, 48, 3)).astype(np.float32)
    result = tiny_model.render(tiny_model.prepare(image), 0.5, blur=4.0)
    icc, exif, _ = _meta(save_image(tmp_path / "b.jpg", result))
    assert icc is None and exif.get(MAKE) is None


@pytest.mark.parametrize(("low", "high"), [(0.0, 255.0), (0.0, 1.01), (-0.02, 1.0)])
def test_floats_outside_0_1_are_refused(tmp_path, low, high):
    a = np.linspace(low, high, 48 * 32 * 3, dtype=np.float32).reshape(32, 48, 3)
    with pytest.raises(ValueError, match=r"array: float values must be in \[0, 1\]"):
        save_image(tmp_path / "x.png", a)
    assert not (tmp_path / "x.png").exists()


def test_rounding_past_0_1_is_taken(tmp_path):
    a = np.linspace(-0.0015, 1.0015, 48 * 32 * 3).reshape(32, 48, 3)
    out = np.asarray(Image.open(save_image(tmp_path / "x.png", a)))
    assert out.min() == 0 and out.max() == 255


def test_a_scenes_cache_is_bounded_and_not_pickled(tiny_model):
    """Renders at 20 screen and preview sizes keep the few most recent of each kind; the
    pickled scene carries no cache, renders the same after it, and clear_cache empties it."""
    import pickle

    from d2f_core.pipeline.outputs import SIZES_KEPT

    image = np.random.default_rng(2).random((120, 160, 3)).astype(np.float32)
    scene = tiny_model.prepare(image)
    fresh = len(pickle.dumps(scene))
    for side in range(40, 140, 5):  # 20 sizes
        tiny_model.render(scene, 0.5, blur=4.0, max_side=side)
        tiny_model.render(scene, 0.5, blur=4.0, screen=side)
    kinds: dict = {}
    for key in scene.cache:
        if isinstance(key, tuple):
            kinds[key[0]] = kinds.get(key[0], 0) + 1
    assert kinds and max(kinds.values()) <= SIZES_KEPT, kinds
    assert len(pickle.dumps(scene)) == fresh
    again = pickle.loads(pickle.dumps(scene))
    assert len(again.cache) == 0
    a = tiny_model.render(scene, 0.5, blur=4.0, screen=60).bokeh
    b = tiny_model.render(again, 0.5, blur=4.0, screen=60).bokeh
    np.testing.assert_array_equal(a, b)
    scene.clear_cache()
    assert len(scene.cache) == 0


def test_renders_options_are_keywords_and_the_model_is_callable(tiny_model):
    """``render(scene, 0.5, 30, 40)`` took 40 as ``fusion``; ``model(scene)`` raised torch's
    "missing the required forward function"."""
    image = np.random.default_rng(3).random((48, 64, 3)).astype(np.float32)
    scene = tiny_model.prepare(image)
    with pytest.raises(TypeError, match="positional argument"):
        tiny_model.render(scene, 0.5, 30.0, False)
    np.testing.assert_array_equal(
        tiny_model(scene, 0.5, 30.0, fusion=False).bokeh,
        tiny_model.render(scene, 0.5, 30.0, fusion=False).bokeh,
    )
    with pytest.raises(ValueError, match="renders a Scene from model.prepare"):
        tiny_model(image)
