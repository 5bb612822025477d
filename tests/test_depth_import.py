"""Depth import: files (PNG 8/16, npy, PFM, TIFF), hole filling, depth -> disparity, and the
phone depth embedded in Google Lens Blur JPEGs, Apple portrait MPOs and Apple HEICs."""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
import pytest
from _io_writers import apple_mpo, lensblur_jpeg
from PIL import Image, ImageOps

from d2f_core.io import (
    depth_to_disparity,
    extract_xmp,
    fill_holes,
    load_depth,
    load_image,
    load_photo,
    read_depth_array,
    read_embedded_depth,
    read_pfm,
    save_depth,
    write_pfm,
)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared(rel: str) -> Path:
    path = SHARED / rel
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


def _grad_energy(img: np.ndarray) -> float:
    g = img.mean(axis=2) if img.ndim == 3 else img
    return float(np.mean(np.diff(g, axis=0) ** 2) + np.mean(np.diff(g, axis=1) ** 2))


# --------------------------------------------------------------------------- PFM


class TestPfm:
    def test_roundtrip_grey_and_colour(self, tmp_path):
        rng = np.random.default_rng(0)
        grey = rng.normal(size=(7, 5)).astype(np.float32)
        grey[0, 0] = np.inf
        colour = rng.normal(size=(3, 4, 3)).astype(np.float32)
        for arr in (grey, colour):
            p = write_pfm(tmp_path / "x.pfm", arr)
            np.testing.assert_array_equal(read_pfm(p), arr)

    def test_reads_big_endian_bottom_up(self):
        # 2x2 big-endian file written by hand: rows are stored bottom first.
        body = np.array([[3, 4], [1, 2]], ">f4").tobytes()
        data = b"Pf\n2 2\n1.0\n" + body
        np.testing.assert_array_equal(read_pfm(data), [[1, 2], [3, 4]])

    @pytest.mark.parametrize(
        "data,match",
        [
            (b"P6\n2 2\n255\n" + b"\x00" * 12, "not a PFM"),
            (b"Pf\n2 2\n-1.0\n" + b"\x00" * 8, "truncated"),
            (b"Pf\n2 x\n-1.0\n" + b"\x00" * 16, "bad PFM header"),
            (b"Pf\n2", "truncated"),
        ],
    )
    def test_bad_files(self, data, match):
        with pytest.raises(ValueError, match=match):
            read_pfm(data)


# --------------------------------------------------------------------------- files


