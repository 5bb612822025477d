"""The app under the browser latency bench: test photos written, ``python -m app`` started on a
free port with its own threads and files, and waits until it is ready and idle.
"""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

log = logging.getLogger("app.latency_bench")


REPO_ROOT = Path(__file__).resolve().parents[1]


class BenchError(RuntimeError):
    """The app or the browser did not do what the bench asked (with what it saw)."""


@dataclass
class Server:
    url: str
    process: subprocess.Popen
    log: Path

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(10)


def loadavg() -> str:
    """The first three fields of ``/proc/loadavg`` ('' where there is none)."""
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return ""


def commit() -> str:
    """The checkout's short commit, with ``+dirty`` when app/ or d2f_core/ has changes."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", "app", "d2f_core"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def write_photos(folder: Path, size: tuple[int, int], count: int) -> list[Path]:
    """``count`` JPEGs of the motorcycle at ``size = (W, H)``; photo ``i`` has its top-left
    16x16 block filled with a grey of its own, so every file is a new scene to the app."""
    from skimage import data

    left = data.stereo_motorcycle()[0]  # (500, 741, 3) uint8
    h0, w0 = left.shape[:2]
    w, h = size
    if w0 * h > h0 * w:  # wider than the asked aspect: crop the sides
        cw = round(h0 * w / h)
        left = left[:, (w0 - cw) // 2 : (w0 - cw) // 2 + cw]
    else:
        ch = round(w0 * h / w)
        left = left[(h0 - ch) // 2 : (h0 - ch) // 2 + ch]
    base = np.asarray(Image.fromarray(left).resize((w, h), Image.Resampling.LANCZOS))
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        image = base.copy()
        image[:16, :16] = (37 * i + 20) % 256
        path = folder / f"motorcycle_{w}x{h}_{i}.jpg"
        Image.fromarray(image).save(path, quality=92)
        paths.append(path)
    return paths


def app_env(temp: Path) -> dict[str, str]:
    """This process's environment for a Gradio server or client confined to ``temp`` (its
    files there), offline and without telemetry."""
    env = dict(os.environ)
    env.update(
        GRADIO_TEMP_DIR=str(temp),
        D2F_APP_MASKS=str(temp / "masks"),  # the brushes' masks, kept for the command
        GRADIO_ANALYTICS_ENABLED="False",
        HF_HUB_DISABLE_TELEMETRY="1",
        HF_HUB_OFFLINE="1",
        GRADIO_RUN_HISTORY="False",
        PYTHONUNBUFFERED="1",
    )
    return env


def free_port() -> int:
    """A localhost TCP port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(server: Server, timeout: float) -> None:
    """Poll the app's ``/gradio_api/info`` until it answers 200; :class:`BenchError` with
    the end of the server's log if it exits first or does not answer within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if server.process.poll() is not None:
            code, tail = server.process.returncode, server.log.read_text()[-4000:]
            raise BenchError(f"app exited with {code}:\n{tail}")
        try:
            with urllib.request.urlopen(f"{server.url}/gradio_api/info", timeout=2) as r:
                if r.status == 200:
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            pass
        time.sleep(0.2)
    raise BenchError(f"app not ready after {timeout:.0f} s:\n{server.log.read_text()[-4000:]}")


def start_app(
    folder: Path, threads: int, weights: str | None = None, timeout: float = 180.0
) -> Server:
    """``python -m app`` on a free port with ``threads`` torch threads, Gradio's files and the
    log in ``folder``; returns once ``/gradio_api/info`` answers."""
    port = free_port()
    temp = folder / "gradio_tmp"
    temp.mkdir(parents=True, exist_ok=True)
    env = app_env(temp)
    cmd = [sys.executable, "-m", "app", "--port", str(port), "--threads", str(threads)]
    if weights:
        cmd += ["--weights", str(weights)]
    log = folder / "app.log"
    with log.open("wb") as fh:
        proc = subprocess.Popen(cmd, cwd=REPO_ROOT, env=env, stdout=fh, stderr=fh)
    server = Server(f"http://127.0.0.1:{port}", proc, log)
    try:
        wait_ready(server, timeout)
    except BenchError:
        server.stop()
        raise
    return server


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def wait_idle(pid: int, quiet_s: float = 0.4, max_s: float = 60.0) -> None:
    """Return once process ``pid`` used under 10% of a core for ``quiet_s`` (or after
    ``max_s``, or at once where /proc is missing)."""
    try:
        deadline = time.monotonic() + max_s
        last, since = _cpu_seconds(pid), time.monotonic()
        while time.monotonic() < deadline:
            time.sleep(0.1)
            now = _cpu_seconds(pid)
            if now - last > 0.1 * (time.monotonic() - since) + 0.01:
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= quiet_s:
                return
    except (OSError, ValueError, IndexError):
        return
