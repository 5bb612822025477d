"""Shared pytest fixtures (generic: any test module may use them).

* ``tiny_checkpoint`` / ``tiny_model``: a small, seeded, randomly initialised D2F saved as a
  real checkpoint, so tests never depend on shipped weights.
* ``two_plane_scene`` / ``scene_factory``: a generated photo with a known near subject and
  far background, plus the matching disparity map, as files; ``sharpness`` measures a region.
* ``gradio_env``: environment for a Gradio server/client run confined to the test's tmp dir.
* ``free_port`` and ``app_server``: start ``python -m app`` on a free localhost port.
* ``chromium_path`` / ``chromium_launch_options``: Debian's Chromium for Playwright, or a
  skip with the reason.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

# Debian's Chromium and the launch flags that work with it as root
# (../shared/BROWSER_TESTING.md), shared with the app's browser latency bench
from app.latency_probe import CHROMIUM, CHROMIUM_ARGS
from app.latency_server import BenchError, Server, app_env, wait_ready
from app.latency_server import free_port as find_free_port

REPO_ROOT = Path(__file__).resolve().parent.parent


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist every worker gets its share of the cores for torch (two workers
    of two threads each on two cores spin against each other)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1") or 1)
    if workers > 1:
        import torch

        torch.set_num_threads(max(1, (os.cpu_count() or 1) // workers))


@pytest.fixture(autouse=True, scope="session")
def _masks_in_a_temporary_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The app's painted masks (``app.painting.masks_folder``) go to a temporary folder, not
    the user's cache."""
    old = os.environ.get("D2F_APP_MASKS")
    os.environ["D2F_APP_MASKS"] = str(tmp_path_factory.mktemp("masks"))
    yield
    if old is None:
        os.environ.pop("D2F_APP_MASKS", None)
    else:
        os.environ["D2F_APP_MASKS"] = old


#: Small networks and a small render pass keep model-backed tests fast on 2 cores.
TINY_CONFIG = {"network_size": 64, "max_render_side": 256}


def _torch_threads(n: int) -> Iterator[None]:
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(n)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """One torch thread: tiny tensors gain nothing from threads, and OpenMP spin-waits
    collapse on a busy machine."""
    yield from _torch_threads(1)


@pytest.fixture
def two_threads() -> Iterator[None]:
    """Two torch threads, as the benchmarks and the scene generator run."""
    yield from _torch_threads(2)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Path of a seeded random-init D2F checkpoint with :data:`TINY_CONFIG`."""
    import torch

    from d2f_core.pipeline import D2F

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("weights") / "d2f_tiny.pt"
    D2F.from_config(TINY_CONFIG).save(path)
    return path


@pytest.fixture(scope="session")
def tiny_model(tiny_checkpoint: Path):
    """The model of :func:`tiny_checkpoint`, loaded through ``D2F.from_checkpoint``."""
    from d2f_core.pipeline import D2F

    return D2F.from_checkpoint(tiny_checkpoint)


@dataclass
class TwoPlaneScene:
    """A textured near box in front of a textured far background.

    Attributes:
        photo: PNG path, ``width x height`` RGB.
        disparity: 8-bit PNG path, ``near`` inside ``box`` and ``far`` elsewhere (/255).
        box: ``(x0, y0, x1, y1)`` of the near subject in photo pixels (x1, y1 exclusive).
        near, far: disparity values in [0, 1].
        image: the photo as ``(H, W, 3)`` uint8.
    """

    photo: Path
    disparity: Path
    box: tuple[int, int, int, int]
    near: float
    far: float
    image: np.ndarray

    @property
    def near_point(self) -> tuple[int, int]:
        x0, y0, x1, y1 = self.box
        return (x0 + x1) // 2, (y0 + y1) // 2

    @property
    def far_point(self) -> tuple[int, int]:
        h, w = self.image.shape[:2]
        x0, y0, x1, y1 = self.box
        return (x1 + w) // 2, (y1 + h) // 2


def make_two_plane_scene(
    folder: Path, width: int = 320, height: int = 240, seed: int = 0, stem: str = "scene"
) -> TwoPlaneScene:
    """Write a :class:`TwoPlaneScene`: 2x2-pixel random texture, sharp by construction."""
    rng = np.random.default_rng(seed)
    cells = rng.integers(30, 226, size=(height // 2 + 1, width // 2 + 1, 3), dtype=np.uint8)
    image = cells.repeat(2, 0).repeat(2, 1)[:height, :width].copy()
    box = (width // 8, height // 4, width // 8 + width // 3, height // 4 + height // 2)
    x0, y0, x1, y1 = box
    image[y0:y1, x0:x1] = (image[y0:y1, x0:x1] * 0.6 + np.array([90, 40, 10]) * 0.4).astype(
        np.uint8
    )  # a warmer subject, so it is visible in screenshots
    near, far = 230 / 255, 26 / 255
    disp = np.full((height, width), 26, np.uint8)
    disp[y0:y1, x0:x1] = 230
    folder.mkdir(parents=True, exist_ok=True)
    photo = folder / f"{stem}.png"
    disparity = folder / f"{stem}_disparity.png"
    Image.fromarray(image).save(photo)
    Image.fromarray(disp).save(disparity)
    return TwoPlaneScene(photo, disparity, box, near, far, image)


@pytest.fixture
def two_plane_scene(tmp_path: Path) -> TwoPlaneScene:
    """A 320x240 :class:`TwoPlaneScene` in the test's tmp dir."""
    return make_two_plane_scene(tmp_path / "scene")