class TestLoadDepth:
    Z = np.array([[1.0, 2.0], [4.0, 4.0]])  # metres
    DISP = np.array([[1.0, 1 / 3], [0.0, 0.0]])  # (1/z - 1/4) / (1 - 1/4)

    def test_png16_metric_depth(self, tmp_path):
        p = tmp_path / "d.png"
        Image.fromarray((self.Z * 1000).astype(np.uint16)).save(p)  # millimetres
        assert Image.open(p).mode.startswith("I;16")
        out = load_depth(p, kind="depth", robust=False)
        np.testing.assert_allclose(out, self.DISP, atol=1e-6)
        assert out.dtype == np.float32

    def test_png8_disparity_bright_and_dark(self, tmp_path):
        ramp = np.tile(np.arange(1, 256, 2, dtype=np.uint8), (4, 1))
        p = tmp_path / "r.png"
        Image.fromarray(ramp).save(p)
        bright = load_depth(p, robust=False)
        dark = load_depth(p, near="dark", robust=False)
        np.testing.assert_allclose(bright[0], (ramp[0] - 1) / 254.0, atol=1e-6)
        np.testing.assert_allclose(dark, 1.0 - bright, atol=1e-6)

    def test_npy_float_tiff_pfm_agree(self, tmp_path):
        z = np.linspace(1.0, 5.0, 60, dtype=np.float32).reshape(6, 10)
        np.save(tmp_path / "z.npy", z)
        Image.fromarray(z).save(tmp_path / "z.tif")
        write_pfm(tmp_path / "z.pfm", z)
        ref = load_depth(tmp_path / "z.npy", kind="depth")
        for name in ("z.tif", "z.pfm"):
            np.testing.assert_allclose(load_depth(tmp_path / name, kind="depth"), ref, atol=1e-6)
        # disparity is 1/z: the middle of a linear depth ramp is not the middle of [0, 1]
        assert ref[0, 0] == 1.0 and ref[-1, -1] == 0.0
        expect = (1 / z - 1 / 5) / (1 - 1 / 5)
        np.testing.assert_allclose(ref, expect, atol=1e-5)

    @pytest.mark.parametrize("version", [(1, 0), (2, 0), (3, 0)])
    def test_npy_of_each_format_version(self, tmp_path, version):
        z = np.linspace(1.0, 5.0, 60, dtype=np.float32).reshape(6, 10)
        with open(tmp_path / "z.npy", "wb") as fh:
            np.lib.format.write_array(fh, z, version=version)
        np.testing.assert_array_equal(read_depth_array(tmp_path / "z.npy"), z)
        # the header is read before the values: a cut file is refused by what it lacks
        data = (tmp_path / "z.npy").read_bytes()
        (tmp_path / "cut.npy").write_bytes(data[:-8])
        with pytest.raises(ValueError, match="truncated .npy file"):
            read_depth_array(tmp_path / "cut.npy")

    def test_npy_unknown_version_or_broken_header(self, tmp_path):
        buf = io.BytesIO()
        np.save(buf, np.ones((4, 4)))
        data = bytearray(buf.getvalue())
        data[6] = 9  # format version 9.0
        (tmp_path / "v9.npy").write_bytes(bytes(data))
        with pytest.raises(ValueError, match="version 9.0 is not 1.0, 2.0 or 3.0"):
            read_depth_array(tmp_path / "v9.npy")
        (tmp_path / "bad.npy").write_bytes(
            b"\x93NUMPY\x03\x00" + b"\x10\x00\x00\x00" + b"{'a': 1}" + b" " * 8
        )
        with pytest.raises(ValueError, match="unreadable .npy header"):
            read_depth_array(tmp_path / "bad.npy")

    def test_npy_header_over_the_limit_is_refused_unread(self, tmp_path):
        # a 3.0 header holding a list of a million numbers: parsing it took seconds and GBs
        body = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), 'x': [%s]}" % (
            "1," * 1_000_000
        )
        header = body.encode() + b" " * (-(len(body) + 13) % 64) + b"\n"
        data = b"\x93NUMPY\x03\x00" + len(header).to_bytes(4, "little") + header + bytes(16)
        (tmp_path / "big.npy").write_bytes(data)
        with pytest.raises(ValueError, match=r"header is \d+ bytes, over the 10000 allowed"):
            read_depth_array(tmp_path / "big.npy")

    @pytest.mark.parametrize(
        ("shape", "sides"),
        [((1, 50), (1, 50)), ((1, 50, 1), (1, 50)), ((1, 1), (1, 1)), ((1, 6, 10), (6, 10)),
         ((1, 1, 6, 10), (6, 10)), ((6, 10, 1), (6, 10)), ((50, 1), (50, 1))],
    )  # fmt: skip
    def test_a_map_one_pixel_tall_or_wide_keeps_its_sides(self, tmp_path, shape, sides):
        values = np.linspace(1.0, 2.0, int(np.prod(shape))).reshape(shape)
        np.save(tmp_path / "d.npy", values)
        np.testing.assert_array_equal(read_depth_array(tmp_path / "d.npy"), values.reshape(sides))
        if sides[0] == 1 and sides[1] > 1:  # as a PNG of a photo one pixel tall, loaded for it
            row = (values.reshape(sides) * 100).astype(np.uint8)
            Image.fromarray(row).save(tmp_path / "d.png")
            out = load_depth(tmp_path / "d.png", size=sides, robust=False)
            assert out.shape == sides and out[0, -1] == 1.0 and out[0, 0] == 0.0
        with pytest.raises(ValueError, match=r"2-D depth map, got shape \(50,\)"):
            np.save(tmp_path / "v.npy", np.ones(50))
            read_depth_array(tmp_path / "v.npy")

    @pytest.mark.parametrize("orientation", [3, 6, 8])
    def test_a_rotated_map_is_read_upright_as_its_photo(self, tmp_path, orientation):
        """A PNG or JPEG map with an EXIF orientation is read as a viewer shows it, the way
        its photo is loaded: upright, its size checked upright."""
        upright = np.add.outer(np.arange(6) * 40, np.arange(10) * 4).astype(np.uint8)  # 6x10
        turn = {3: 2, 6: 1, 8: 3}[orientation]  # quarter turns anticlockwise it is stored in
        stored = Image.fromarray(np.rot90(upright, turn))
        exif = Image.Exif()
        exif[0x0112] = orientation
        for ext in ("png", "jpg"):
            path = tmp_path / f"d{orientation}.{ext}"
            stored.save(path, exif=exif, **({"quality": 100} if ext == "jpg" else {}))
            with Image.open(path) as im:
                viewer = np.asarray(ImageOps.exif_transpose(im), dtype=np.float64)
            read = read_depth_array(path, size=(60, 100))  # the photo upright, 100x60
            assert read.shape == (6, 10)
            np.testing.assert_array_equal(read, viewer)
            assert np.abs(read - upright).max() <= (0 if ext == "png" else 3)
            with pytest.raises(ValueError, match="rotated by 90 degrees"):
                read_depth_array(path, size=(100, 60))

    @pytest.mark.parametrize("orientation", [3, 6, 8])
    def test_a_rotated_tiff_map_is_read_upright(self, tmp_path, orientation):
        """The same for a TIFF's orientation tag, whether Pillow decodes the page (8-bit grey)
        or tifffile does (float RGB), its size checked from the header upright."""
        tifffile = pytest.importorskip("tifffile")
        upright = np.add.outer(np.arange(6) * 40, np.arange(10) * 4).astype(np.float32)
        stored = np.rot90(upright, {3: 2, 6: 1, 8: 3}[orientation]).copy()
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.fromarray(stored.astype(np.uint8)).save(tmp_path / "grey.tif", exif=exif.tobytes())
        tag = [(274, "H", 1, orientation, True)]
        rgb = np.dstack([stored] * 3)
        tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb", extratags=tag)
        for name in ("grey.tif", "rgb.tif"):
            np.testing.assert_array_equal(
                read_depth_array(tmp_path / name, size=(60, 100)), upright, err_msg=name
            )
            with pytest.raises(ValueError, match="rotated by 90 degrees"):
                read_depth_array(tmp_path / name, size=(100, 60))

    def test_multichannel_float_tiff(self, tmp_path):
        tifffile = pytest.importorskip("tifffile")
        z = np.linspace(1.0, 2.0, 24, dtype=np.float32).reshape(4, 6)
        tifffile.imwrite(tmp_path / "z3.tif", np.dstack([z, z, z]), photometric="rgb")
        np.testing.assert_allclose(read_depth_array(tmp_path / "z3.tif"), z, atol=1e-7)

    def test_resized_to_image_size(self, tmp_path):
        np.save(tmp_path / "d.npy", np.tile(np.linspace(0, 1, 8), (6, 1)))
        out = load_depth(tmp_path / "d.npy", size=(30, 40), robust=False)
        assert out.shape == (30, 40) and out.min() >= 0 and out.max() <= 1
        assert np.all(np.diff(out[15]) >= -1e-6)  # still increasing left to right

    def test_aspect_mismatch(self, tmp_path):
        np.save(tmp_path / "d.npy", np.ones((30, 40)))
        with pytest.raises(ValueError, match="aspect"):
            load_depth(tmp_path / "d.npy", size=(30, 30))
        with pytest.raises(ValueError, match="rotated"):
            load_depth(tmp_path / "d.npy", size=(400, 300))

    def test_nan_holes_filled_not_zero(self, tmp_path):
        rng = np.random.default_rng(3)
        z = np.full((40, 50), 2.0)
        z[:, 25:] = 4.0
        holes = rng.random(z.shape) < 0.2
        z[holes] = np.nan
        z[5, 5] = np.inf
        z[6, 6] = 0.0
        np.save(tmp_path / "z.npy", z)
        out = load_depth(tmp_path / "z.npy", kind="depth", robust=False)
        assert np.isfinite(out).all()
        # Without a guide, filled pixels within 2 px of the depth edge may blend (measured
        # max 0.167 there); further away they take their own side's value exactly.
        assert np.abs(out[:, :22] - 1.0).max() < 1e-6
        assert np.abs(out[:, 28:] - 0.0).max() < 1e-6
        guide = np.zeros((40, 50, 3))
        guide[:, 25:] = 1.0
        out = load_depth(tmp_path / "z.npy", kind="depth", robust=False, guide=guide)
        assert np.abs(out[:, :25] - 1.0).max() < 0.01
        assert np.abs(out[:, 25:] - 0.0).max() < 0.01

    @pytest.mark.parametrize("value", [0.0, np.nan, np.inf])
    def test_all_holes(self, tmp_path, value):
        np.save(tmp_path / "z.npy", np.full((4, 4), value))
        with pytest.raises(ValueError, match="no valid pixels"):
            load_depth(tmp_path / "z.npy", kind="depth")
        if value == 0.0:
            with pytest.raises(ValueError, match="no valid pixels"):
                load_depth(tmp_path / "z.npy", zero_is_hole=True)

    def test_negative_depth_is_named(self, tmp_path):
        """A metric depth map of negative numbers (a sign flipped on export) is refused for
        what it is, not as holes; a few negative pixels in a good map are holes."""
        np.save(tmp_path / "neg.npy", -np.linspace(1.0, 2.0, 16).reshape(4, 4))
        with pytest.raises(ValueError, match=r"no positive values \(from -2 to -1\)"):
            load_depth(tmp_path / "neg.npy", kind="depth")
        d = np.linspace(1.0, 2.0, 64).reshape(8, 8)
        d[0, 0] = -1.0
        np.save(tmp_path / "few.npy", d)
        out = load_depth(tmp_path / "few.npy", kind="depth", robust=False)
        assert np.isfinite(out).all() and out[-1, -1] == 0.0 and out[0, 1] > 0.95

    def test_zero_disparity_is_far_unless_marked_as_hole(self, tmp_path):
        d = np.zeros((8, 8))
        d[:, 4:] = 10.0
        d[0, 5] = 0.0
        np.save(tmp_path / "d.npy", d)
        kept = load_depth(tmp_path / "d.npy")
        assert kept[0, 5] == 0.0 and kept[:, :4].max() == 0.0  # zeros = farthest
        filled = load_depth(tmp_path / "d.npy", zero_is_hole=True, robust=False)
        assert filled[0, 5] == 0.5  # the hole takes its (constant) surroundings

    def test_constant_map_warns(self, caplog):
        with caplog.at_level(logging.WARNING, logger="d2f_core.io"):
            out = depth_to_disparity(np.full((3, 3), 7.0))
        assert np.all(out == 0.5) and "constant" in caplog.text

    @pytest.mark.parametrize(
        "kwargs,match",
        [
            ({"kind": "metres"}, "kind"),
            ({"near": "up"}, "near"),
            ({"kind": "depth", "near": "bright"}, "near"),
            ({"size": (0, 4)}, "size"),
        ],
    )
    def test_bad_arguments(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            depth_to_disparity(np.ones((4, 4)), **kwargs)

    def test_colour_map_rejected_and_bad_shape(self, tmp_path):
        rgb = np.zeros((4, 4, 3), np.uint8)
        rgb[..., 0] = 255
        Image.fromarray(rgb).save(tmp_path / "jet.png")
        with pytest.raises(ValueError, match="colour"):
            load_depth(tmp_path / "jet.png")
        np.save(tmp_path / "v.npy", np.ones((2, 3, 4, 5)))
        with pytest.raises(ValueError, match="2-D"):
            load_depth(tmp_path / "v.npy")
        # an H x W x 3 array gets the rule of an RGB PNG: a colour map is refused ...
        z = np.linspace(1.0, 2.0, 24).reshape(4, 6)
        np.save(tmp_path / "jet.npy", np.dstack([z, z[::-1], 0 * z]))
        with pytest.raises(ValueError, match="colour"):
            load_depth(tmp_path / "jet.npy")
        # ... and agreeing channels are one map
        np.save(tmp_path / "grey3.npy", np.dstack([z, z, z]))
        np.testing.assert_allclose(read_depth_array(tmp_path / "grey3.npy"), z)
        # a complex map is refused, not cut to its real part
        np.save(tmp_path / "c.npy", (z + 1j * z).astype(np.complex64))
        with pytest.raises(ValueError, match="complex"):
            load_depth(tmp_path / "c.npy")
        (tmp_path / "t.png").write_text("text")
        with pytest.raises(ValueError, match="t.png"):
            load_depth(tmp_path / "t.png")

    @pytest.mark.parametrize("ext", [".png", ".npy", ".pfm", ".tif"])
    def test_save_depth_roundtrip(self, tmp_path, ext):
        d = np.linspace(0.01, 1, 35, dtype=np.float32).reshape(5, 7)
        p = save_depth(tmp_path / f"d{ext}", d)
        back = load_depth(p, robust=False)
        np.testing.assert_allclose(back, (d - d.min()) / (d.max() - d.min()), atol=2e-5)


class TestHoleFilling:
    def test_guided_fill_respects_image_edges(self):
        """A hole band straddles a colour edge that is also a depth edge. With the image as
        guide the fill keeps each side's depth; without it the two sides blend.
        Measured: guided max error 0.0004 (left) / 0.0004 (right), unguided 0.47."""
        h, w = 40, 60
        guide = np.zeros((h, w, 3))
        guide[:, 30:] = 1.0
        disp = np.where(np.arange(w)[None, :] < 30, 1.0, 0.0) * np.ones((h, 1))
        valid = np.ones((h, w), bool)
        valid[:, 20:40] = False
        guided = fill_holes(disp, valid, guide)
        plain = fill_holes(disp, valid)
        err_guided = np.abs(guided - disp)[:, 20:40].max()
        err_plain = np.abs(plain - disp)[:, 20:40].max()
        assert err_guided < 0.02
        assert err_plain > 0.3

    def test_large_hole_and_single_valid_pixel(self):
        v = np.zeros((33, 17))
        m = np.zeros_like(v, bool)
        m[3, 4] = True
        v[3, 4] = 0.7
        out = fill_holes(v, m)
        np.testing.assert_allclose(out, 0.7)

    def test_valid_pixels_unchanged(self):
        rng = np.random.default_rng(0)
        v = rng.random((20, 30))
        m = rng.random((20, 30)) > 0.5
        out = fill_holes(v, m, rng.random((20, 30, 3)))
        np.testing.assert_array_equal(out[m], v[m])
        assert out.min() >= v[m].min() - 1e-9 and out.max() <= v[m].max() + 1e-9

    def test_errors(self):
        with pytest.raises(ValueError, match="no valid"):
            fill_holes(np.zeros((3, 3)), np.zeros((3, 3), bool))
        with pytest.raises(ValueError, match="shapes"):
            fill_holes(np.zeros((3, 3)), np.zeros((3, 4), bool))


# --------------------------------------------------------------------------- Lens Blur


def _scene(h=48, w=32):
    """Metric depth: a near square (1 m) in front of a far wall (4 m), plus a photo."""
    z = np.full((h, w), 4.0)
    z[10:30, 8:20] = 1.0
    photo = np.zeros((h, w, 3), np.uint8)
    photo[..., 1] = 120
    photo[10:30, 8:20] = (220, 30, 30)
    blurred = np.full((h, w, 3), 90, np.uint8)
    return z, photo, blurred


class TestLensBlur:
    @pytest.mark.parametrize("fmt", ["RangeInverse", "RangeLinear"])
    @pytest.mark.parametrize("bits", [8, 16])
    def test_depth_and_focus(self, fmt, bits):
        z, photo, blurred = _scene()
        data = lensblur_jpeg(
            photo, blurred, z, near=1.0, far=4.0, fmt=fmt, bits=bits, focal_distance=2.0,
            chunk_size=500, shuffle=True,
        )  # fmt: skip
        std, ext = extract_xmp(data)
        assert b"HasExtendedXMP" in std and b"GDepth:Data" in ext
        disp, info = read_embedded_depth(data)
        assert disp.shape == z.shape and info["source"] == "google_gdepth"
        assert disp[20, 12] == pytest.approx(1.0, abs=1e-3)  # near square
        assert disp[2, 2] == pytest.approx(0.0, abs=1e-3)  # far wall
        # focus at 2 m: 1/2 lies a third of the way from 1/4 to 1/1
        assert info["focus"] == pytest.approx(1 / 3, abs=0.01)
        assert info["near"] == 1.0 and info["far"] == 4.0 and info["format"] == fmt

    def test_focus_from_point_when_no_distance(self):
        z, photo, blurred = _scene()
        data = lensblur_jpeg(photo, blurred, z, near=1.0, far=4.0, focal_point=(0.45, 0.4))
        _, info = read_embedded_depth(data)
        assert info["focus"] == pytest.approx(1.0, abs=0.01)  # the point is on the square
        assert info["focus_point"] == (0.45, 0.4)

    def test_load_photo_uses_original_image(self):
        z, photo, blurred = _scene()
        data = lensblur_jpeg(photo, blurred, z, near=1.0, far=4.0, focal_distance=1.0)
        assert np.abs(load_image(data) - 90 / 255).max() < 0.02  # main image = rendering
        p = load_photo(data)
        assert np.abs(p.image - photo / 255.0).mean() < 0.01
        assert p.focus == pytest.approx(1.0, abs=1e-3)
        assert p.disparity.shape == p.image.shape[:2]
        assert "original_image" not in p.depth_info
        assert any("GImage" in c for c in p.info.conversions)

    def test_incomplete_extended_xmp(self, caplog):
        z, photo, blurred = _scene()
        data = lensblur_jpeg(photo, blurred, z, near=1.0, far=4.0, chunk_size=300, drop_chunk=True)
        with pytest.raises(ValueError, match="incomplete"):
            read_embedded_depth(data)
        with caplog.at_level(logging.WARNING, logger="d2f_core.io"):
            p = load_photo(data)  # the photo itself stays usable
        assert p.disparity is None and "incomplete" in caplog.text

    def test_max_pixels_applies_to_depth_and_original(self):
        z, photo, blurred = _scene(96, 64)
        data = lensblur_jpeg(photo, blurred, z, near=1.0, far=4.0)
        p = load_photo(data, max_pixels=1536)
        assert p.image.shape[:2] == p.disparity.shape == (48, 32)

    def test_plain_files_have_no_depth(self, tmp_path):
        buf = io.BytesIO()
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(buf, "JPEG")
        assert read_embedded_depth(buf.getvalue()) is None
        buf = io.BytesIO()
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(buf, "PNG")
        assert read_embedded_depth(buf.getvalue()) is None
        assert load_photo(buf.getvalue()).disparity is None


# --------------------------------------------------------------------------- Apple MPO


class TestAppleMpo:
    def test_disparity_and_focus_region(self):
        h, w = 64, 48
        disp8 = np.zeros((32, 24), np.uint8)
        disp8[:, :] = 40
        disp8[8:24, 6:18] = 240  # near subject
        photo = np.full((h, w, 3), 128, np.uint8)
        data = apple_mpo(
            photo, disp8, float_min=0.5, float_max=2.5, focus_region=(0.5, 0.5, 0.2, 0.2)
        )
        disp, info = read_embedded_depth(data)
        assert info["source"] == "apple_mpo" and info["kind"] == "disparity"
        assert disp.shape == (h, w)
        assert disp[32, 24] == pytest.approx(1.0, abs=0.03)
        assert disp[2, 2] == pytest.approx(0.0, abs=0.03)
        assert info["focus"] == pytest.approx(1.0, abs=0.03)
        assert info["focus_point"][0] == pytest.approx(0.5, abs=0.05)

    def test_depth_type_is_inverted(self):
        disp8 = np.tile(np.linspace(0, 255, 24).astype(np.uint8), (32, 1))
        data = apple_mpo(
            np.zeros((64, 48, 3), np.uint8), disp8, float_min=1.0, float_max=3.0, aux_type="depth"
        )
        disp, info = read_embedded_depth(data)
        assert info["kind"] == "depth" and info["focus"] is None
        assert disp[:, 0].mean() > 0.95 and disp[:, -1].mean() < 0.05  # small depth = near


# --------------------------------------------------------------------------- real files


@pytest.mark.shared_data
class TestRealFiles:
    def test_google_lens_blur_sample(self):
        path = shared("google_lensblur_depthy/lensblur_sample.jpg")
        disp, info = read_embedded_depth(path)
        assert disp.shape == (1024, 580)
        assert info["format"] == "RangeInverse"
        assert info["near"] == pytest.approx(9.6155, abs=1e-3)
        assert info["far"] == pytest.approx(44.636, abs=1e-3)
        # The focal distance (26.71) and the map at the focal point agree: measured focus
        # 0.1746, map median 0.1627 in a 41x41 window around (0.399, 0.496).
        fx, fy = info["focus_point"]
        y, x = int(fy * 1023), int(fx * 579)
        assert np.median(disp[y - 20 : y + 21, x - 20 : x + 21]) == pytest.approx(
            info["focus"], abs=0.03
        )
        photo = load_photo(path)
        rendered = load_image(path)
        # GImage is the all-in-focus original: measured gradient energy 24.4x the rendering's
        assert _grad_energy(photo.image) > 5.0 * _grad_energy(rendered)
        assert photo.focus == info["focus"]

    @pytest.mark.parametrize(
        "name,focus", [("image-with-depth.jpg", 0.82), ("image-with-matte.jpg", 0.748)]
    )
    def test_apple_portrait_jpeg(self, name, focus):
        path = shared(f"apple_portrait_jpeg_depth/{name}")
        p = load_photo(path, max_pixels=800_000)
        assert p.disparity.shape == p.image.shape[:2]
        assert p.depth_info["native_size"] == (768, 576)
        assert p.focus == pytest.approx(focus, abs=0.01)
        if "matte" in name:
            assert p.depth_info["matte"].shape == (2016, 1512)
            # the person (matte > 0.5) is nearer than the rest of the scene
            matte = np.asarray(
                Image.fromarray(p.depth_info["matte"]).resize(p.disparity.shape[::-1])
            )
            assert p.disparity[matte > 0.5].mean() > p.disparity[matte < 0.1].mean() + 0.2

    def test_apple_heic(self):
        pytest.importorskip("pillow_heif")
        path = shared("apple_heic_depth_pillow_heif/pug.heic")
        disp, info = read_embedded_depth(path, size=(300, 400))
        assert disp.shape == (300, 400)
        assert info["representation_type"] == 1 and info["kind"] == "disparity"
        assert info["d_min"] == pytest.approx(1.498, abs=1e-3)
        # the floor/bed at the bottom is nearer than the wall at the top
        assert disp[-30:].mean() > disp[:30].mean() + 0.4

    def test_middlebury_gt_holes(self):
        img = load_image(shared("middlebury_aloe_opencv/aloeL.jpg"))
        gt_path = shared("middlebury_aloe_opencv/aloeGT.png")
        raw = read_depth_array(gt_path)
        d = load_depth(gt_path, size=img.shape[:2], guide=img, zero_is_hole=True)
        assert d.shape == img.shape[:2] and np.isfinite(d).all()
        valid = raw > 0
        # GT is disparity in px: normalised map is an affine copy of it on valid pixels
        # (measured r = 0.998; the robust 0.5/99.5 % range clips the extremes)
        assert np.corrcoef(d[valid], raw[valid])[0, 1] > 0.995
        assert d[~valid].min() >= 0.0  # 3.5% holes filled, none left at zero by force

    def test_kinect_metric_depth(self):
        img = load_image(shared("rgbd_kinect2_esanet/sample_rgb.png"))
        path = shared("rgbd_kinect2_esanet/sample_depth.png")
        raw = read_depth_array(path)
        assert (raw == 0).mean() == pytest.approx(0.114, abs=0.005)
        d = load_depth(path, kind="depth", size=img.shape[:2], guide=img)
        valid = raw > 0
        # disparity = 1/depth, normalised on the robust range: 0.17% of the valid pixels are
        # bogus 1-7 cm readings, so compare against 1/depth clipped to that range.
        inv = 1.0 / raw[valid]
        lo, hi = np.percentile(inv, [0.5, 99.5])
        assert np.corrcoef(d[valid], np.clip(inv, lo, hi))[0, 1] > 0.9999
        # the filled holes lie inside the range of their surroundings, not at 0
        assert d[~valid].mean() > 0.05

    @pytest.mark.parametrize("scene", ["flowers", "hut", "shelf"])
    def test_depthy_split_maps_are_dark_near(self, scene):
        """Measured: the decoded GDepth greys keep Google's RangeInverse convention (near = 0,
        dark), although the data README calls them bright = near: the bottom (foreground)
        rows are darker than the top rows in every scene (e.g. flowers 159 vs 249)."""
        raw = read_depth_array(shared(f"google_lensblur_depthy/split/{scene}-depth.jpg"))
        h = raw.shape[0]
        assert raw[-h // 10 :].mean() < raw[: h // 10].mean() - 40
        d = load_depth(shared(f"google_lensblur_depthy/split/{scene}-depth.jpg"), near="dark")
        assert d[-h // 10 :].mean() > d[: h // 10].mean()


# --------------------------------------------------------------------------- truncation fuzz


def _png16_grey(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(array.astype(np.uint16)).save(buf, "PNG")
    return buf.getvalue()


def _fuzz_files() -> dict[str, tuple[str, bytes]]:
    """One small file of every format with depth the project reads: name -> (ext, bytes)."""
    z, photo, blurred = _scene()
    disp8 = np.tile(np.linspace(255, 0, 32).astype(np.uint8), (48, 1))
    files = {
        "gdepth": (
            "jpg",
            lensblur_jpeg(photo, blurred, z, near=1.0, far=4.0, chunk_size=600, focal_distance=1.0),
        ),  # fmt: skip
        "apple_mpo": ("jpg", apple_mpo(photo, disp8, float_min=0.5, float_max=2.5)),
        "png16": ("png", _png16_grey(np.tile(np.arange(0, 65536, 2048, dtype=np.uint16), (24, 1)))),
    }
    pfm = io.BytesIO()
    pfm.write(b"Pf\n32 24\n-1.0\n")
    pfm.write(np.linspace(1.0, 4.0, 32 * 24, dtype="<f4").tobytes())
    files["pfm"] = ("pfm", pfm.getvalue())
    try:
        import pillow_heif

        pillow_heif.register_heif_opener()
        buf = io.BytesIO()
        Image.fromarray(photo).save(buf, "HEIF", quality=90)
        files["heic"] = ("heic", buf.getvalue())
    except (ImportError, OSError, ValueError, KeyError):
        pass  # no HEIF encoder here: the other formats still run
    return files


def test_truncation_fuzz(tmp_path):
    """Every embedded-depth format cut at seeded offsets (every byte of an MPO's disparity
    frame among them): each cut file either loads or raises ValueError naming the file, and
    d2f's photo and depth readers never raise anything else."""
    rng = np.random.default_rng(21)
    files = _fuzz_files()
    assert {"gdepth", "apple_mpo", "png16", "pfm"} <= set(files)
    outcomes: dict[str, set[str]] = {}
    for name, (ext, data) in files.items():
        offsets = set(rng.integers(1, len(data), 40).tolist()) | {1, len(data) - 1}
        if name == "apple_mpo":
            second = data.index(b"\xff\xd8", 2)  # frame 1, the disparity image
            offsets |= set(range(second, min(len(data), second + 400), 3))
        for cut in sorted(offsets):
            path = tmp_path / f"{name}_{cut}.{ext}"
            path.write_bytes(data[:cut])
            readers = [load_depth] if ext == "pfm" else [load_photo]
            if ext == "png":
                readers.append(load_depth)
            for read in readers:
                try:
                    read(path)
                    outcomes.setdefault(name, set()).add("loaded")
                except ValueError as exc:
                    assert path.name in str(exc), (name, cut, str(exc))
                    outcomes.setdefault(name, set()).add("refused")
    # the fuzz reached both outcomes where a cut file can still be a photo (a cut MPO keeps
    # its first frame)
    assert outcomes["apple_mpo"] == {"loaded", "refused"}
    assert "refused" in outcomes["pfm"] and "refused" in outcomes["png16"]
