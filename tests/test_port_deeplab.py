"""The DeepLab teachers' torch port (d2f_core.teachers.deeplab) against the original files run
by their own runtimes, the converter (d2f_core.train.port_deeplab) against the shipped
weights, and what the port must get right without them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core.teachers import deeplab as D
from d2f_core.teachers.weights import load_teacher, teacher_path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
TEACHERS = SHARED / "datasets" / "teachers"
#: a scene, a close-up and a room
PHOTOS = (
    "data/google_lensblur_depthy/lensblur_sample.jpg",
    "data/middlebury_aloe_opencv/aloeL.jpg",
    "data/rgbd_kinect2_esanet/sample_rgb.png",
)
#: ADE20K's sky and VOC's cat (ade20k_labels_151.txt; the standard VOC order)
ADE_SKY, VOC_CAT = 3, 8


@pytest.fixture(scope="module", autouse=True)
def _one_thread(one_thread):
    yield


@pytest.fixture(scope="module")
def ade() -> D.DeepLab:
    return D.load_ade20k()


@pytest.fixture(scope="module")
def voc() -> D.DeepLab:
    return D.load_voc()


def _sample(name: str) -> Image.Image:
    with Image.open(REPO / "assets" / "samples" / name) as im:
        return im.convert("RGB")


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


# --------------------------------------------------------------- without ../shared


def test_shipped_weights_load_with_their_graphs_config(ade, voc):
    """Both files load strictly (load_teacher refuses a missing, extra or misshapen tensor)
    into the structure each graph has."""
    assert ade.decoder is not None and ade.resize == "align_corners"
    assert ade.logits.conv.out_channels == 151 and ade.backbone.out_channels == 320
    assert voc.decoder is None and voc.resize == "asymmetric"
    assert voc.logits.conv.out_channels == 21 and voc.backbone.out_channels == 160
    # the ADE20K graph's int8 1x1 convolutions: every 1x1 but the first block's projection
    quantized = {n for n, m in ade.named_modules() if isinstance(m, D.ConvAct) and m.quantize}
    ones = {
        n
        for n, m in ade.named_modules()
        if isinstance(m, D.ConvAct) and m.conv.kernel_size == (1, 1)
    }
    assert quantized == ones - {"backbone.blocks.0.project"}
    assert not any(m.quantize for m in voc.modules() if isinstance(m, D.ConvAct))


def test_output_stride_8_dilates_the_last_stages():
    """DeepLab's MobileNetV2 at output stride 8: the stride-16 stage's first block keeps
    stride 1 and dilation 1, the blocks after it dilate by 2, those past stride 32 by 4."""
    net = D.MobileNetV2(D.WIDTH_1, output_stride=8)
    strides = [b.depthwise.conv.stride[0] for b in net.blocks]
    dilations = [b.depthwise.conv.dilation[0] for b in net.blocks]
    assert strides == [1, 2, 1, 2, 1, 1] + [1] * 11
    assert dilations == [1] * 7 + [2] * 7 + [4] * 3
    x = torch.zeros(1, 3, 513, 513)
    with torch.inference_mode():
        low, out = net(x)
    assert low.shape == (1, 144, 129, 129) and out.shape == (1, 320, 65, 65)


def test_dynamic_int8_rounds_each_pixel_as_the_runtime():
    """Worked by hand from the runtime's rule: pixel [0, 255/128] has 128 steps per unit and
    zero point -128, its halves rounded to even; pixel [-1, 1] has 127.5 steps and zero
    point round(-0.5) = 0, so -1 rounds to -128 steps and 1 saturates at 127; a pixel of
    zeros stays zero."""
    x = torch.tensor(
        [
            [0.0, 12.5 / 128, 13.5 / 128, 0.5, 255 / 128],
            [-1.0, -0.5, 0.0, 0.5, 1.0],
            [0.0, 0.0, 0.0, 0.0, 0.0],
        ]
    ).T.reshape(1, 5, 3, 1)  # the channels on dim 1, one pixel per row of the table
    y = D.dynamic_int8(x).reshape(5, 3).T
    np.testing.assert_allclose(y[0], [0.0, 12 / 128, 14 / 128, 0.5, 255 / 128], atol=1e-7)
    np.testing.assert_allclose(
        y[1], [-128 / 127.5, -64 / 127.5, 0.0, 64 / 127.5, 127 / 127.5], atol=1e-7
    )
    assert not y[2].any()


def test_asymmetric_resize_samples_without_half_pixel_offset():
    """Output pixel i reads input i x in / out, the last ones clamped to the edge."""
    x = torch.tensor([[1.0, 3.0]]).reshape(1, 1, 1, 2)
    y = D._resize_asymmetric(x, (1, 4))
    np.testing.assert_allclose(y.reshape(-1), [1.0, 2.0, 3.0, 3.0])


def test_ade20k_finds_the_sky_over_the_rocket(ade):
    """The top of rocket.jpg is sky; the probabilities have the photo's aspect at 513."""
    rgb = _sample("rocket.jpg")  # 640 x 427
    p = D.ade20k_probabilities(rgb, ade)
    assert p.shape == (342, 513, 151) and p.dtype == np.float32
    assert p.min() >= 0 and np.allclose(p.sum(axis=-1), 1, atol=1e-4)
    assert (p[:85].argmax(axis=-1) == ADE_SKY).mean() > 0.85
    labels = D.ade20k_labels(rgb, (256, 171), ade)
    assert labels.shape == (171, 256) and labels.dtype == np.uint8
    assert (labels[:40] == ADE_SKY).mean() > 0.85


