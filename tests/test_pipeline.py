"""D2F pipeline: prepare/render contract, fusion guarantees, checkpoints, input checks."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from PIL import Image

from d2f_core import rendering
from d2f_core.errors import InputTypeError
from d2f_core.metrics import psnr
from d2f_core.pipeline import D2F, D2FConfig, Result, Scene
from d2f_core.rendering.adaptive import BUDGETS
from d2f_core.sizing import resize
from d2f_core.train.synth import linear_to_srgb, make_scene, render_pinhole

pytestmark = pytest.mark.usefixtures("one_thread")


def _image(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.random((h // 8 + 1, w // 8 + 1, 3)).astype(np.float32)
    img = np.kron(base, np.ones((8, 8, 1), dtype=np.float32))[:h, :w]
    return np.clip(img + 0.05 * rng.standard_normal((h, w, 3)).astype(np.float32), 0, 1)


def _ramp(h: int = 48, w: int = 64) -> np.ndarray:
    return np.tile(np.linspace(0, 1, w, dtype=np.float32), (h, 1))


@pytest.fixture(scope="module")
def model() -> D2F:
    torch.manual_seed(0)
    return D2F.from_config({})


class TestPrepareRender:
    def test_scene_fields(self, model):
        scene = model.prepare(_image())
        assert isinstance(scene, Scene)
        assert scene.image.shape == (1, 3, 48, 64)
        assert scene.image_lr.shape == (1, 3, 24, 32)
        assert scene.disparity_lr.shape == (1, 1, 24, 32)
        assert scene.radiance_lr.shape == (1, 1, 24, 32)
        assert scene.size == (48, 64)
        assert scene.disparity_source == "d2f"
        assert 0 <= float(scene.disparity_lr.min()) <= float(scene.disparity_lr.max()) <= 1
        assert scene.disparity_full().shape == (48, 64)

    def test_network_reads_the_photo_not_the_smaller_pass(self):
        """A small photo's rendering pass is half its size; the network reads the photo
        itself, at up to ``network_size``, and its map is brought to the pass."""
        torch.manual_seed(0)
        model = D2F.from_config({"network_size": 48})
        seen = []
        hook = model.defocus_net.register_forward_hook(lambda m, i, o: seen.append(i[0].shape))
        try:
            scene = model.prepare(_image(40, 60), refine=False)
        finally:
            hook.remove()
        assert seen == [(1, 3, 32, 48)]  # the photo at network_size, not the 20 x 30 pass
        assert scene.disparity_lr.shape == (1, 1, 20, 30)
        x = torch.from_numpy(_image(40, 60)).permute(2, 0, 1)[None]
        with torch.no_grad():
            want = model.predict_disparity(torch.zeros(1, 3, 20, 30), False, photo=x)
            direct = resize(model.defocus_net(resize(x, (32, 48))), (20, 30))
        torch.testing.assert_close(scene.disparity_lr, want)
        torch.testing.assert_close(want, direct.clamp(0, 1))
        # a pass as large as network_size or larger is read as before: the same map
        big = torch.from_numpy(_image(200, 300)).permute(2, 0, 1)[None]
        lr = resize(big, (100, 150))
        with torch.no_grad():
            torch.testing.assert_close(
                model.predict_disparity(lr, False, photo=big), model.predict_disparity(lr, False)
            )

    @pytest.mark.parametrize(
        ("photo", "match"),
        [
            (torch.rand(2, 3, 40, 60), "batch"),  # a batch of 2 for one image
            (torch.rand(3, 40, 60), "batch"),
            ((torch.rand(1, 3, 40, 60) * 255).to(torch.uint8), "float"),
            (torch.rand(1, 3, 10, 15), "smaller"),
            (torch.rand(1, 3, 90, 40), "same frame"),  # a portrait photo for a landscape pass
            (torch.rand(1, 3, 40, 90), "same frame"),
        ],
    )
    def test_a_photo_that_is_not_the_images_is_refused(self, photo, match):
        model = D2F.from_config({"network_size": 48})
        with torch.no_grad(), pytest.raises(ValueError, match=match):
            model.predict_disparity(torch.rand(1, 3, 20, 30), False, photo=photo)

    @pytest.mark.parametrize("size", [(1, 1), (1, 9), (3, 767), (767, 3), (5, 7), (33, 1000)])
    def test_odd_sizes_read_the_photo(self, size):
        """Every photo and its rendering pass (rounded on each side) pass the check."""
        model = D2F.from_config({"network_size": 48})
        scene = model.prepare(_image(*size), refine=False)
        assert scene.disparity_lr.shape[-2:] == model.pass_size(size)

    def test_uint8_equals_float(self, model):
        img8 = (_image() * 255).round().astype(np.uint8)
        a = model.prepare(img8)
        b = model.prepare(img8.astype(np.float32) / 255)
        assert torch.allclose(a.disparity_lr, b.disparity_lr, atol=1e-6)

    def test_result_fields(self, model):
        res = model.render(model.prepare(_image()), focus=0.5, blur=12.0)
        assert isinstance(res, Result)
        assert res.bokeh.shape == (48, 64, 3) and res.bokeh.dtype == np.float32
        assert res.bokeh_lr.shape == (24, 32, 3)
        assert res.disparity.shape == res.defocus.shape == (24, 32)
        assert res.fusion_mask.shape == (48, 64)
        for arr in (res.bokeh, res.bokeh_lr, res.disparity, res.defocus, res.fusion_mask):
            assert arr.min() >= 0 and arr.max() <= 1
        assert {"render_lr", "total"} <= set(res.timings)

    def test_low_res_pass_equals_render_bokeh(self, model):
        image, disp = _image(), _ramp()
        scene = model.prepare(image, disparity=disp)
        res = model.render(scene, focus=0.3, blur=20.0)
        expected = rendering.render_bokeh(
            scene.image_lr[0].permute(1, 2, 0).numpy(),
            scene.disparity_lr[0, 0].numpy(),
            0.3,
            10.0,  # K scales with the pass: 24x32 is half of 48x64
            radiance=scene.radiance_lr,
            placement=model.config.placement,
        )
        np.testing.assert_allclose(res.bokeh_lr, expected, atol=1e-6)

    def test_full_scale_without_fusion_is_render_bokeh(self):
        torch.manual_seed(0)
        model = D2F.from_config({"render_scale": 1.0})
        image, disp = _image(), _ramp()
        scene = model.prepare(image, disparity=disp)
        res = model.render(scene, focus=0.6, blur=9.0, fusion=False, highlight_boost=False)
        expected = rendering.render_bokeh(
            image,
            disp,
            0.6,
            9.0,
            radiance=scene.radiance_lr,
            highlight_boost=False,
            placement=model.config.placement,
        )
        np.testing.assert_allclose(res.bokeh, expected, atol=1e-6)
        assert not res.fusion_mask.any()

    def test_given_disparity_resized(self, model):
        scene = model.prepare(_image(), disparity=np.full((12, 16), 0.25, np.float32))
        assert scene.disparity_source == "given"
        np.testing.assert_allclose(scene.disparity_full(), 0.25, atol=1e-6)
        np.testing.assert_allclose(scene.disparity_lr.numpy(), 0.25, atol=1e-6)
        # a map of another shape is refused, not stretched onto the 64x48 photo
        with pytest.raises(ValueError, match=r"depth map is 48x64 .* rotated by 90 degrees"):
            model.prepare(_image(), depth=np.full((64, 48), 0.25, np.float32))
        with pytest.raises(ValueError, match="depth map is 48x48 but the image is 64x48"):
            model.prepare(_image(), depth=np.full((48, 48), 0.25, np.float32))

    def test_zero_blur_returns_input(self, model):
        image = _image()
        res = model.render(model.prepare(image, disparity=_ramp()), focus=0.5, blur=0.0)
        np.testing.assert_allclose(res.bokeh, image, atol=1e-6)
        np.testing.assert_allclose(res.fusion_mask, 1.0)

    def test_in_focus_pixels_stay_sharp(self, model):
        # left half exactly at the focal plane, right half far behind it
        disp = np.where(np.arange(64)[None, :] < 32, 0.8, 0.0).astype(np.float32)
        disp = np.repeat(disp, 48, axis=0)
        image = _image()
        res = model.render(model.prepare(image, disparity=disp), focus=0.8, blur=40.0)
        np.testing.assert_allclose(res.fusion_mask[:, :31], 1.0)
        np.testing.assert_allclose(res.bokeh[:, :31], image[:, :31], atol=1e-6)
        # far half: CoC 32 px, D well above the gate, so the blurred pass is used
        assert res.fusion_mask[:, 34:].max() == 0.0
        assert np.abs(res.bokeh[:, 34:] - image[:, 34:]).mean() > 0.01

    def test_preview(self, model):
        scene = model.prepare(_image(96, 128), disparity=_ramp(96, 128))
        res = model.render(scene, focus=0.5, blur=30.0, max_side=32)
        assert res.bokeh.shape == (24, 32, 3)
        assert res.fusion_mask.shape == (24, 32) and not res.fusion_mask.any()
        again = model.render(scene, focus=0.5, blur=30.0, max_side=32)
        np.testing.assert_array_equal(res.bokeh, again.bokeh)

    def test_render_options_pass_through(self, model):
        scene = model.prepare(_image(), disparity=_ramp())
        a = model.render(scene, 0.5, 30.0, kernel="hard", fusion=False)
        b = model.render(scene, 0.5, 30.0, kernel="soft", fusion=False)
        assert np.abs(a.bokeh - b.bokeh).max() > 1e-4
        with pytest.raises(ValueError, match="kernel"):
            model.render(scene, 0.5, 30.0, kernel="bogus")


class TestFusion:
    @pytest.mark.parametrize(
        ("focus", "blur"), [(0.5, 20.0), (0.52, 200.0), (0.3, 3.0), (0.5, 0.5), (0.0, 40.0)]
    )
    def test_tiled_equals_dense(self, focus, blur):
        torch.manual_seed(0)
        model = D2F.from_config({"fusion": "paper"})  # the widest halo
        h, w = 300, 600
        image = np.random.default_rng(0).random((h, w, 3), dtype=np.float32)
        # a ramp (mixed tiles), then a flat region at 0.5 (all-sharp tiles when focus = 0.5)
        disp = np.full((h, w), 0.5, np.float32)
        disp[:, :280] = np.linspace(0, 1, 280, dtype=np.float32)
        scene = model.prepare(image, disparity=disp)
        bokeh_up = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(1))
        with torch.no_grad():
            mask, _ = model.fusion_mask(
                scene.image, scene.disparity_full_tensor(), focus, blur, 0.5
            )
            expected = torch.lerp(bokeh_up, scene.image, mask)
            fused, tiled_mask = model._fuse_tiled(scene, bokeh_up.clone(), focus, blur, 0.5)
        torch.testing.assert_close(tiled_mask, mask, atol=1e-6, rtol=0)
        torch.testing.assert_close(fused, expected, atol=1e-6, rtol=0)

    def test_mask_is_at_least_the_prior(self, model):
        image = torch.rand(1, 3, 16, 16)
        disp = torch.linspace(0, 1, 16).expand(1, 1, 16, 16).contiguous()
        with torch.no_grad():
            mask, soft = model.fusion_mask(image, disp, 0.5, 10.0, 0.5)
        coc = 10.0 * (disp - 0.5).abs()
        assert torch.all(mask[coc <= 1.0] == 1.0)
        assert torch.all(mask >= soft)


class TestFocusAt:
    def test_median_ignores_outliers(self, model):
        disp = np.full((48, 64), 0.2, np.float32)
        disp[10:15, 20:25] = 0.8
        disp[12, 22] = 0.0  # one outlier inside the window
        scene = model.prepare(_image(), disparity=disp)
        assert model.focus_at(scene, 22, 12, radius=2) == pytest.approx(0.8, abs=1e-6)

    def test_edges_and_outside(self, model):
        disp = np.full((48, 64), 0.1, np.float32)
        disp[:, -4:] = 0.9
        scene = model.prepare(_image(), disparity=disp)
        # the photo's pixel area, [-0.5, W - 0.5] x [-0.5, H - 0.5], is inside
        assert model.focus_at(scene, 63.5, -0.5, radius=1) == pytest.approx(0.9, abs=1e-6)
        assert model.focus_at(scene, -0.5, 47.5) == pytest.approx(0.1, abs=1e-6)
        # a point outside is refused, not moved onto the border
        for x, y in ((500, -30), (-5, 10), (10, 48), (-1, -1)):
            with pytest.raises(ValueError, match=r"outside the 64x48 photo"):
                model.focus_at(scene, x, y)

    def test_bad_args(self, model):
        scene = model.prepare(_image())
        with pytest.raises(ValueError, match="finite"):
            model.focus_at(scene, float("nan"), 3)
        with pytest.raises(TypeError, match="scene"):
            model.focus_at("scene", 1, 1)
        # a window radius is a whole number of pixels, never truncated
        for radius, words in (
            (float("nan"), "radius must be a whole number"),
            (2.7, "radius must be a whole number, got 2.7"),
            (-1, "radius must be >= 0"),
            ("3", "radius must be a whole"),
        ):
            with pytest.raises(ValueError, match=words):
                model.focus_at(scene, 5, 5, radius=radius)
        assert model.focus_at(scene, 5, 5, radius=np.int64(2)) == model.focus_at(
            scene, 5, 5, radius=2.0
        )


class TestInputChecks:
    def test_bad_images(self, model):
        with pytest.raises(ValueError, match="image"):
            model.prepare(np.zeros((8, 8), np.float32))
        with pytest.raises(ValueError, match="image"):
            model.prepare(np.full((8, 8, 3), 2.0, np.float32))
        with pytest.raises(ValueError, match="NaN"):
            model.prepare(np.full((8, 8, 3), np.nan, np.float32))
        with pytest.raises(TypeError, match="image"):
            model.prepare([[1, 2, 3]])
        # wrong types and dtypes are ValueErrors too: one except clause catches all bad input
        with pytest.raises(ValueError, match="uint8 or float"):
            model.prepare(np.zeros((8, 8, 3), np.int16))
        with pytest.raises(ValueError, match="image"):
            model.prepare("photo.jpg")

    def test_bad_disparity(self, model):
        nan = np.zeros((8, 8), np.float32)
        nan[2, 2] = np.inf
        with pytest.raises(ValueError, match="disparity contains NaN or inf"):
            model.prepare(_image(), disparity=nan)
        with pytest.raises(ValueError, match="disparity must have shape"):
            model.prepare(_image(), disparity=np.zeros((4, 4, 3), np.float32))
        with pytest.raises(ValueError, match=r"disparity must be in \[0, 1\]"):
            model.prepare(_image(), disparity=np.full((4, 4), 3.0, np.float32))
        for kind in (np.complex64, np.bool_):
            with pytest.raises(ValueError, match="disparity must be real numbers"):
                model.prepare(_image(), disparity=np.zeros((4, 4), kind))
        with pytest.raises(ValueError, match="disparity must be real numbers"):
            model.prepare(_image(), disparity=torch.zeros(4, 4, dtype=torch.complex64))

    def test_focus_is_checked_once_on_the_way_down(self, model, monkeypatch):
        # D2F.render checks focus and blur; choose_settings and rendering.render take them
        # as checked, with the preview, the adaptive settings and fixed settings alike
        scene = model.prepare(_image())
        check = rendering.inputs._check_focus
        for kwargs in ({}, {"max_side": 32}, {"budget": None}, {"num_layers": 8}):
            seen: list[float] = []
            monkeypatch.setattr(
                rendering.inputs, "_check_focus", lambda v, seen=seen: seen.append(v) or check(v)
            )
            model.render(scene, 0.4, 20.0, **kwargs)
            assert seen == [0.4], kwargs
        with pytest.raises(ValueError, match="'checked'"):
            model.render(scene, 0.4, 20.0, checked=False)

    def test_bad_focus_blur(self, model):
        scene = model.prepare(_image())
        with pytest.raises(ValueError, match="focus"):
            model.render(scene, focus=1.5, blur=10.0)
        with pytest.raises(ValueError, match="blur"):
            model.render(scene, focus=0.5, blur=-1.0)
        # text and bools are no numbers, though float() takes them ("0.5", True as 1 px)
        for focus, blur, name in (("0.5", 10.0, "focus"), (True, 10.0, "focus"),
                                  (0.5, True, "blur"), (0.5, np.bool_(True), "blur"),
                                  (0.5, b"10", "blur"), (np.array(True), 10.0, "focus"),
                                  (0.5, torch.tensor(True), "blur"),
                                  (np.array("0.5"), 10.0, "focus")):  # fmt: skip
            with pytest.raises(InputTypeError, match=f"{name} must be a number, got"):
                model.render(scene, focus=focus, blur=blur)
        with pytest.raises(ValueError, match="max_side"):
            model.render(scene, focus=0.5, blur=1.0, max_side=0)
        # a preview side is a whole number: 1.5 is not truncated to a 1 px preview
        for side in (float("nan"), 1.5, "x", True):
            with pytest.raises(ValueError, match="max_side must be a whole number"):
                model.render(scene, focus=0.5, blur=1.0, max_side=side)
        same = model.render(scene, focus=0.5, blur=4.0, max_side=np.int32(32)).bokeh
        np.testing.assert_array_equal(same, model.render(scene, 0.5, 4.0, max_side=32.0).bokeh)
        # an f-number may be a NumPy scalar, as focus and blur may
        np.testing.assert_array_equal(
            model.render(scene, 0.5, f_number=np.float32(2.8)).bokeh,
            model.render(scene, 0.5, f_number=float(np.float32(2.8))).bokeh,
        )
        with pytest.raises(TypeError, match="scene"):
            model.render(None, 0.5, 1.0)

    def test_bad_config(self):
        with pytest.raises(ValueError, match="unknown config keys"):
            D2F.from_config({"colour": "red"})
        with pytest.raises(ValueError, match="variant"):
            D2F.from_config({"defocus": "vit"})
        with pytest.raises(TypeError, match="network_size"):
            D2FConfig(network_size="big")
        with pytest.raises(ValueError, match="placement"):
            D2FConfig(placement="middle")

    def test_placement_comes_from_the_config(self, model):
        # the shipped weights were trained with "paper" placement: a model renders with its
        # config's placement unless the call names one
        assert model.config.placement == "paper"
        scene = model.prepare(_image(), disparity=_ramp())
        kw = {"fusion": False, "budget": None}
        default = model.render(scene, 0.9, 24.0, **kw).bokeh
        paper = model.render(scene, 0.9, 24.0, placement="paper", **kw).bokeh
        nearest = model.render(scene, 0.9, 24.0, placement="nearest", **kw).bokeh
        np.testing.assert_array_equal(default, paper)
        assert np.abs(nearest - paper).max() > 0.01  # CoCs behind focus get the next kernel
        other = D2F.from_config({"placement": "nearest"})
        other.load_state_dict(model.state_dict())
        np.testing.assert_allclose(
            other.render(other.prepare(_image(), disparity=_ramp()), 0.9, 24.0, **kw).bokeh,
            nearest,
            atol=1e-6,
        )


class TestCheckpoints:
    def test_roundtrip_identical(self, model, tmp_path):
        path = tmp_path / "m.pt"
        model.save(path)
        loaded = D2F.from_checkpoint(path)
        assert loaded.config == model.config
        assert not loaded.training
        image = _image()
        a = model.render(model.prepare(image), 0.5, 20.0)
        b = loaded.render(loaded.prepare(image), 0.5, 20.0)
        np.testing.assert_array_equal(a.bokeh, b.bokeh)

    def test_truncated(self, model, tmp_path):
        path = tmp_path / "m.pt"
        model.save(path)
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        with pytest.raises(ValueError, match="cannot be read: its archive is damaged or cut short"):
            D2F.from_checkpoint(path)

    def test_not_a_checkpoint_in_one_line(self, tmp_path):
        """A photo or a pickled object given as weights: one line that names the file and
        says why, never torch's advice to load it with ``weights_only=False``."""
        photo = tmp_path / "photo.png"
        Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(photo)
        with pytest.raises(ValueError) as info:
            D2F.from_checkpoint(photo)
        text = str(info.value)
        assert text == f"checkpoint {photo} cannot be read: not a PyTorch checkpoint, or cut short"
        obj = tmp_path / "obj.pt"
        torch.save({"weights": os.getcwd}, obj)
        with pytest.raises(ValueError) as info:
            D2F.from_checkpoint(obj)
        text = str(info.value)
        assert "holds a Python object (posix.getcwd)" in text
        assert "\n" not in text and "weights_only" not in text
        # the usual form of torch's refusal: an object of an allowed-looking class
        torch.save({"weights": slice(1, 2)}, obj)
        with pytest.raises(ValueError, match=r"holds a Python object \(slice\)"):
            D2F.from_checkpoint(obj)

    def test_garbage_and_wrong_layout(self, tmp_path):
        path = tmp_path / "g.pt"
        path.write_bytes(b"\x00garbage")
        with pytest.raises(ValueError, match="cannot be read: not a PyTorch checkpoint"):
            D2F.from_checkpoint(path)
        torch.save({"weights": torch.zeros(1)}, path)
        with pytest.raises(ValueError, match="'config' and 'state_dict'"):
            D2F.from_checkpoint(path)

    def test_mismatched_config(self, model, tmp_path):
        ckpt = model.checkpoint()
        ckpt["config"] = dict(ckpt["config"], fusion="paper")
        path = tmp_path / "mm.pt"
        torch.save(ckpt, path)
        with pytest.raises(ValueError, match="does not match its config"):
            D2F.from_checkpoint(path)
        ckpt = model.checkpoint()
        ckpt["config"]["bogus"] = 1
        torch.save(ckpt, path)
        with pytest.raises(ValueError, match="invalid config"):
            D2F.from_checkpoint(path)
        ckpt = model.checkpoint()
        ckpt["version"] = 99
        torch.save(ckpt, path)
        with pytest.raises(ValueError, match="version"):
            D2F.from_checkpoint(path)

    def test_missing_files(self, tmp_path, monkeypatch):
        with pytest.raises(FileNotFoundError, match="nope.pt"):
            D2F.from_checkpoint(tmp_path / "nope.pt")
        with pytest.raises(FileNotFoundError, match="missing.pt"):
            D2F.from_pretrained(tmp_path / "missing.pt")
        monkeypatch.setenv("D2F_WEIGHTS", str(tmp_path / "env.pt"))
        with pytest.raises(FileNotFoundError, match="env.pt"):
            D2F.from_pretrained()

    def test_pretrained_from_env(self, model, tmp_path, monkeypatch):
        path = tmp_path / "env.pt"
        model.save(path)
        monkeypatch.setenv("D2F_WEIGHTS", str(path))
        assert D2F.from_pretrained().config == model.config


