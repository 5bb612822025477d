"""The FastDepth teacher's torch port (d2f_core.teachers.fastdepth) against its original.

With ``../shared`` (and ``ai-edge-litert``), the int8 TFLite file run by its own runtime through
``Teachers`` and the port with the shipped weights must agree on three real photos (a room, a
street, a close-up) to the bar of the port: at least 99 % of pixels within one uint8 step and a
Spearman of at least 0.99; and the converter must write the shipped file's tensors. Without it,
the shipped weights must load, give a depth map of the contract's shape, and see a corridor
drawn in perspective the way its geometry says: far down the middle, near at the edges.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core.bundled import assets_dir
from d2f_core.teachers import fastdepth
from d2f_core.teachers.weights import save_teacher, teacher_path

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
TEACHERS = SHARED / "datasets" / "teachers"
#: a room (Kinect v2 frame), a street scene and a close-up (Middlebury Aloe)
PHOTOS = (
    "data/rgbd_kinect2_esanet/sample_rgb.png",
    "datasets/photos/sun_hays80/street_sun_bkgpqbvgorkjqzgp.jpg",
    "data/middlebury_aloe_opencv/aloeL.jpg",
)


@pytest.fixture(scope="module")
def net() -> fastdepth.FastDepth:
    return fastdepth.load_fastdepth()


def _corridor(side: int = 224, focal: float = 110.0, end: float = 12.0):
    """A corridor 2 m wide and high seen down its axis, floor, ceiling and walls tiled in
    0.5 m squares, its end wall ``end`` m away: ``(rgb float32 in [0, 1], depth in m)``."""
    y, x = np.mgrid[0:side, 0:side].astype(np.float64) + 0.5
    u, v = (x - side / 2) / focal, (y - side / 2) / focal
    with np.errstate(divide="ignore"):
        to_floor = 1.0 / np.abs(v)  # the depth where the ray meets the floor or ceiling
        to_wall = 1.0 / np.abs(u)
    depth = np.minimum(np.minimum(to_floor, to_wall), end)
    flat = (to_floor <= to_wall) & (depth < end)
    across = np.where(flat, u * depth, v * depth)
    checker = (np.floor(across / 0.5) + np.floor(depth / 0.5)) % 2
    shade = np.where(depth >= end, 0.6, np.where(flat, np.where(v > 0, 0.35, 0.8), 0.55))
    rgb = shade[..., None] * np.array([1.0, 0.95, 0.85]) * (0.75 + 0.25 * checker[..., None])
    return rgb.astype(np.float32), depth


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    return float(spearmanr(a.ravel(), b.ravel())[0])


# --- without ../shared ------------------------------------------------------------------------


def test_shipped_weights_load_strictly_and_hold_the_files_integers(net):
    raw = torch.load(teacher_path("fastdepth"), weights_only=True)
    assert raw["teacher"] == "fastdepth"
    assert set(raw["state_dict"]) == set(net.state_dict())
    for key, value in net.state_dict().items():
        want = torch.int8 if key.endswith("weight") else torch.int32
        assert value.dtype == want, key
        assert torch.equal(value, raw["state_dict"][key])
    # 20 convolutions and 18 depthwise ones, each with its bias, as the original graph has
    convs = [m for m in net.modules() if isinstance(m, fastdepth.QuantConv)]
    assert len(convs) == 38 and sum(m.groups > 1 for m in convs) == 18
    assert net.metres_per_step == pytest.approx(0.0717, abs=1e-4)  # the file's contract


def test_sample_photo_gives_a_depth_map_of_the_contract(net):
    photo = Image.open(assets_dir() / "samples" / "coffee.jpg")
    depth = fastdepth.depth_uint8(photo, net)
    assert depth.shape == (224, 224) and depth.dtype == np.uint8
    assert depth.max() > depth.min()
    metres = fastdepth.depth_metres(photo, net)
    assert metres.dtype == np.float32 and metres.shape == (224, 224)
    np.testing.assert_allclose(metres, depth * net.metres_per_step, rtol=1e-6)


def test_float_array_input_matches_the_pil_path(net):
    """The depth source passes images as float in [0, 1] (8-bit value / 255): rounding them
    back gives the very bytes PIL would resize."""
    photo = Image.open(assets_dir() / "samples" / "chelsea.jpg").convert("RGB")
    as_float = np.asarray(photo, dtype=np.float32) * np.float32(1 / 255)
    assert np.array_equal(fastdepth.fastdepth_input(as_float), fastdepth.fastdepth_input(photo))
    grey = photo.convert("L")  # converted to RGB first, as the labelling did
    as_rgb = np.asarray(grey.convert("RGB"))
    assert np.array_equal(fastdepth.depth_uint8(grey, net), fastdepth.depth_uint8(as_rgb, net))


def test_corridor_is_far_down_the_middle_and_near_at_the_edges(net):
    """What any depth model must get right about a corridor seen down its axis: the end is
    the farthest, the walls at the frame's edge the nearest, and the floor recedes from the
    bottom row towards the middle. The truth is the corridor's own geometry."""
    rgb, truth = _corridor()
    depth = fastdepth.depth_metres(rgb, net)
    centre = depth[96:128, 96:128].mean()
    edges = np.concatenate([depth[:16].ravel(), depth[-16:].ravel()])
    edges = np.concatenate([edges, depth[:, :16].ravel(), depth[:, -16:].ravel()])
    assert centre > 1.5 * edges.mean()
    floor = [depth[r : r + 16, 80:144].mean() for r in (208, 176, 144, 112)]
    assert all(b > a for a, b in zip(floor, floor[1:])), floor  # bottom row nearest
    assert _spearman(depth, truth) > 0.6


