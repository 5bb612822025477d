"""The renderer's output, bit for bit, on a fixed set of scenes.

The SHA-256 of each output tensor's bytes, one torch thread; a change meant to move code
without changing it must leave every hash as it is. They were recorded on the renderer as it
stood before the package was restructured (commit c5c5045) and changed on purpose since: by the
"blend" layer placement made the default (every case but the paper order's), by the weight
of a lone saturated spot with no radiance map (every case but the gradients', which give one),
and by that weight with a radiance map too (the gradients').
The scenes cover the paths a render can take: a small and a medium frame in depth and paper
order, the direct convolution with a polygon aperture, the ``behind`` outputs, the 12 MP tiled
path, float64 and the gradients.

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
    "384x576": ["1aa9710283c9bb77a6bdb6af54c8604d77e3129141cd46f06c2c0399dbc2b51f"],
    "384x576 paper order": ["119d96d9775ead17e9287f6cc6b2c8862a60c33e17db72b858820a25f9964bde"],
    "384x576 direct hexagon": ["6dc210f3f00cbd9236b3f036ef6710910dd4b81fb54603bb841f4d822431ddd9"],
    "384x576 behind": [
        "cc49cc7d536640e998c292b3c1421ab663337e2ec5c1d8f64aba2aea94ba8b9f",
        "2b857ffa3179c83c69fca85f8206a1010a474f38b9fff740502799953a7c3d0c",
        "b02b9dead74b6fff30c5699f645c54c86422a1e501a909d3ecf4ac15fa456f0a",
    ],
    "1024x1536": ["83371df43b55c9b7f8f60691c2623ba027c5c9270301c5edca823e7a5e5840b5"],
    "12 MP tiled": ["376bdb538c79a6a2c6ae779f2cf5ffc8168f478fded5585edc97875e0bfa65b6"],
    "float64": ["dd55af69caf3403995436e5501428b513b817917f66a49a8180815ef9530933e"],
    "gradient": [
        "65164be4f32f9d57bd0a3615249169af0d674d8977e2eecca73585692e340494",
        "034f3ae026911389ad66d9076c40b1ec18417cf085ab225914941cd61134b195",
        "07e67f6dbcaf0e9a65b1eb471f5794ec2b2256b9ed8fb0599e0c41839d7d5a2a",
        "04f4425d31bce6dc371204e74639ac9db6831c93362cb088ca1b2cf5e4424f4a",
    ],
    "render_bokeh": ["8941a950b55d73d3ea0da36ba38dcfaedbc1cd72d65cfcf62b9cfdb2118064a2"],
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