class TestTrainingForwards:
    def test_stage1_gradients(self):
        torch.manual_seed(0)
        model = D2F.from_config({}).train()
        out = model.forward_stage1(torch.rand(2, 3, 32, 32), 1.0, torch.tensor([8.0, 12.0]))
        assert out["bokeh_lr"].shape == (2, 3, 32, 32)
        out["bokeh_lr"].mean().backward()
        assert model.defocus_net.project[0][1].weight.grad is not None
        assert model.radiance_net.net[0].weight.grad is not None
        assert model.fusion_net.net[0].weight.grad is None

    def test_stage2_trains_fusion_only(self):
        torch.manual_seed(0)
        model = D2F.from_config({}).train()
        image = torch.rand(1, 3, 32, 32)
        out = model.forward_stage2(image, 0.5, 10.0)
        assert out["bokeh"].shape == out["bokeh_up"].shape == (1, 3, 32, 32)
        assert out["bokeh_lr"].shape == (1, 3, 16, 16)
        out["bokeh"].mean().backward()
        assert model.fusion_net.net[0].weight.grad is not None
        assert all(p.grad is None for p in model.defocus_net.parameters())


class TestAdaptive:
    """``D2F.render`` picks its settings per focus and blur from an error budget."""

    @staticmethod
    def _no_render(*args, **kwargs):
        raise AssertionError("the layered renderer must not run")

    def test_sub_pixel_blur_takes_the_identity_path(self, model, monkeypatch):
        image = _image()
        scene = model.prepare(image, disparity=_ramp())
        monkeypatch.setattr(rendering, "render", self._no_render)
        for blur in (0.0, 0.9):  # largest CoC 0.9 px: nothing to blur
            res = model.render(scene, focus=0.0, blur=blur)
            assert res.settings is not None and res.settings.identity
            np.testing.assert_allclose(res.bokeh, image, atol=1e-6)
            np.testing.assert_array_equal(res.fusion_mask, 1.0)
        with pytest.raises(AssertionError, match="must not run"):
            model.render(scene, focus=0.0, blur=1.5)  # a 1.5 px CoC needs the renderer
        with pytest.raises(AssertionError, match="must not run"):
            model.render(scene, focus=0.0, blur=0.0, budget=None)  # fixed settings

    def test_identity_uses_the_full_resolution_map(self, model):
        # the given map's one near pixel is averaged away in the low-res copy
        disp = np.zeros((48, 64), np.float32)
        disp[20, 30] = 1.0
        scene = model.prepare(_image(), disparity=disp)
        assert float(scene.disparity_lr.max()) < 0.5
        res = model.render(scene, focus=0.0, blur=1.5)
        assert not res.settings.identity  # full-res CoC there is 1.5 px

    def test_fusion_skipped_when_nothing_is_near_focus(self, model, monkeypatch):
        scene = model.prepare(_image(), disparity=_ramp() * 0.4)
        calls = []
        fuse = model._fuse_tiled
        monkeypatch.setattr(model, "_fuse_tiled", lambda *a: calls.append(1) or fuse(*a))
        # nearest pixel 0.6 from focus: CoC >= 60 px at full res, far above the fusion gate
        res = model.render(scene, focus=1.0, blur=100.0)
        assert not res.settings.fusion and calls == [] and not res.fusion_mask.any()
        fixed = model.render(scene, focus=1.0, blur=100.0, budget=None, quality="exact")
        assert calls == [1] and not fixed.fusion_mask.any()  # the fixed path ran it for nothing
        res = model.render(scene, focus=0.2, blur=100.0)
        assert res.settings.fusion and calls == [1, 1] and res.fusion_mask.max() == 1.0

    @pytest.mark.parametrize("budget", ["balanced", "fast", 35.0])
    def test_stays_within_budget_of_the_exact_renderer(self, budget):
        torch.manual_seed(0)
        model = D2F.from_config({"render_scale": 0.5})
        radiance, disp = render_pinhole(make_scene((192, 288), seed=11))
        scene = model.prepare(linear_to_srgb(radiance), disparity=disp)
        limit = budget if isinstance(budget, float) else BUDGETS[budget]
        for focus, blur in ((0.3, 20.0), (0.7, 60.0), (0.5, 150.0), (0.0, 400.0)):
            res = model.render(scene, focus, blur, fusion=False, budget=budget)
            ref = model.render(scene, focus, blur, fusion=False, budget=None, quality="exact")
            assert res.settings is not None and not res.settings.identity
            assert res.settings.num_layers in (5, 7, 9, 11, 15)
            score = psnr(res.bokeh_lr, ref.bokeh_lr)
            assert score >= limit, (focus, blur, res.settings, score)

    def test_low_budget_affords_fewer_layers(self):
        # CoCs over 128 px and a 20 dB budget: a coarser schedule is cheaper and still within it
        torch.manual_seed(0)
        model = D2F.from_config({"render_scale": 0.5})
        radiance, disp = render_pinhole(make_scene((192, 288), seed=11))
        scene = model.prepare(linear_to_srgb(radiance), disparity=disp)
        res = model.render(scene, 0.0, 400.0, fusion=False, budget=20.0)
        ref = model.render(scene, 0.0, 400.0, fusion=False, budget=None, quality="exact")
        assert res.settings.num_layers < 15
        assert psnr(res.bokeh_lr, ref.bokeh_lr) >= 20.0  # 7 layers, 34.8 dB measured

    def test_fixed_settings_pick_nothing(self, model):
        scene = model.prepare(_image(), disparity=_ramp())
        assert model.render(scene, 0.5, 30.0, quality="high").settings is None
        assert model.render(scene, 0.5, 30.0, num_layers=9).settings is None
        assert model.render(scene, 0.5, 30.0, order="paper").settings is None
        assert model.render(scene, 0.5, 30.0, budget=None).settings is None
        assert model.render(scene, 0.5, 30.0).settings.budget_db == 40.0

    @pytest.mark.parametrize("budget", ["bogus", True, "40", float("nan"), [40], -1.0, 0])
    def test_bad_budget(self, model, budget):
        scene = model.prepare(_image(), disparity=_ramp())
        with pytest.raises(ValueError, match="budget"):
            model.render(scene, 0.5, 30.0, budget=budget)


