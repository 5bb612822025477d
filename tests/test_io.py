"""Image I/O: every format and mode the loader promises, EXIF orientation, size caps, damaged
files, and saving with ICC/EXIF."""

from __future__ import annotations

import builtins
import io
import logging
from pathlib import Path

import numpy as np
import pytest
from _io_writers import png16_bytes, png_bomb_header
from PIL import Image, ImageCms, ImageOps

from d2f_core.io import image as io_image
from d2f_core.io import load_image, load_image_with_info, save_image
from d2f_core.io import save as io_save

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _rgb(h: int = 24, w: int = 32, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def _encode(img: Image.Image, fmt: str, **params) -> bytes:
    buf = io.BytesIO()
    img.save(buf, fmt, **params)
    return buf.getvalue()


def _asym(h: int = 6, w: int = 10) -> np.ndarray:
    """An image where every pixel differs, so any flip/rotation is visible."""
    a = np.arange(h * w * 3, dtype=np.int64).reshape(h, w, 3) % 251
    return a.astype(np.uint8)


class TestFormats:
    @pytest.mark.parametrize(
        "fmt,params,tol",
        [
            ("PNG", {}, 0.0),
            ("TIFF", {}, 0.0),
            ("WEBP", {"lossless": True}, 0.0),
            ("BMP", {}, 0.0),
            ("JPEG", {"quality": 100, "subsampling": 0}, 6 / 255),
        ],
    )
    def test_rgb_roundtrip(self, fmt, params, tol):
        src = _rgb()
        out = load_image(_encode(Image.fromarray(src), fmt, **params))
        assert out.shape == (24, 32, 3) and out.dtype == np.float32
        assert out.min() >= 0.0 and out.max() <= 1.0
        err = np.abs(out - src / 255.0)
        # JPEG at q100 4:4:4: measured mean error 0.0026, max < 6 levels on random noise.
        assert err.mean() <= max(tol / 2, 1e-7)

    def test_path_and_bytes_agree(self, tmp_path):
        p = tmp_path / "a.png"
        Image.fromarray(_rgb()).save(p)
        np.testing.assert_array_equal(load_image(p), load_image(p.read_bytes()))
        np.testing.assert_array_equal(load_image(str(p)), load_image(p))

    def test_png16_grey_full_precision(self):
        g = (np.arange(20 * 30).reshape(20, 30) * 97 % 65536).astype(np.uint16)
        out, info = load_image_with_info(_encode(Image.fromarray(g), "PNG"))
        np.testing.assert_allclose(out[..., 0], g / 65535.0, atol=1e-6)
        assert info.bit_depth == 16 and info.mode.startswith("I;16")

    @pytest.mark.parametrize("channels", [2, 3, 4])
    def test_png16_colour_every_filter(self, channels):
        rng = np.random.default_rng(1)
        a = rng.integers(0, 65536, (10, 7, channels), dtype=np.uint16)
        if channels in (2, 4):
            a[..., -1] = 65535  # opaque, so colours are comparable
        data = png16_bytes(a, filters=[0, 1, 2, 3, 4])
        out, info = load_image_with_info(data)
        assert info.bit_depth == 16
        ref = a[..., :3] if channels >= 3 else np.repeat(a[..., :1], 3, axis=2)
        # Pillow alone truncates to 8 bits (error up to 255/65535); we keep all 16.
        np.testing.assert_allclose(out, ref / 65535.0, atol=1e-6)

    def test_png16_alpha_over_white(self):
        a = np.zeros((4, 4, 4), np.uint16)
        a[..., 3] = 0  # fully transparent black -> white
        a[0, 0, 3] = 65535
        out = load_image(png16_bytes(a))
        assert out[1, 1].tolist() == [1.0, 1.0, 1.0]
        assert out[0, 0].tolist() == [0.0, 0.0, 0.0]


class TestModes:
    def test_grey(self):
        g = _rgb()[..., 0]
        out, info = load_image_with_info(_encode(Image.fromarray(g), "PNG"))
        np.testing.assert_allclose(out, np.repeat(g[..., None], 3, 2) / 255.0, atol=1e-7)
        assert "grayscale -> RGB" in info.conversions

    def test_one_bit(self):
        im = Image.fromarray(_rgb()[..., 0] > 127).convert("1")
        out = load_image(_encode(im, "PNG"))
        assert set(np.unique(out).tolist()) <= {0.0, 1.0}

    def test_palette_and_palette_transparency(self):
        im = Image.fromarray(_rgb()).convert("P", palette=Image.Palette.ADAPTIVE, colors=16)
        ref = np.asarray(im.convert("RGB")) / 255.0
        np.testing.assert_allclose(load_image(_encode(im, "PNG")), ref, atol=1e-7)
        p = Image.new("P", (4, 4), 0)
        p.putpalette([0, 0, 0, 255, 0, 0] + [0] * 762)
        p.putpixel((0, 0), 1)
        out, info = load_image_with_info(_encode(p, "PNG", transparency=0))
        assert out[0, 0].tolist() == [1.0, 0.0, 0.0]
        assert out[2, 2].tolist() == [1.0, 1.0, 1.0]  # transparent index -> white
        assert any("over white" in c for c in info.conversions)

    def test_rgba_composited_over_white(self, caplog):
        a = np.zeros((4, 4, 4), np.uint8)
        a[..., 3] = 128  # half-transparent black
        a[0, 0] = [255, 0, 0, 255]
        with caplog.at_level(logging.INFO, logger="d2f_core.io"):
            out = load_image(_encode(Image.fromarray(a), "PNG"))
        np.testing.assert_allclose(out[1, 1], 1.0 - 128 / 255.0, atol=1e-6)
        assert out[0, 0].tolist() == [1.0, 0.0, 0.0]
        assert "over white" in caplog.text

    def test_opaque_alpha_is_just_dropped(self):
        a = np.dstack([_rgb(), np.full((24, 32), 255, np.uint8)])
        out, info = load_image_with_info(_encode(Image.fromarray(a), "PNG"))
        np.testing.assert_allclose(out, _rgb() / 255.0, atol=1e-7)
        assert "dropped an all-opaque alpha channel" in info.conversions

    def test_la(self):
        la = Image.merge("LA", [Image.new("L", (3, 3), 0), Image.new("L", (3, 3), 0)])
        out = load_image(_encode(la, "PNG"))
        assert np.all(out == 1.0)  # fully transparent -> white

    @pytest.mark.parametrize("fmt", ["JPEG", "TIFF"])
    def test_cmyk(self, fmt):
        cmyk = Image.new("CMYK", (8, 8), (255, 0, 0, 0))  # pure cyan
        out, info = load_image_with_info(_encode(cmyk, fmt))
        assert out.shape == (8, 8, 3)
        r, g, b = out.reshape(-1, 3).mean(axis=0)
        assert r < 0.1 and g > 0.9 and b > 0.9
        assert any("CMYK" in c for c in info.conversions)

    def test_cmyk_with_icc_profile_converted_to_srgb(self):
        # lcms has no built-in CMYK profile; an sRGB profile must be refused gracefully
        # (wrong colour space) and fall back to the naive conversion.
        srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
        cmyk = Image.new("CMYK", (4, 4), (0, 255, 0, 0))
        out, info = load_image_with_info(_encode(cmyk, "JPEG", icc_profile=srgb))
        r, g, b = out.reshape(-1, 3).mean(axis=0)
        assert r > 0.9 and g < 0.1 and b > 0.9  # magenta
        assert info.icc_profile is None or info.icc_profile != srgb

    @pytest.mark.parametrize("fmt", ["PNG", "JPEG"])
    def test_a_grey_photos_gray_profile_is_not_kept_for_its_rgb_pixels(self, tmp_path, fmt):
        # a profile of the GRAY colour space (an sRGB one relabelled: lcms builds no grey
        # profile) describes one channel, not the RGB copy every loaded photo is
        srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
        gray = srgb[:16] + b"GRAY" + srgb[20:]
        grey = Image.fromarray(np.linspace(0, 255, 64, dtype=np.uint8).reshape(8, 8))
        out, info = load_image_with_info(_encode(grey, fmt, icc_profile=gray))
        assert out.shape == (8, 8, 3) and info.icc_profile is None
        assert "the GRAY ICC profile dropped (it does not describe RGB pixels)" in info.conversions
        written = save_image(tmp_path / f"o.{fmt.lower()}", out, icc_profile=info.icc_profile)
        with Image.open(written) as im:
            assert im.mode == "RGB" and "icc_profile" not in im.info
        # an RGB photo keeps its profile
        _, info = load_image_with_info(_encode(grey.convert("RGB"), fmt, icc_profile=srgb))
        assert info.icc_profile == srgb

    @pytest.mark.parametrize("compression", ["raw", "tiff_lzw"])
    @pytest.mark.parametrize("orientation", [2, 3, 5, 6, 7, 8])
    def test_a_tiffs_orientation_is_applied_once(self, tmp_path, orientation, compression):
        """Pillow turns a TIFF upright itself (it reports the upright size and transposes on
        load): the photo is as a viewer shows it, not turned a second time."""
        rgb = _rgb(20, 40)
        exif = Image.Exif()
        exif[0x0112] = orientation
        path = tmp_path / "o.tif"
        Image.fromarray(rgb).save(path, exif=exif.tobytes(), compression=compression)
        with Image.open(path) as im:
            viewer = np.asarray(ImageOps.exif_transpose(im).convert("RGB"), np.float32) / 255
        out, info = load_image_with_info(path)
        np.testing.assert_allclose(out, viewer, atol=1e-6)
        assert info.original_size == viewer.shape[:2]

    def test_int32_and_float_tiff(self, caplog):
        i32 = (np.arange(12, dtype=np.int32).reshape(3, 4) * 5000).astype(np.int32)
        out, info = load_image_with_info(_encode(Image.fromarray(i32), "TIFF"))
        np.testing.assert_allclose(out[..., 0], i32 / 65535.0, atol=1e-6)
        assert info.bit_depth == 32
        f = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
        f[0, 0] = np.nan
        out = load_image(_encode(Image.fromarray(f), "TIFF"))
        assert out[0, 0, 0] == 0.0
        np.testing.assert_allclose(out[..., 1].ravel()[1:], f.ravel()[1:], atol=1e-6)
        with caplog.at_level(logging.WARNING, logger="d2f_core.io.image"):
            _, info = load_image_with_info(_encode(Image.fromarray(f), "TIFF"))
        assert "1 NaN or infinite pixels set to 0" in info.conversions
        assert "1 of 12 pixels are NaN or infinite" in caplog.text
        with pytest.raises(ValueError, match="no finite value"):
            load_image(_encode(Image.fromarray(np.full((3, 4), np.nan, np.float32)), "TIFF"))
        big = f * 1000
        big[0, 0] = 0
        out = load_image(_encode(Image.fromarray(big), "TIFF"))
        assert out.max() == pytest.approx(1.0)

    def test_i16_tiff(self):
        g = np.array([[0, 1000], [40000, 65535]], np.uint16)
        out = load_image(_encode(Image.fromarray(g), "TIFF"))
        np.testing.assert_allclose(out[..., 2], g / 65535.0, atol=1e-6)


class TestOrientation:
    @pytest.mark.parametrize("orientation", range(1, 9))
    def test_matches_pillow_exif_transpose(self, orientation):
        im = Image.fromarray(_asym())
        exif = Image.Exif()
        exif[0x0112] = orientation
        data = _encode(im, "PNG", exif=exif.tobytes())
        expect = np.asarray(ImageOps.exif_transpose(Image.open(io.BytesIO(data))))
        out, info = load_image_with_info(data)
        np.testing.assert_array_equal(np.round(out * 255).astype(np.uint8), expect)
        assert info.orientation == orientation
        assert info.size == expect.shape[:2] == info.original_size
        # The returned EXIF must not ask viewers to rotate again.
        if info.exif:
            ex = Image.Exif()
            ex.load(info.exif)
            assert 0x0112 not in ex

    def test_jpeg_orientation_6(self):
        im = Image.fromarray(np.zeros((20, 40, 3), np.uint8))
        im.paste((255, 255, 255), (0, 0, 10, 5))  # white block at top-left
        exif = Image.Exif()
        exif[0x0112] = 6
        out = load_image(_encode(im, "JPEG", exif=exif.tobytes(), quality=95))
        assert out.shape == (40, 20, 3)
        # rotated 90 degrees clockwise: the block moves to the top-right corner
        assert out[:5, -3:].mean() > 0.8 and out[:5, :3].mean() < 0.2


class TestSizeLimits:
    def test_resize_keeps_aspect_and_logs(self, caplog):
        data = _encode(Image.fromarray(_rgb(300, 400)), "PNG")
        with caplog.at_level(logging.INFO, logger="d2f_core.io"):
            out, info = load_image_with_info(data, max_pixels=10_000)
        h, w = out.shape[:2]
        assert h * w <= 10_000 and abs(w / h - 4 / 3) < 0.02
        assert info.original_size == (300, 400) and info.resized
        assert "max_pixels" in caplog.text

    def test_jpeg_draft_path(self):
        grad = np.linspace(0, 255, 1600, dtype=np.float32)
        img = np.broadcast_to(grad[None, :, None], (1200, 1600, 3)).astype(np.uint8)
        out = load_image(_encode(Image.fromarray(img), "JPEG"), max_pixels=120_000)
        assert out.shape[0] * out.shape[1] <= 120_000
        assert out.shape[:2] == (300, 400)
        np.testing.assert_allclose(out[150, :, 0], np.linspace(0, 1, 400), atol=0.02)

    def test_resize_with_orientation(self):
        im = Image.fromarray(_rgb(200, 400))
        exif = Image.Exif()
        exif[0x0112] = 6
        data = _encode(im, "JPEG", exif=exif.tobytes())
        out, info = load_image_with_info(data, max_pixels=20_000)
        assert info.original_size == (400, 200)  # upright
        assert out.shape[0] > out.shape[1] and out.shape[0] * out.shape[1] <= 20_000

    def test_error_mode(self):
        data = _encode(Image.fromarray(_rgb(100, 100)), "PNG")
        with pytest.raises(ValueError, match="max_pixels=100"):
            load_image(data, max_pixels=100, on_too_large="error")
        assert load_image(data, max_pixels=10_000, on_too_large="error").shape == (100, 100, 3)

    @pytest.mark.parametrize(
        "kwargs,exc",
        [
            ({"max_pixels": 0}, ValueError),
            ({"max_pixels": 1.5}, TypeError),
            ({"on_too_large": "crop"}, ValueError),
        ],
    )
    def test_bad_arguments(self, kwargs, exc):
        with pytest.raises(exc):
            load_image(_encode(Image.fromarray(_rgb()), "PNG"), **kwargs)


class TestDamagedFiles:
    def _check(self, path: Path, match: str):
        with pytest.raises(ValueError, match=match) as err:
            load_image(path)
        assert str(path) in str(err.value)
        assert type(err.value) is ValueError

    def test_empty(self, tmp_path):
        p = tmp_path / "empty.jpg"
        p.write_bytes(b"")
        self._check(p, "empty")

    def test_text_file(self, tmp_path):
        p = tmp_path / "notes.jpg"
        p.write_text("hello, not an image\n")
        self._check(p, "not an image")

    def test_random_bytes(self, tmp_path):
        p = tmp_path / "noise.png"
        p.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
        self._check(p, "not an image")

    @pytest.mark.parametrize("fmt,ext", [("JPEG", "jpg"), ("PNG", "png"), ("WEBP", "webp")])
    def test_truncated(self, tmp_path, fmt, ext):
        data = _encode(Image.fromarray(_rgb(64, 64)), fmt)
        p = tmp_path / f"cut.{ext}"
        p.write_bytes(data[: len(data) // 2])
        self._check(p, "truncated|corrupt|not an image")

    def test_truncated_png16(self, tmp_path):
        noise = np.random.default_rng(0).integers(0, 65536, (8, 8, 3), dtype=np.uint16)
        data = png16_bytes(noise)
        p = tmp_path / "cut16.png"
        p.write_bytes(data[: len(data) - 200])
        self._check(p, "truncated|corrupt")

    def test_decompression_bomb(self, tmp_path):
        p = tmp_path / "bomb.png"
        p.write_bytes(png_bomb_header())
        self._check(p, "decompression bomb")

    def test_directory_and_missing(self, tmp_path):
        self._check(tmp_path, "directory")
        with pytest.raises(FileNotFoundError, match="nope.jpg"):
            load_image(tmp_path / "nope.jpg")
        with pytest.raises(TypeError):
            load_image(12345)  # type: ignore[arg-type]


class TestHeif:
    def test_roundtrip_when_encoder_available(self, tmp_path):
        pillow_heif = pytest.importorskip("pillow_heif")
        src = np.zeros((64, 96, 3), np.uint8)
        src[:, :48] = (200, 40, 40)
        src[:, 48:] = (40, 40, 200)
        try:
            heif = pillow_heif.from_bytes(mode="RGB", size=(96, 64), data=src.tobytes())
            buf = io.BytesIO()
            heif.save(buf, quality=95)
        except Exception as exc:  # encoder not compiled in
            pytest.skip(f"pillow-heif cannot encode here: {exc}")
        out, info = load_image_with_info(buf.getvalue())
        assert out.shape == (64, 96, 3) and info.format == "HEIF"
        assert abs(out[:, :40, 0].mean() - 200 / 255) < 0.05
        assert abs(out[:, 56:, 2].mean() - 200 / 255) < 0.05

    def test_missing_pillow_heif_gives_clear_error(self, monkeypatch):
        real_import = builtins.__import__

        def fake_import(name, *args, **kwargs):
            if name == "pillow_heif":
                raise ImportError("no pillow_heif")
            return real_import(name, *args, **kwargs)

        monkeypatch.setattr(io_image, "_heif_registered", False)
        monkeypatch.setattr(builtins, "__import__", fake_import)
        fake_heic = b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + b"\x00" * 64
        with pytest.raises(ValueError, match="pillow-heif"):
            load_image(fake_heic)

    @pytest.mark.shared_data
    def test_real_iphone_heic(self):
        path = SHARED / "apple_heic_depth_pillow_heif" / "pug.heic"
        if not path.exists():
            pytest.skip(f"shared data not available: {path}")
        out, info = load_image_with_info(path, max_pixels=1_000_000)
        assert info.original_size == (3024, 4032)
        assert out.shape[0] * out.shape[1] <= 1_000_000
        assert info.icc_profile is not None and info.exif is not None


class TestSave:
    @pytest.mark.parametrize("ext", [".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp"])
    def test_formats_by_extension(self, tmp_path, ext):
        src = np.linspace(0, 1, 16 * 24 * 3, dtype=np.float32).reshape(16, 24, 3)
        p = save_image(tmp_path / f"out{ext}", src, quality=100)
        back = load_image(p)
        tol = 1 / 255 if ext in (".png", ".tif", ".tiff") else 0.03
        assert np.abs(back - src).mean() <= tol
        assert [f.name for f in tmp_path.iterdir()] == [f"out{ext}"]  # no temp files left

    @pytest.mark.parametrize("quality", [90, 95, 100])
    def test_grainy_photo_as_jpeg(self, tmp_path, quality, capfd):
        # noise compresses to more than the 1-2 bytes a pixel Pillow gives libjpeg for
        # optimised Huffman tables (2.45 bytes at quality 95): written with the standard ones,
        # and libjpeg is never asked for the optimised ones, so it prints nothing
        noise = np.random.default_rng(0).integers(0, 256, (300, 400, 3), dtype=np.uint8)
        exif = Image.Exif()
        exif[0x010F] = "TestMake"
        p = save_image(tmp_path / "grain.jpg", noise, quality=quality, exif=exif.tobytes())
        assert p.stat().st_size > 1.5 * noise.shape[0] * noise.shape[1]
        back = np.asarray(Image.open(p).convert("RGB"), dtype=np.float32)
        assert np.abs(back - noise).mean() < {90: 8, 95: 5, 100: 1}[quality]
        with Image.open(p) as im:
            assert im.getexif().get(0x010F) == "TestMake"
        assert [f.name for f in tmp_path.iterdir()] == ["grain.jpg"]  # no temp files left
        assert capfd.readouterr().err == ""  # no "Suspension not allowed here"
        # a smooth picture keeps the optimised tables: smaller than the standard ones give
        smooth = np.linspace(0, 1, 300 * 400 * 3, dtype=np.float32).reshape(300, 400, 3)
        small = save_image(tmp_path / "smooth.jpg", smooth, quality=quality).stat().st_size
        plain = tmp_path / "plain.jpg"
        Image.fromarray((smooth * 255 + 0.5).astype(np.uint8)).save(
            plain, quality=quality, subsampling=0
        )
        assert small < plain.stat().st_size

    def test_icc_and_exif_kept_orientation_dropped(self, tmp_path):
        srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
        exif = Image.Exif()
        exif[0x0112] = 6
        exif[0x010F] = "TestMake"
        exif.get_ifd(0x8769)[0x9003] = "2020:01:02 03:04:05"
        src_bytes = _encode(
            Image.fromarray(_rgb(10, 20)), "JPEG", exif=exif.tobytes(), icc_profile=srgb
        )
        img, info = load_image_with_info(src_bytes)
        assert img.shape == (20, 10, 3)
        for ext in (".jpg", ".png", ".webp", ".tif"):
            out = save_image(
                tmp_path / f"o{ext}", img, icc_profile=info.icc_profile, exif=info.exif
            )
            with Image.open(out) as im:
                assert im.info.get("icc_profile") == srgb, ext
                ex = im.getexif()
                assert ex.get(0x010F) == "TestMake", ext
                assert ex.get(0x0112, 1) == 1, ext
                assert ex.get_ifd(0x8769).get(0x9003) == "2020:01:02 03:04:05", ext
            again = load_image(out)
            assert again.shape == (20, 10, 3)  # not rotated a second time

    def test_rounding_and_uint8(self, tmp_path):
        a = np.full((2, 2, 3), 0.5, np.float32)
        p = save_image(tmp_path / "h.png", a)
        assert np.asarray(Image.open(p))[0, 0, 0] == 128
        u = np.full((2, 2, 3), 7, np.uint8)
        assert np.asarray(Image.open(save_image(tmp_path / "u.png", u)))[0, 0, 0] == 7
        g = np.full((2, 3), 1.0, np.float32)
        assert Image.open(save_image(tmp_path / "g.png", g)).mode == "L"

    def test_bad_input(self, tmp_path):
        good = np.zeros((4, 4, 3), np.float32)
        with pytest.raises(ValueError, match="unknown extension"):
            save_image(tmp_path / "x.gifx", good)
        with pytest.raises(ValueError, match="NaN"):
            save_image(tmp_path / "x.png", np.full((4, 4, 3), np.nan, np.float32))
        with pytest.raises(ValueError, match="shape"):
            save_image(tmp_path / "x.png", np.zeros((4, 4, 5), np.float32))
        with pytest.raises(TypeError):
            save_image(tmp_path / "x.png", np.zeros((4, 4, 3), np.int64))
        with pytest.raises(ValueError, match="quality"):
            save_image(tmp_path / "x.jpg", good, quality=0)
        with pytest.raises(ValueError, match="does not exist"):
            save_image(tmp_path / "nodir" / "x.png", good)

    def test_refuses_to_overwrite_protected_input(self, tmp_path):
        src = tmp_path / "photo.png"
        save_image(src, np.zeros((4, 4, 3), np.float32))
        before = src.read_bytes()
        with pytest.raises(ValueError, match="overwrite"):
            save_image(src, np.ones((4, 4, 3), np.float32), protect=src)
        with pytest.raises(ValueError, match="overwrite"):
            save_image(tmp_path / "." / "photo.png", np.ones((4, 4, 3)), protect=[str(src)])
        assert src.read_bytes() == before

    def test_sides_over_the_encoders_limit(self, tmp_path):
        """WebP writes at most 16,383 px a side and JPEG 65,500: a longer picture is refused
        before the encoder runs, naming the limit, and a file already there is kept; PNG
        takes it."""
        long = np.zeros((1, 16384, 3), np.uint8)
        old = tmp_path / "x.webp"
        save_image(old, np.zeros((2, 2, 3), np.uint8))
        before = old.read_bytes()
        with pytest.raises(ValueError, match=r"WEBP holds at most 16383 px a side .* 16384x1"):
            save_image(old, long)
        assert old.read_bytes() == before
        with pytest.raises(ValueError, match="JPEG holds at most 65500 px"):
            save_image(tmp_path / "x.jpg", np.zeros((65501, 1), np.uint8))
        assert not (tmp_path / "x.jpg").exists()
        save_image(tmp_path / "x.png", long)
        assert load_image(tmp_path / "x.png").shape[:2] == (1, 16384)

    @pytest.mark.parametrize("quality", [float("nan"), 90.5, "95", True, 0, 101])
    def test_quality_is_a_whole_number_from_1_to_100(self, tmp_path, quality):
        with pytest.raises(ValueError, match="quality"):
            save_image(tmp_path / "x.jpg", np.zeros((4, 4, 3), np.uint8), quality=quality)
        assert not (tmp_path / "x.jpg").exists()


class TestFloatToUint8:
    """Floats to bytes by bands of rows: the same bytes as the whole-picture formula."""

    @staticmethod
    def reference(a: np.ndarray) -> np.ndarray:
        return (np.clip(a.astype(np.float32), 0, 1) * np.float32(255) + np.float32(0.5)).astype(
            np.uint8
        )

    @pytest.mark.parametrize("shape", [(1, 1), (7, 5, 3), (300, 17, 3), (2049, 512)])
    def test_same_bytes_as_whole_picture(self, shape, monkeypatch):
        monkeypatch.setattr(io_save, "_BAND_ELEMENTS", 4096)  # many bands, a short last one
        rng = np.random.default_rng(3)
        a = rng.uniform(-0.2, 1.2, shape)
        a.flat[:6] = [0.0, 1.0, 0.5 / 255, 254.5 / 255, -0.0, 1.0 + 1e-9][: a.size]
        for x in (a, a.astype(np.float32), a[::-1]):  # float64, float32, a strided view
            out = io_save.float_to_uint8(x)
            assert out.dtype == np.uint8 and out.shape == x.shape
            np.testing.assert_array_equal(out, self.reference(x))

    def test_known_values(self):
        got = io_save.float_to_uint8(np.array([[0.0, 0.5, 1.0, 2.0, -1.0, 0.499 / 255]]))
        np.testing.assert_array_equal(got, [[0, 128, 255, 255, 0, 0]])
        scalar = io_save.float_to_uint8(np.float32(0.5))
        assert scalar.shape == () and scalar == 128
        assert io_save.float_to_uint8(np.zeros((0, 4, 3))).shape == (0, 4, 3)

    def test_nan_in_a_later_band_is_named(self, monkeypatch):
        monkeypatch.setattr(io_save, "_BAND_ELEMENTS", 64)
        a = np.zeros((100, 8, 3), np.float32)
        a[97, 2, 1] = np.nan
        with pytest.raises(ValueError, match="bokeh: contains NaN"):
            io_save.float_to_uint8(a, "bokeh")
        with pytest.raises(ValueError, match="contains NaN"):
            io_save.to_uint8(a)
        out = io_save.float_to_uint8(np.where(np.isnan(a), 0, a), None)
        assert not out.any()

    def test_no_float_temporary_of_the_whole_picture(self):
        """Peak memory is the bytes out plus one band, not a float copy of the picture."""
        import tracemalloc

        a = np.full((2000, 1000, 3), 0.5, np.float32)  # 24 MB of floats, 6 MB of bytes
        tracemalloc.start()
        try:
            io_save.to_uint8(a)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < a.nbytes // 4 + 4 * io_save._BAND_ELEMENTS + (1 << 20), peak


def test_check_aspect_known_answers():
    """A depth map is resized onto its photo only when their shapes agree within 5 %."""
    from d2f_core.io.depth import check_aspect

    check_aspect((300, 400), (3000, 4000), "d")  # another resolution, the same shape
    check_aspect((300, 412), (300, 400), "d")  # 3 % wider: rounding of a resized map
    check_aspect((1, 1), (300, 400), "d")  # a single value fits any photo
    with pytest.raises(ValueError, match=r"^d: depth map is 424x300 but the image is 400x300: "
                       r"aspect ratios differ$"):  # fmt: skip
        check_aspect((300, 424), (300, 400), "d")  # 6 % wider
    with pytest.raises(ValueError, match=r"looks rotated by 90 degrees"):
        check_aspect((400, 300), (300, 400), "d")
    with pytest.raises(ValueError, match="a side is empty"):
        check_aspect((0, 5), (300, 400), "d")


@pytest.mark.parametrize("src", [None, 123, 1.5, ["a.png"], np.zeros((4, 4, 3), np.float32)])
def test_a_source_that_is_no_path_nor_bytes_is_named(src):
    """Every file loader refuses what is neither a path nor the file's bytes with the
    library's InputTypeError (a ValueError), naming what it got."""
    from d2f_core import load_depth, load_photo
    from d2f_core.errors import InputTypeError
    from d2f_core.io import load_mask

    for load in (load_image, load_photo, load_depth, load_mask):
        with pytest.raises(InputTypeError, match=f"got {type(src).__name__}"):
            load(src)


def test_load_depth_takes_the_photos_shape_as_its_size(tmp_path):
    from d2f_core import load_depth

    np.save(tmp_path / "d.npy", np.linspace(0, 1, 12).reshape(3, 4))
    image = np.zeros((30, 40, 3), np.float32)
    assert load_depth(tmp_path / "d.npy", size=image.shape).shape == (30, 40)


@pytest.mark.parametrize("size", [(240,), (0, 5), (1.5, 5), (True, 4), "ab", 7, (30, 40, 5)])
def test_load_depth_names_a_bad_photo_size(tmp_path, size):
    from d2f_core import load_depth

    np.save(tmp_path / "d.npy", np.linspace(0, 1, 12).reshape(3, 4))
    with pytest.raises(ValueError, match=r"size: expected the photo's \(H, W\)"):
        load_depth(tmp_path / "d.npy", size=size)


def test_a_failed_write_names_the_output_and_leaves_nothing(tmp_path):
    """An OSError while the file is written (a full disk gives no file name) names the output,
    not the hidden temporary file beside it, and the temporary file is gone."""
    import errno

    def full_disk(fh):
        fh.write(b"part")
        raise OSError(errno.ENOSPC, "No space left on device")

    out = tmp_path / "out.jpg"
    with pytest.raises(OSError, match="No space left on device") as caught:
        io_save.atomic_write(out, full_disk)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(out)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "x.png").write_bytes(b"a file")
    with pytest.raises(OSError) as caught:  # in a "folder" that is a file: mkstemp fails
        io_save.atomic_write(tmp_path / "x.png" / "y.png", lambda fh: None)
    assert caught.value.filename == str(tmp_path / "x.png" / "y.png")