@pytest.mark.parametrize("side", [321, 513])
@pytest.mark.parametrize("name, size", [("rocket.jpg", (256, 171)), ("coffee.jpg", (97, 61))])
def test_ade20k_labels_are_the_argmax_of_the_resized_logits(ade, name, side, size):
    """The labels, computed only at the pixels PIL's nearest neighbour reads and only across
    a change of class, are the argmax of the logits resized to the input's size, resized by
    PIL: the same but on ties."""
    rgb = _sample(name)
    full = D.ade20k_logits(rgb, ade, side).argmax(dim=-1).to(torch.uint8).numpy()
    want = np.asarray(Image.fromarray(full).resize(size, Image.NEAREST))
    got = D.ade20k_labels(rgb, size, ade, side=side)
    assert got.shape == want.shape == size[::-1] and got.dtype == np.uint8
    assert (got == want).mean() >= 0.999
    assert len(np.unique(want)) >= 3  # a parse with changes of class to cross


def test_voc_finds_the_cat(voc):
    """chelsea.jpg is a cat filling the middle of the frame."""
    rgb = _sample("chelsea.jpg")
    p = D.voc_probabilities(rgb, voc)
    assert p.shape == (257, 257, 21) and np.allclose(p.sum(axis=-1), 1, atol=1e-4)
    cls = p.argmax(axis=-1)
    assert np.bincount(cls[cls > 0].ravel()).argmax() == VOC_CAT
    fg = D.voc_foreground(rgb, voc)
    assert fg.shape == (257, 257) and fg.dtype == np.uint8
    assert fg[96:160, 96:160].mean() > 200


def test_array_inputs_read_as_the_uint8_photo(voc):
    """A float photo in [0, 1] (as d2f_core.io loads it) gives the same as its uint8."""
    rgb = _sample("coffee.jpg")
    u8 = np.asarray(rgb)
    assert np.array_equal(D.voc_foreground(u8, voc), D.voc_foreground(rgb, voc))
    assert np.array_equal(
        D.voc_foreground(u8.astype(np.float32) / 255, voc), D.voc_foreground(rgb, voc)
    )


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (np.zeros((4, 4)), "H x W x 3"),
        (np.zeros((4, 4, 3), np.int32), "uint8 or float"),
        (np.full((4, 4, 3), 1.5, np.float32), r"in \[0, 1\]"),
        (np.full((4, 4, 3), np.nan, np.float32), "finite"),
    ],
)
def test_bad_images_are_refused(voc, image, match):
    with pytest.raises(ValueError, match=match):
        D.voc_foreground(image, voc)


@pytest.mark.parametrize("size", [(0, 10), (10,), (2.5, 3), (True, 4)])
def test_bad_label_sizes_are_refused(ade, size):
    with pytest.raises(ValueError, match="size must be"):
        D.ade20k_labels(np.zeros((8, 8, 3), np.uint8), size, ade)


def test_another_teachers_or_a_damaged_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="holds the 'deeplab_voc' teacher"):
        load_teacher(D.DeepLab, D.ADE20K, teacher_path(D.VOC))
    with pytest.raises(ValueError, match="unknown DeepLab weight set"):
        D.load_deeplab("deeplab_cityscapes")
    cut = tmp_path / "cut.pt"
    cut.write_bytes(teacher_path(D.ADE20K).read_bytes()[:100_000])
    with pytest.raises(ValueError, match="cannot read"):
        D.load_ade20k(cut)


# --------------------------------------------------------------- against the originals


def _shared_photos() -> list[Image.Image]:
    paths = [SHARED / p for p in PHOTOS]
    missing = [p for p in paths if not p.is_file()]
    if missing or not TEACHERS.is_dir():
        pytest.skip(f"../shared photos or teachers not available: {missing or TEACHERS}")
    out = []
    for p in paths:
        with Image.open(p) as im:
            out.append(im.convert("RGB"))
    return out


