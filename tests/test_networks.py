"""Shapes, ranges, parameter counts and weight loading of the D2F networks."""

from __future__ import annotations

import pytest
import torch

from d2f_core.networks import (
    DEFOCUS_NETS,
    FUSION_NETS,
    RADIANCE_NETS,
    DefocusNet,
    FusionNet,
    RadianceNet,
    build_defocus_net,
    build_fusion_net,
    build_radiance_net,
    count_parameters,
    rgb_to_gray,
)

# torchvision's resnext50_32x4d has 25,028,904 parameters, 2,049,000 of them in `fc`.
RESNEXT50_ENCODER_PARAMS = 25_028_904 - 2_049_000


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def resnext() -> DefocusNet:
    torch.manual_seed(0)
    return DefocusNet("resnext50").eval()


def _trained_looking(variant: str, seed: int) -> DefocusNet:
    """A lite network in eval mode with a non-zero context output (where it has a context)
    and batch-norm statistics moved off their start, so that growing it checks they carry."""
    torch.manual_seed(seed)
    net = DefocusNet(variant)
    if net.context is not None:
        torch.nn.init.normal_(net.context.out.weight, std=0.05)
    net.train()
    with torch.no_grad():
        for _ in range(3):
            net(torch.rand(4, 3, 64, 96))
    return net.eval()


class TestDefocusNet:
    @pytest.mark.parametrize("size", [(64, 64), (50, 70), (33, 97)])
    def test_lite_shape_and_range(self, size):
        torch.manual_seed(0)
        net = DefocusNet("lite").eval()
        with torch.no_grad():
            out = net(torch.rand(2, 3, *size))
        assert out.shape == (2, 1, *size)
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0

    def test_resnext_shape_and_range(self, resnext):
        with torch.no_grad():
            out = resnext(torch.rand(1, 3, 40, 72))
        assert out.shape == (1, 1, 40, 72)
        assert 0.0 <= float(out.min()) <= float(out.max()) <= 1.0

    def test_parameter_counts(self, resnext):
        lite = DefocusNet("lite")
        assert count_parameters(lite) <= 5_000_000
        assert count_parameters(resnext.encoder) == RESNEXT50_ENCODER_PARAMS

    def test_gradients_reach_encoder(self):
        torch.manual_seed(0)
        net = DefocusNet("lite").train()
        net(torch.rand(2, 3, 32, 32)).mean().backward()
        first = next(net.encoder.parameters())
        assert first.grad is not None and float(first.grad.abs().sum()) > 0

    @pytest.mark.parametrize("size", [(64, 64), (50, 70), (33, 97)])
    def test_context_variant_grows_from_lite(self, size):
        torch.manual_seed(0)
        lite = DefocusNet("lite").eval()
        ctx = DefocusNet("lite-ctx").eval()
        ctx.load_lite(lite.state_dict())
        x = torch.rand(2, 3, *size)
        with torch.no_grad():
            assert torch.equal(ctx(x), lite(x))  # zero-initialised context output
            # once trained, the context changes the map everywhere, padding or not
            torch.nn.init.normal_(ctx.context.out.weight, std=0.5)
            changed = ctx(x)
            plain = lite(x)
        assert changed.shape == (2, 1, *size)
        assert float((changed - plain).abs().mean()) > 1e-3
        assert count_parameters(ctx) - count_parameters(lite) < 50_000
        with pytest.raises(ValueError, match="not a 'lite'"):
            ctx.load_lite({"nope": torch.zeros(1)})

    @pytest.mark.parametrize("small_variant", ["lite", "lite-ctx"])
    def test_wide_variant_grows_from_smaller_lite(self, small_variant):
        small = _trained_looking(small_variant, seed=0)
        wide = DefocusNet("lite-wide")
        wide.load_lite(small.state_dict())
        wide.eval()
        x = torch.rand(2, 3, 50, 70)
        with torch.no_grad():
            before = small(x)
            assert float((wide(x) - before).abs().max()) < 1e-5  # the same map
            # the new hidden channels have inputs; their outputs start at zero, and once
            # they are trained the map changes
            block = wide.encoder.stages[3][0].block
            assert float(block[6].weight[:, 96 * 4 :].abs().max()) == 0.0
            assert float(block[0].weight[96 * 4 :].abs().max()) > 0.0
            deepest = small.encoder(x)[3]
            assert float((wide.encoder(x)[3] - deepest).abs().max()) < 1e-4
            torch.nn.init.normal_(block[6].weight, std=0.2)
            assert float((wide.encoder(x)[3] - deepest).abs().mean()) > 1e-2
        assert 2_000_000 < count_parameters(wide) < 2 * count_parameters(small)
        with pytest.raises(ValueError, match="not a 'lite'"):
            wide.load_lite({"nope": torch.zeros(1)})
        with pytest.raises(ValueError, match="does not fit"):
            wide.load_lite(
                DefocusNet("lite-wide").state_dict() | {"head.2.weight": torch.zeros(1, 64, 1, 1)}
            )

    def test_xl_variant_grows_from_the_shipped_size_within_budget(self):
        """``"lite-xl"`` starts from a trained ``"lite-ctx"`` computing the same map, and stays
        inside the depth issue's budget of 5 M parameters."""
        small = _trained_looking("lite-ctx", seed=1)
        xl = DefocusNet("lite-xl")
        xl.load_lite(small.state_dict())
        xl.eval()
        x = torch.rand(2, 3, 70, 50)
        with torch.no_grad():
            assert float((xl(x) - small(x)).abs().max()) < 1e-5
        assert 3_500_000 < count_parameters(xl) < 5_000_000
        assert xl.context.branches[0][0].out_channels == 192

    def test_context_sees_the_whole_frame(self):
        """A change in one corner of the deepest map reaches the far corner, and the
        padding beyond the image neither enters the pooling nor changes the image part."""
        from d2f_core.networks import GlobalContext

        torch.manual_seed(0)
        ctx = GlobalContext(8, hidden=4).eval()
        torch.nn.init.normal_(ctx.out.weight, std=0.5)
        x = torch.rand(1, 8, 6, 9)
        y = x.clone()
        y[..., 0, 0] += 5.0
        with torch.no_grad():
            assert float((ctx(x) - ctx(y))[..., -1, -1].abs().max()) > 1e-3
            padded = torch.cat([x, torch.full((1, 8, 2, 9), 100.0)], dim=2)
            assert torch.allclose(ctx(padded, (6, 9))[..., :6, :], ctx(x), atol=1e-6)

    def test_normalisation_buffers_not_saved(self):
        assert "mean" not in DefocusNet("lite").state_dict()

    def test_bad_input(self):
        net = DefocusNet("lite")
        with pytest.raises(ValueError, match="image"):
            net(torch.rand(1, 1, 32, 32))
        with pytest.raises(TypeError, match="image"):
            net([1, 2, 3])
        with pytest.raises(ValueError, match="variant"):
            DefocusNet("vgg")