def test_bad_images_are_refused_with_a_value_error(net):
    for bad in (
        np.zeros((10, 10), np.float32),
        np.zeros((10, 10, 4), np.uint8),
        np.full((10, 10, 3), 1.5, np.float32),
        np.full((10, 10, 3), np.nan, np.float32),
        np.zeros((10, 10, 3), np.int16),
        [[0.0, 0.0, 0.0]],
    ):
        with pytest.raises(ValueError):
            fastdepth.depth_uint8(bad, net)


def test_load_refuses_another_teachers_file_and_a_damaged_one(tmp_path, net):
    other = save_teacher(tmp_path / "other.pt", "deeplab", {}, net.state_dict())
    with pytest.raises(ValueError, match="deeplab"):
        fastdepth.load_fastdepth(other)
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(teacher_path("fastdepth").read_bytes()[:50_000])
    with pytest.raises(ValueError):
        fastdepth.load_fastdepth(damaged)
    with pytest.raises(FileNotFoundError):
        fastdepth.load_fastdepth(tmp_path / "missing.pt")


# --- with ../shared: the original file and its runtime ----------------------------------------


def _need_original() -> None:
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    pytest.importorskip("onnxruntime", reason="onnxruntime is not installed (.[teach])")
    pytest.importorskip("scipy", reason="scipy is not installed (.[dev])")
    if not (TEACHERS / "fast_depth_224_int8.tflite").is_file():
        pytest.skip(f"the original teacher is not available: {TEACHERS}")


@pytest.mark.shared_data
def test_port_matches_the_original_on_real_photos(net):
    _need_original()
    from d2f_core.train.teachers import Teachers

    original = Teachers(TEACHERS, threads=1)
    for name in PHOTOS:
        path = SHARED / name
        if not path.is_file():
            pytest.skip(f"photo not available: {path}")
        with Image.open(path) as im:
            rgb = im.convert("RGB")
        want = original(rgb)[1]
        got = fastdepth.depth_uint8(rgb, net)
        assert got.shape == want.shape and got.dtype == want.dtype
        steps = np.abs(got.astype(np.int16) - want.astype(np.int16))
        assert np.mean(steps <= 1) >= 0.99, name
        assert _spearman(got, want) >= 0.99, name


@pytest.mark.shared_data
def test_converter_writes_the_shipped_file(tmp_path):
    _need_original()
    from d2f_core.train.port_fastdepth import convert

    (path,) = convert(TEACHERS, tmp_path)
    made = torch.load(path, weights_only=True)
    shipped = torch.load(teacher_path("fastdepth"), weights_only=True)
    assert made["config"] == shipped["config"]
    assert made["state_dict"].keys() == shipped["state_dict"].keys()
    for key, value in shipped["state_dict"].items():
        assert torch.equal(made["state_dict"][key], value), key
    fastdepth.load_fastdepth(path)  # loads strictly
