"""The defocus network's encoders (:class:`~d2f_core.networks.DefocusNet`): the paper's
ResNeXt-50 and the MobileNetV2-like lite encoder. Both return four feature maps at strides 4,
8, 16 and 32.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

__all__ = ["LiteEncoder", "ResNeXt50Encoder"]


class _Bottleneck(nn.Module):
    """ResNeXt bottleneck; attribute names follow torchvision so its weights load as-is."""

    expansion = 4

    def __init__(
        self, inplanes: int, planes: int, stride: int, groups: int, base_width: int
    ) -> None:
        super().__init__()
        width = int(planes * (base_width / 64.0)) * groups
        out = planes * self.expansion
        self.conv1 = nn.Conv2d(inplanes, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, groups=groups, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out)
        self.relu = nn.ReLU(inplace=True)
        self.downsample: nn.Module | None = None
        if stride != 1 or inplanes != out:
            self.downsample = nn.Sequential(
                nn.Conv2d(inplanes, out, 1, stride, bias=False), nn.BatchNorm2d(out)
            )

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + identity)


class ResNeXt50Encoder(nn.Module):
    """ResNeXt-50 (32x4d) backbone without the classifier.

    Parameter names match torchvision's ``resnext50_32x4d`` (minus ``fc``), so an
    ImageNet state dict loads through :meth:`DefocusNet.load_imagenet`.

    Shape: (B, 3, H, W) normalised -> [(B,256,H/4,W/4), (B,512,H/8,W/8),
    (B,1024,H/16,W/16), (B,2048,H/32,W/32)].
    """

    channels = (256, 512, 1024, 2048)

    def __init__(self, groups: int = 32, width_per_group: int = 4) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        inplanes = 64
        stages = []
        for planes, blocks, stride in ((64, 3, 1), (128, 4, 2), (256, 6, 2), (512, 3, 2)):
            layers = []
            for i in range(blocks):
                layers.append(
                    _Bottleneck(inplanes, planes, stride if i == 0 else 1, groups, width_per_group)
                )
                inplanes = planes * _Bottleneck.expansion
            stages.append(nn.Sequential(*layers))
        self.layer1, self.layer2, self.layer3, self.layer4 = stages
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
        # Zero-init the last BN of each block: every block starts as identity, which
        # keeps a randomly initialised 50-layer encoder trainable from scratch.
        for m in self.modules():
            if isinstance(m, _Bottleneck):
                nn.init.zeros_(m.bn3.weight)

    def forward(self, x: Tensor) -> list[Tensor]:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        f1 = self.layer1(x)
        f2 = self.layer2(f1)
        f3 = self.layer3(f2)
        f4 = self.layer4(f3)
        return [f1, f2, f3, f4]


class _InvertedResidual(nn.Module):
    """MobileNetV2-style block: 1x1 expand, 3x3 depthwise, 1x1 project."""

    def __init__(self, cin: int, cout: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = cin * expand
        self.use_residual = stride == 1 and cin == cout
        self.block = nn.Sequential(
            nn.Conv2d(cin, hidden, 1, bias=False),
            nn.BatchNorm2d(hidden),
            nn.ReLU6(inplace=True),
            nn.Conv2d(hidden, hidden, 3, stride, 1, groups=hidden, bias=False),
            nn.BatchNorm2d(hidden),
            nn.ReLU6(inplace=True),
            nn.Conv2d(hidden, cout, 1, bias=False),
            nn.BatchNorm2d(cout),
        )

    def forward(self, x: Tensor) -> Tensor:
        y = self.block(x)
        return x + y if self.use_residual else y


class LiteEncoder(nn.Module):
    """Small MobileNetV2-like encoder for CPU inference (about 1 M parameters).

    Shape: (B, 3, H, W) normalised -> four maps at strides 4, 8, 16, 32 with
    :attr:`channels` channels.
    """

    channels = (24, 48, 96, 192)

    def __init__(self, expand: int | Sequence[int] = 4) -> None:
        super().__init__()
        expands = (expand,) * 4 if isinstance(expand, int) else tuple(expand)
        self.stem = nn.Sequential(
            nn.Conv2d(3, 16, 3, 2, 1, bias=False), nn.BatchNorm2d(16), nn.ReLU(inplace=True)
        )
        cin = 16
        stages = []
        for cout, blocks, ex in zip(self.channels, (2, 3, 4, 3), expands, strict=True):
            layers = []
            for i in range(blocks):
                layers.append(_InvertedResidual(cin, cout, 2 if i == 0 else 1, ex))
                cin = cout
            stages.append(nn.Sequential(*layers))
        self.stages = nn.ModuleList(stages)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: Tensor) -> list[Tensor]:
        x = self.stem(x)
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        return feats