@pytest.mark.slow
@pytest.mark.shared_data
def test_ade20k_port_is_as_close_as_the_original_is_to_itself(ade):
    """The original is dynamic-range quantized (its activations rounded to int8 per pixel),
    so one float32 ulp on its input moves its probabilities by up to ~0.07: the bar is that
    nudge. On each photo the port's mean difference from the original is at most 1.5 times
    the nudge's, its largest at most 0.15, its argmax agrees on at least the nudge's share
    less 0.5 %, and the class labels agree with SceneTeachers.parse on 98 % of pixels
    (measured: mean 0.93-1.09 x, largest 0.049-0.064, argmax 99.31 / 98.84 / 99.80 % against
    the nudge's 99.36 / 98.76 / 99.83 %, labels 99.31 / 98.91 / 99.81 %). A float port
    without the int8 rounding fails it (largest 0.13-0.26, argmax 95.3-99.5 %), and so do
    these weights stored as float16."""
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    from d2f_core.train.scene_teachers import SceneTeachers, label_size

    photos = _shared_photos()
    original = SceneTeachers(TEACHERS, threads=1)
    for rgb in photos:
        x, (h, w) = D.ade20k_input(rgb)
        ref = _softmax(next(iter(original.ade.run(x[None]).values()))[0, :h, :w])
        nudged = np.nextafter(x, np.float32(2))[None]
        jitter = _softmax(next(iter(original.ade.run(nudged).values()))[0, :h, :w])
        port = D.ade20k_probabilities(rgb, ade)
        assert port.shape == ref.shape
        diff, own = np.abs(port - ref), np.abs(jitter - ref)
        assert diff.mean() <= 1.5 * own.mean()
        assert diff.max() <= 0.15
        agree = (port.argmax(-1) == ref.argmax(-1)).mean()
        assert agree >= (jitter.argmax(-1) == ref.argmax(-1)).mean() - 0.005
        labels = D.ade20k_labels(rgb, label_size(*rgb.size), ade)
        assert (labels == original.parse(rgb)).mean() >= 0.98


@pytest.mark.shared_data
def test_voc_port_matches_the_original(voc):
    """Float32 graph, float32 port: the probabilities within 1e-3 (measured 4e-6 to 9e-6;
    with the weights stored as float16, up to 0.026), the argmax everywhere but on ties,
    and Teachers' uint8 foreground within one level."""
    pytest.importorskip("onnxruntime", reason="onnxruntime is not installed (.[teach])")
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    from d2f_core.train.teachers import Teachers

    photos = _shared_photos()
    original = Teachers(TEACHERS, threads=1)
    for rgb in photos:
        x = D.voc_input(rgb)[None]
        ref = _softmax(original.seg.run(None, {original.seg_input: x})[0][0])
        port = D.voc_probabilities(rgb, voc)
        assert np.abs(port - ref).max() <= 1e-3
        assert (port.argmax(-1) == ref.argmax(-1)).mean() >= 0.999
        fg, _ = original(rgb)
        mine = D.voc_foreground(rgb, voc)
        assert np.abs(mine.astype(int) - fg).max() <= 1 and (mine == fg).mean() >= 0.999


@pytest.mark.shared_data
def test_converter_writes_the_shipped_files(tmp_path):
    pytest.importorskip("onnx", reason="onnx is not installed (.[teach])")
    pytest.importorskip("tflite", reason="tflite is not installed (.[teach])")
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    if not TEACHERS.is_dir():
        pytest.skip(f"teachers not available: {TEACHERS}")
    from d2f_core.train.port_deeplab import convert

    written = convert(TEACHERS, tmp_path)
    assert [p.name for p in written] == ["teacher_deeplab_ade20k.pt", "teacher_deeplab_voc.pt"]
    for path, name in zip(written, (D.ADE20K, D.VOC), strict=True):
        new = torch.load(path, weights_only=True)
        old = torch.load(teacher_path(name), weights_only=True)
        assert new["teacher"] == old["teacher"] == name and new["config"] == old["config"]
        assert new["state_dict"].keys() == old["state_dict"].keys()
        for k, v in new["state_dict"].items():
            assert v.dtype == old["state_dict"][k].dtype and torch.equal(v, old["state_dict"][k])
        D.load_deeplab(name, path)


@pytest.mark.shared_data
def test_converter_refuses_a_module_of_another_structure():
    """Matching by structure: the ADE20K graph does not fit the VOC config, a DeepLab without
    the decoder (the logits find no convolution) or one resizing the logits another way."""
    pytest.importorskip("tflite", reason="tflite is not installed (.[teach])")
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert is not installed (.[teach])")
    if not TEACHERS.is_dir():
        pytest.skip(f"teachers not available: {TEACHERS}")
    from d2f_core.train.port_deeplab import ADE_FILE, CONFIGS, match, read_tflite

    graph = read_tflite(TEACHERS / ADE_FILE)
    state, quantized = match(D.DeepLab(**CONFIGS[D.ADE20K]), graph)
    assert len(state) == len(D.DeepLab(**CONFIGS[D.ADE20K]).state_dict()) and quantized
    for change, what in [
        (CONFIGS[D.VOC], "0 candidates for backbone.stem"),
        ({**CONFIGS[D.ADE20K], "decoder": False}, "0 candidates for logits"),
        ({**CONFIGS[D.ADE20K], "resize": "asymmetric"}, "the logits' resize"),
    ]:
        with pytest.raises(ValueError, match=what):
            match(D.DeepLab(**change), graph)
