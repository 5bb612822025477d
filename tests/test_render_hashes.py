"""The renderer's output, bit for bit, on a fixed set of scenes.

The SHA-256 of each output tensor's bytes was recorded on the renderer as it stood before the
package was restructured (commit c5c5045, one torch thread); a change meant to move code
without changing it must leave every hash as it is. The scenes cover the paths a render can
take: a small and a medium frame in depth and paper order, the direct convolution with a
polygon aperture, the ``behind`` outputs, the 12 MP tiled path, float64 and the gradients.

The cases run in a child process with ``MKL_CBWR=COMPATIBLE``: Intel's MKL, which torch uses
for its matrix products, otherwise picks its code path by the CPU, and on a CPU with AVX-512
three of the cases (the medium frame, float64 and the gradients) came out a few bits apart from
the hashes below. The compatible path gives the same bits on every x86 CPU.

Run ``MKL_CBWR=COMPATIBLE python tests/test_render_hashes.py`` to print the hashes of the code
as it is now.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from d2f_core import render_bokeh
from d2f_core.rendering import render


def _scene(height: int, width: int, seed: int, dtype=torch.float32):
    """A seeded photo with saturated highlights and a smooth disparity with a near box."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, height // 16 + 2, width // 16 + 2, generator=g)
    image = F.interpolate(coarse, size=(height, width), mode="bilinear", align_corners=False)
    image = (image + 0.15 * torch.rand(1, 3, height, width, generator=g)).clamp(0, 1)
    spots = torch.rand(1, 1, height, width, generator=g) > 0.998
    image = torch.where(spots, torch.ones_like(image), image)  # highlights for the HDR boost
    ramp = torch.linspace(0.1, 0.7, height).view(1, 1, height, 1).expand(1, 1, height, width)
    wobble = F.interpolate(
        torch.rand(1, 1, 6, 8, generator=g), size=(height, width), mode="bilinear"
    )
    disparity = (ramp + 0.2 * wobble).clone()
    disparity[..., height // 3 : 2 * height // 3, width // 4 : width // 2] = 0.95  # near box
    return image.to(dtype).contiguous(), disparity.clamp(0, 1).to(dtype).contiguous()


def _sha(t: torch.Tensor | np.ndarray) -> str:
    a = t.detach().contiguous().numpy() if isinstance(t, torch.Tensor) else np.ascontiguousarray(t)
    return hashlib.sha256(a.tobytes()).hexdigest()


def _small(**options) -> list[str]:
    image, disparity = _scene(384, 576, 0)
    out = render(image, disparity, 0.45, 24.0, **options)
    return [_sha(t) for t in (out if isinstance(out, tuple) else (out,))]


def _medium() -> list[str]:
    image, disparity = _scene(1024, 1536, 1)
    return [_sha(render(image, disparity, 0.3, 40.0))]


def _tiled() -> list[str]:
    # 12 MP takes the tiled path (above 1.4 MP, fft, no gradients); a small blur and few
    # layers keep it to a few seconds
    image, disparity = _scene(3000, 4000, 2)
    return [_sha(render(image, disparity, 0.5, 10.0, num_layers=4, quality="fast"))]


def _float64() -> list[str]:
    image, disparity = _scene(96, 128, 3, torch.float64)
    return [_sha(render(image, disparity, 0.4, 12.0))]


def _gradient() -> list[str]:
    image, disparity = _scene(64, 96, 4, torch.float64)
    image.requires_grad_(True)
    disparity.requires_grad_(True)
    radiance = torch.full_like(disparity[:, :1], 1.5).requires_grad_(True)
    out = render(image, disparity, 0.4, 10.0, radiance=radiance)
    weights = torch.linspace(0, 1, out.numel(), dtype=out.dtype).view_as(out)
    (out * weights).sum().backward()
    return [_sha(t) for t in (out, image.grad, disparity.grad, radiance.grad)]


def _numpy() -> list[str]:
    image, disparity = _scene(120, 160, 5)
    photo = image[0].permute(1, 2, 0).numpy()
    return [_sha(render_bokeh(photo, disparity[0, 0].numpy(), 0.6, 16.0))]


CASES = {
    "384x576": lambda: _small(),
    "384x576 paper order": lambda: _small(order="paper"),
    "384x576 direct hexagon": lambda: _small(method="direct", kernel="hard", blades=6),
    "384x576 behind": lambda: _small(behind=True, front_size=4.0),
    "1024x1536": _medium,
    "12 MP tiled": _tiled,
    "float64": _float64,
    "gradient": _gradient,
    "render_bokeh": _numpy,
}

EXPECTED: dict[str, list[str]] = {
    "384x576": ["f85a3a23fb663643e48e0e263cf91843ab64ffb7912ef166775aac6a02f86574"],
    "384x576 paper order": ["b61751315dd827843ea8648c9782a9a790ad8024cfe762e99c626cf8f8415f60"],
    "384x576 direct hexagon": ["8b918b834fea97121f49fc920bcde801ae0c32ee21c4a1a3798916c3dd35d258"],
    "384x576 behind": [
        "6e8f9b40368627fb5a2dc387705c07ba6c94ae5abe5624e3608f35cb9b9169d5",
        "9360f8071c3ace12b0ae0c068a749a10186f782c6d9377d9ad068ffad7e8da2f",
        "7dfc4d240b3df6f54e95b9c5908cdb0f457945b3f336d61b2bd70162fda7668e",
    ],
    "1024x1536": ["27dbd26684c5f206f2d373257583ff127f7614f6b8f8d62d4cae99390f4d47ce"],
    "12 MP tiled": ["845cc43f4f047bca4e70728362470a08e5dc219fc5e1fa95c265fc795d272a48"],
    "float64": ["d09c213bd31ac4609d3b00c932b1907093169c0c22b2988916a9f666b117cee3"],
    "gradient": [
        "5d3a4b94ddaa789998acbe16d21ec39f3e7b5f575bf702fd5a3b037679186cd2",
        "c016dc4903e2656250176b38c06c64266194a20da37a594e615f6770ba9ba7f1",
        "3357121c82c3b29d2cb8b06fb2115ac4aad020590682a07f4ecc521ee859f94d",
        "458859f8a44f5a8a154a82ac5a4aea9b20164ad7365c58ee6e965ddfd6d8859a",
    ],
    "render_bokeh": ["cf961abbbd9bdcb4e0e37f9a88c2a358e875c8068b6d12068ff34abcf677e8bb"],
}


@pytest.fixture(scope="module")
def hashes() -> dict[str, list[str]]:
    """Every case's hashes, from a child process on MKL's compatible path, one thread."""
    env = {**os.environ, "MKL_CBWR": "COMPATIBLE", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, __file__, "--json"], env=env, capture_output=True, text=True, timeout=900
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


@pytest.mark.parametrize("name", list(CASES))
def test_render_hash_unchanged(name, hashes):
    assert hashes[name] == EXPECTED[name], name


if __name__ == "__main__":
    torch.set_num_threads(1)
    if "--json" in sys.argv[1:]:
        print(json.dumps({name: case() for name, case in CASES.items()}))
    else:
        for name, case in CASES.items():
            print(f"    {name!r}: {case()!r},")