class TestLoadImagenet:
    def test_torchvision_style_file_loads(self, resnext, tmp_path):
        torch.manual_seed(1)
        state = {
            f"module.{k}": torch.randn_like(v) if v.is_floating_point() else v
            for k, v in resnext.encoder.state_dict().items()
        }
        state["module.fc.weight"] = torch.zeros(1000, 2048)
        path = tmp_path / "resnext.pth"
        torch.save({"state_dict": state}, path)
        resnext.load_imagenet(path)
        got = resnext.encoder.state_dict()["layer3.2.conv2.weight"]
        assert torch.equal(got, state["module.layer3.2.conv2.weight"])

    def test_missing_file(self, resnext, tmp_path):
        with pytest.raises(FileNotFoundError, match="nothere.pth"):
            resnext.load_imagenet(tmp_path / "nothere.pth")

    def test_corrupt_file(self, resnext, tmp_path):
        path = tmp_path / "bad.pth"
        path.write_bytes(b"not a torch file")
        with pytest.raises(ValueError, match="cannot read"):
            resnext.load_imagenet(path)

    def test_wrong_architecture(self, resnext, tmp_path):
        path = tmp_path / "lite.pth"
        torch.save(DefocusNet("lite").encoder.state_dict(), path)
        with pytest.raises(ValueError, match="not a ResNeXt50"):
            resnext.load_imagenet(path)

    def test_wrong_shape(self, resnext, tmp_path):
        state = dict(resnext.encoder.state_dict())
        state["conv1.weight"] = torch.zeros(64, 3, 3, 3)
        path = tmp_path / "shape.pth"
        torch.save(state, path)
        with pytest.raises(ValueError, match="shape mismatch"):
            resnext.load_imagenet(path)

    def test_lite_has_no_imagenet_loader(self, tmp_path):
        with pytest.raises(ValueError, match="resnext50"):
            DefocusNet("lite").load_imagenet(tmp_path / "x.pth")


