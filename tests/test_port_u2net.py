"""The U^2-Net-p teacher's torch port (d2f_core.teachers.u2net) against its original.

With ``../shared`` (and ``ai-edge-litert`` and ``tflite``), the float16 TFLite file run by its
own runtime (``SceneTeachers``, as the labels were made) and the port with the shipped weights
must agree on three real photos (a street, a close-up, a room): the fused sigmoid map within
1e-3 everywhere, and the uint8 label within one level; and the converter must write the
shipped file's tensors. Without it, the shipped weights must load strictly, give a map of the
contract's shape and range, find the cup at the centre of ``coffee.jpg`` and a red disc drawn
on a grey ground wherever the disc is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core.bundled import assets_dir
from d2f_core.teachers import u2net
from d2f_core.teachers.weights import save_teacher, teacher_path

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
TEACHERS = SHARED / "datasets" / "teachers"
#: a street scene, a close-up (Middlebury Aloe) and a room (Kinect v2 frame)
PHOTOS = (
    "datasets/photos/sun_hays80/street_sun_bkgpqbvgorkjqzgp.jpg",
    "data/middlebury_aloe_opencv/aloeL.jpg",
    "data/rgbd_kinect2_esanet/sample_rgb.png",
)
#: the port's bar: the largest difference of the fused sigmoid map
BAR = 1e-3


@pytest.fixture(scope="module")
def net(one_thread) -> u2net.U2NetP:
    return u2net.load_u2netp()


def test_shipped_weights_load_strictly_and_are_float16_on_disk(net):
    raw = torch.load(teacher_path(u2net.NAME), weights_only=True)
    assert raw["teacher"] == "u2netp"
    own = net.state_dict()
    assert set(raw["state_dict"]) == set(own)
    # 119 convolutions (112 in the blocks, 6 side, 1 fuse), a weight and a bias each
    assert len(own) == 2 * 119
    # 3x3 convolutions of out x (9 in + 1): per RSU-L block of input c, 64 (9c + 1) in,
    # 16 x 577 + (L - 1) x 16 x 145 down, (L - 2) x 16 x 289 + 64 x 289 up; 6 x 577 side
    # and 7 fuse: 1,125,485 (the paper's 1.13 M)
    assert sum(v.numel() for v in own.values()) == 1_125_485
    for k, v in raw["state_dict"].items():
        assert v.dtype == torch.float16 and torch.equal(v.float(), own[k]), k


def test_sample_photo_gives_a_map_of_the_contract(net):
    m = u2net.silhouette(Image.open(assets_dir() / "samples" / "coffee.jpg"), net)
    assert m.shape == (320, 320) and m.dtype == np.float32
    assert np.isfinite(m).all() and 0.0 < m.min() and m.max() < 1.0
    # the cup fills the middle of the frame; the table around it is not the subject
    assert m[120:200, 120:200].mean() > 0.9
    border = np.concatenate(
        [m[:20].ravel(), m[-20:].ravel(), m[:, :20].ravel(), m[:, -20:].ravel()]
    )
    assert border.mean() < 0.2


@pytest.mark.parametrize("cx, cy", [(0.3, 0.6), (0.7, 0.35)])
def test_a_red_disc_on_grey_is_the_subject_where_it_is_drawn(net, cx, cy):
    """A 4:3 frame of noisy grey with a red disc off the centre: the map, stretched back to
    the frame, covers the disc (intersection over union above 0.9), which also catches a map
    mirrored or transposed."""
    h, w = 240, 320
    y, x = np.mgrid[0:h, 0:w] + 0.5
    disc = (x - cx * w) ** 2 + (y - cy * h) ** 2 < (0.18 * h) ** 2
    rng = np.random.default_rng(1)
    rgb = 0.5 + 0.05 * rng.standard_normal((h, w, 3))
    rgb[disc] = (0.85, 0.1, 0.1)
    m = u2net.silhouette(np.clip(rgb, 0, 1).astype(np.float32), net)
    fg = np.asarray(Image.fromarray(m).resize((w, h), Image.BILINEAR)) > 0.5
    assert (fg & disc).sum() / (fg | disc).sum() > 0.9


def test_float_and_uint8_arrays_match_the_pil_path(net):
    rgb = Image.open(assets_dir() / "samples" / "chelsea.jpg").convert("RGB")
    pixels = np.asarray(rgb)
    want = u2net.silhouette_input(rgb)
    assert want.shape == (320, 320, 3) and want.dtype == np.float32
    assert np.array_equal(u2net.silhouette_input(pixels), want)
    assert np.array_equal(u2net.silhouette_input(pixels.astype(np.float32) / 255), want)
    # the label: min-max normalised to 0..255 at the asked (width, height)
    label = u2net.silhouette_label(rgb, (90, 60), net)
    assert label.shape == (60, 90) and label.dtype == np.uint8


@pytest.mark.parametrize(
    "image, match",
    [
        (np.zeros((8, 8), np.float32), "H x W x 3"),
        (np.zeros((8, 8, 4), np.uint8), "H x W x 3"),
        (np.zeros((0, 8, 3), np.uint8), "H x W x 3"),
        (np.full((8, 8, 3), 1.5, np.float32), r"\[0, 1\]"),
        (np.full((8, 8, 3), np.nan, np.float32), r"\[0, 1\]"),
        (np.zeros((8, 8, 3), np.int16), "uint8 or float"),
        ("photo.jpg", "PIL image or a numpy array"),
    ],
)
def test_bad_images_are_refused_with_a_value_error(net, image, match):
    with pytest.raises(ValueError, match=match):
        u2net.silhouette(image, net)


@pytest.mark.parametrize("size", [(0, 10), (10,), (10.5, 10), (True, 10)])
def test_bad_label_sizes_are_refused_with_a_value_error(net, size):
    with pytest.raises(ValueError, match="width, height"):
        u2net.silhouette_label(np.zeros((8, 8, 3), np.uint8), size, net)


def test_load_refuses_another_teachers_file_and_a_damaged_one(tmp_path, net):
    other = save_teacher(tmp_path / "other.pt", "fastdepth", {}, net.state_dict())
    with pytest.raises(ValueError, match="'fastdepth' teacher, not 'u2netp'"):
        u2net.load_u2netp(other)
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(teacher_path(u2net.NAME).read_bytes()[:100_000])
    with pytest.raises(ValueError):
        u2net.load_u2netp(damaged)
    short = dict(net.state_dict())
    short.pop("fuse.bias")
    with pytest.raises(ValueError, match="1 missing"):
        u2net.load_u2netp(save_teacher(tmp_path / "short.pt", u2net.NAME, {}, short))


def _original() -> None:
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    pytest.importorskip("tflite", reason="tflite is not installed (.[teach])")
    if not (TEACHERS / "u2netp_float16.tflite").is_file():
        pytest.skip(f"the original teacher is not available: {TEACHERS}")


@pytest.mark.slow
@pytest.mark.shared_data
def test_port_matches_the_original_on_real_photos(net):
    _original()
    from d2f_core.train.scene_teachers import SAL_FILE, _Lite, label_size

    lite = _Lite(TEACHERS / SAL_FILE, threads=1)
    for name in PHOTOS:
        path = SHARED / name
        if not path.is_file():
            pytest.skip(f"photo not available: {path}")
        rgb = Image.open(path).convert("RGB")
        x = u2net.silhouette_input(rgb)
        want = lite.run(x[None])["Identity"][0, ..., 0]
        got = u2net.silhouette(rgb, net)
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= BAR, name
        # the label as SceneTeachers.silhouette makes it, from the original's map: within one
        # level (the min-max stretch and the rounding to 8 bits may tip a pixel over a step)
        lo, hi = float(want.min()), float(want.max())
        norm = (want - lo) / max(hi - lo, 1e-6)
        size = label_size(*rgb.size)
        label = Image.fromarray(np.round(norm * 255).astype(np.uint8)).resize(size, Image.BILINEAR)
        diff = np.abs(u2net.silhouette_label(rgb, size, net).astype(int) - np.asarray(label))
        assert diff.max() <= 1 and (diff > 0).mean() < 0.01, name


@pytest.mark.shared_data
def test_converter_writes_the_shipped_file(tmp_path):
    _original()
    from d2f_core.train.port_u2net import convert

    (path,) = convert(TEACHERS, tmp_path)
    assert path == tmp_path / "teacher_u2netp.pt"
    made = torch.load(path, weights_only=True)
    shipped = torch.load(teacher_path(u2net.NAME), weights_only=True)
    assert made["config"] == shipped["config"]
    assert set(made["state_dict"]) == set(shipped["state_dict"])
    for k, v in made["state_dict"].items():
        assert torch.equal(v, shipped["state_dict"][k]), k
    u2net.load_u2netp(path)  # and it loads