@pytest.mark.slow
def test_one_blur_limit_named_in_the_units_typed(tiny_model):
    """D2F.render and render_bokeh take the same largest blur, and a blur past it is reported
    as it was given (D2F.render passes blur / 2 to its half-resolution pass)."""
    from d2f_core import render_bokeh
    from d2f_core.rendering import MAX_BLUR

    image = np.zeros((32, 32, 3), np.float32)
    scene = tiny_model.prepare(image)
    tiny_model.render(scene, 0.5, MAX_BLUR, budget=None)  # the limit itself renders
    render_bokeh(image, np.zeros((32, 32), np.float32), 0.5, MAX_BLUR)
    for call in (
        lambda: tiny_model.render(scene, 0.5, 1e9),
        lambda: render_bokeh(image, np.zeros((32, 32), np.float32), 0.5, 1e9),
    ):
        with pytest.raises(ValueError, match=r"blur must .*10000.*got 1000000000\.0"):
            call()


def _rim(edge_step: float) -> tuple[float, float]:
    """A bright disc in focus before a dark wall, its map stored at a quarter size as a
    phone stores it: how much brighter the blurred wall is 2-12 px outside the disc than
    30-50 px out (its true brightness is the same), and the same for the input."""
    from PIL import Image
    from scipy.ndimage import distance_transform_edt

    h = w = 192
    yy, xx = np.mgrid[:h, :w]
    disc = np.hypot(yy - 96, xx - 96) < 40
    rng = np.random.default_rng(0)
    img = np.where(disc[..., None], 0.9, 0.2) + 0.02 * rng.standard_normal((h, w, 3))
    img = np.clip(img, 0, 1).astype(np.float32)
    small = Image.fromarray((0.1 + 0.8 * disc[::4, ::4]).astype(np.float32))
    soft = np.array(small.resize((w, h), Image.BILINEAR), dtype=np.float32)
    out = distance_transform_edt(~disc)
    ring, far = (out > 2) & (out <= 12), (out > 30) & (out <= 50)
    torch.manual_seed(0)
    model = D2F.from_config({"render_scale": 1.0, "edge_step": edge_step})
    bokeh = model.render(model.prepare(img, disparity=soft), focus=0.9, blur=40.0).bokeh
    grey, photo = bokeh.mean(-1), img.mean(-1)
    return float(grey[ring].mean() - grey[far].mean()), float(
        photo[ring].mean() - photo[far].mean()
    )