@pytest.fixture
def scene_factory(tmp_path: Path) -> Callable[..., TwoPlaneScene]:
    """``make(width=320, height=240, seed=0, stem="scene")`` -> a new :class:`TwoPlaneScene`."""

    def make(width: int = 320, height: int = 240, seed: int = 0, stem: str = "scene"):
        return make_two_plane_scene(tmp_path / "scenes", width, height, seed, stem)

    return make


def _sharpness(image: np.ndarray, box: tuple[int, int, int, int] | None = None) -> float:
    a = np.asarray(image, np.float32)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2)
    if box is not None:
        x0, y0, x1, y1 = box
        a = a[y0:y1, x0:x1]
    return float(np.abs(np.diff(a, axis=0)).mean() + np.abs(np.diff(a, axis=1)).mean())


@pytest.fixture
def sharpness() -> Callable[..., float]:
    """``sharpness(image, box=None)``: mean absolute x+y gradient of the grey image in box."""
    return _sharpness


@pytest.fixture
def gradio_env(tmp_path: Path) -> dict[str, str]:
    """Environment for a Gradio server or client confined to this test (no telemetry)."""
    temp = tmp_path / "gradio_tmp"
    temp.mkdir()
    return app_env(temp)


@pytest.fixture
def free_port() -> int:
    return find_free_port()


@pytest.fixture
def app_server(
    tmp_path: Path, gradio_env: dict[str, str], tiny_checkpoint: Path
) -> Iterator[Callable[..., Server]]:
    """Factory: ``start(*extra_args, env=None)`` runs ``python -m app`` on a free port.

    The server uses :func:`tiny_checkpoint` and this test's ``gradio_env``; it is stopped
    (SIGTERM, then SIGKILL) at teardown. Its output goes to ``tmp_path/app_<n>.log``.
    """
    started: list[Server] = []

    def start(*extra: str, env: dict[str, str] | None = None, timeout: float = 60) -> Server:
        port = find_free_port()
        log = tmp_path / f"app_{len(started)}.log"
        cmd = [sys.executable, "-m", "app", "--port", str(port)]
        cmd += ["--weights", str(tiny_checkpoint), *extra]
        with log.open("wb") as fh:
            proc = subprocess.Popen(
                cmd, cwd=REPO_ROOT, env={**gradio_env, **(env or {})}, stdout=fh, stderr=fh
            )
        server = Server(f"http://127.0.0.1:{port}", proc, log)
        started.append(server)
        try:
            wait_ready(server, timeout)
        except BenchError as err:
            pytest.fail(str(err))
        return server

    yield start
    for server in started:
        server.stop()


@pytest.fixture(scope="session")
def chromium_path() -> str:
    """Debian's Chromium binary for Playwright; skips when it (or Playwright) is missing."""
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    path = shutil.which("chromium") if not Path(CHROMIUM).exists() else CHROMIUM
    if not path:
        pytest.skip(
            f"{CHROMIUM} not found: install Debian's chromium (apt-get install -y chromium); "
            "never `playwright install`"
        )
    return path


@pytest.fixture(scope="session")
def chromium_launch_options(chromium_path: str) -> dict:
    """Keyword arguments for ``playwright.chromium.launch`` (headless Debian Chromium)."""
    return {"executable_path": chromium_path, "headless": True, "args": list(CHROMIUM_ARGS)}