class TestRadianceNet:
    def test_shape_range_and_per_pixel(self):
        torch.manual_seed(0)
        net = RadianceNet().eval()
        x = torch.rand(1, 3, 8, 9)
        with torch.no_grad():
            out = net(x)
            # 1x1 convolutions: permuting pixels permutes the output the same way
            perm = torch.randperm(72)
            shuffled = x.flatten(2)[..., perm].reshape(1, 3, 8, 9)
            out_shuffled = net(shuffled)
        assert out.shape == (1, 1, 8, 9)
        assert float(out.min()) > 0.0 and float(out.max()) < 1.0
        assert torch.allclose(out.flatten(2)[..., perm].reshape(1, 1, 8, 9), out_shuffled)

    def test_parameter_count(self):
        # 3*16+16 + 16*16+16 + 16*1+1
        assert count_parameters(RadianceNet()) == 353


class TestFusionNet:
    def test_paper_parameter_count(self):
        # conv3x3 2->64, 64->16, 16->16, 16->1 with biases
        assert count_parameters(FusionNet("paper")) == 1216 + 9232 + 2320 + 145

    def test_lite_is_much_smaller(self):
        assert count_parameters(FusionNet("lite")) * 10 < count_parameters(FusionNet("paper"))

    @pytest.mark.parametrize("variant", ["paper", "lite"])
    def test_shape_range(self, variant):
        torch.manual_seed(0)
        net = FusionNet(variant).eval()
        with torch.no_grad():
            out = net(torch.rand(2, 1, 20, 30), torch.rand(2, 1, 20, 30))
        assert out.shape == (2, 1, 20, 30)
        assert 0.0 <= float(out.min()) <= float(out.max()) <= 1.0

    @pytest.mark.parametrize("variant", ["paper", "lite"])
    def test_halo_is_receptive_field(self, variant):
        torch.manual_seed(0)
        net = FusionNet(variant).eval()
        a, g = torch.rand(1, 1, 31, 31), torch.rand(1, 1, 31, 31)
        b = a.clone()
        b[..., 15, 15] += 0.5
        with torch.no_grad():
            diff = (net(a, g) - net(b, g)).abs()[0, 0]
        rows = torch.nonzero(diff.amax(dim=1) > 0).flatten()
        assert int(rows.max() - rows.min()) // 2 == net.halo

    def test_bad_input(self):
        net = FusionNet("lite")
        with pytest.raises(ValueError, match="gray"):
            net(torch.rand(1, 1, 4, 4), torch.rand(1, 1, 4, 5))
        with pytest.raises(ValueError, match="focus"):
            net(torch.rand(1, 2, 4, 4), torch.rand(1, 2, 4, 4))


def test_registries_and_builders():
    assert set(DEFOCUS_NETS) == {
        "lite",
        "lite-ctx",
        "lite-wide",
        "lite-xl",
        "lite-ctx-scene",
        "resnext50",
    }
    assert set(FUSION_NETS) == {"paper", "lite"}
    assert set(RADIANCE_NETS) == {"paper"}
    assert isinstance(build_defocus_net("lite"), DefocusNet)
    assert isinstance(build_radiance_net(), RadianceNet)
    assert build_fusion_net("paper").variant == "paper"
    with pytest.raises(ValueError, match="unknown fusion variant"):
        build_fusion_net("huge")


def test_rgb_to_gray_known_values():
    x = torch.tensor([1.0, 0.0, 0.0]).view(1, 3, 1, 1)
    assert float(rgb_to_gray(x)) == pytest.approx(0.299)
    assert float(rgb_to_gray(torch.ones(1, 3, 2, 2)).mean()) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        rgb_to_gray(torch.ones(1, 1, 2, 2))
