"""``d2f-app``'s start-up lines: its own address, no advice about options it does not have."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_start_up_names_the_address_and_no_share_option(free_port, gradio_env, tiny_checkpoint):
    port = free_port
    env = dict(gradio_env, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "app", "--port", str(port), "--weights", str(tiny_checkpoint)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )  # fmt: skip
    lines: list[str] = []
    try:
        # a reader thread: the wait for the address has a deadline even when the server
        # prints nothing
        got: queue.Queue[str] = queue.Queue()
        threading.Thread(target=lambda: [got.put(x) for x in proc.stdout], daemon=True).start()
        deadline = time.monotonic() + 60
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = got.get(timeout=left)
            except queue.Empty:
                break
            lines.append(line)
            if "serving at" in line:
                break
        assert any(f"serving at http://127.0.0.1:{port}/" in line for line in lines), lines
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    time.sleep(0.5)  # the reader thread takes the last lines
    while not got.empty():
        lines.append(got.get())
    text = "".join(lines)
    assert "share=True" not in text, text
    assert "Traceback" not in text, text