def test_no_bright_rim_round_a_sharp_subject():
    """The pixels of a soft silhouette used to be drawn with a blur neither side has, a rim
    of the subject's colour over the background (0.048 brighter with edge_step=0)."""
    rim, truth = _rim(0.1)
    assert abs(truth) < 0.002
    assert rim < 0.012  # 0.005 measured
    before, _ = _rim(0.0)
    assert before > 3 * rim


def _spill(model: D2F) -> tuple[int, int, int, int]:
    """A bright near lamp blurred (CoC 42 px) across the line between an in-focus wall above
    and a far, blurred room below: how far its glow reaches above, below, left and right of
    it along its middle row and column."""
    h = w = 256
    rng = np.random.default_rng(0)
    img = (0.25 + 0.1 * rng.random((h, w, 3))).astype(np.float32)
    disp = np.zeros((h, w), np.float32)
    disp[: h // 2] = 0.3  # the wall, in focus
    y0, y1, x0, x1 = 108, 148, 108, 148
    img[y0:y1, x0:x1], disp[y0:y1, x0:x1] = 0.95, 1.0
    grey = model.render(model.prepare(img, disparity=disp), focus=0.3, blur=60.0).bokeh.mean(-1)
    rows, cols = np.nonzero(grey[:, 128] > 0.45)[0], np.nonzero(grey[128] > 0.45)[0]
    return y0 - rows[0], rows[-1] - (y1 - 1), x0 - cols[0], cols[-1] - (x1 - 1)


def test_blurred_foreground_stays_round_over_an_in_focus_background(model):
    """Sharpening the in-focus wall used to paste it over the lamp's glow: the glow stopped
    dead at the wall (0 px above, 4 below, 6 to the sides). Now only what lies behind the
    glow is sharpened, and the glow reaches as far on every side (12, 12, 13, 13 px)."""
    above, below, left, right = _spill(model)
    assert above >= 8 and max(above, below, left, right) - min(above, below, left, right) <= 2


def test_small_photos_render_at_their_own_size():
    """With a given map, up to ``full_pass_side`` the rendering pass is the photo's own size
    and nothing is fused (there is no lost detail to restore); above it, and for the
    network's own maps, the pass is ``render_scale`` of the photo, fused."""
    torch.manual_seed(0)
    model = D2F.from_config({"full_pass_side": 64})
    image, disp = _image(), _ramp()  # 48x64
    scene = model.prepare(image, disparity=disp)
    assert model.pass_size((48, 64), given=True) == (48, 64) == tuple(scene.image_lr.shape[-2:])
    assert model.pass_size((48, 64)) == (24, 32) == model.prepare(image).image_lr.shape[-2:]
    res = model.render(scene, focus=0.6, blur=9.0)
    expected = rendering.render_bokeh(
        scene.image_lr[0].permute(1, 2, 0).numpy(),
        scene.disparity_lr[0, 0].numpy(),
        0.6,
        9.0,
        radiance=scene.radiance_lr,
        placement=model.config.placement,
    )
    np.testing.assert_allclose(res.bokeh, expected, atol=1e-6)
    assert not res.fusion_mask.any() and "fusion" not in res.timings
    assert model.pass_size((48, 65), given=True) == (24, 32)  # past the side: half, fused
    big = model.render(model.prepare(_image(48, 80), disparity=_ramp(48, 80)), 0.6, 9.0)
    assert big.bokeh_lr.shape == (24, 40, 3) and big.fusion_mask.any()
    with pytest.raises(ValueError, match="full_pass_side"):
        D2F.from_config({"full_pass_side": -1})
