"""Sixteen concurrent sessions against the running app through ``gradio_client``.

Each session uploads its own generated photo (a different size and texture) with its
disparity map, moves the focus and aperture sliders (previews and full renders) and finally
renders with the blur switched off, which must give back exactly its own pixels: any
cross-talk between sessions would show up as a wrong size or wrong content. A quarter of
the sessions first upload a file that is not an image and must get a clean error without
disturbing anyone. The server's RSS growth over the run is checked against a bound.
"""

from __future__ import annotations

import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytestmark = pytest.mark.slow

SESSIONS = 16
#: The /load inputs of the Depth source control: automatic choice, no hub model.
SOURCE = {"depth_source": "auto", "hub_model": ""}
#: The aperture slider's widest: f/1 gives K = 11-19 px on the 160-280 px photos of the
#: 16-session test and 55.6 px on the 800x600 ones (d2f_core.lens.blur_px).
F1 = 1.0
#: RSS growth allowed while 16 sessions open and move sliders. Measured on the 2-core
#: machine: 170-220 MB (16 scenes and session states of ~4 MB each, malloc arenas of the
#: worker threads, the renderer's kernel-spectrum cache for 16 different image sizes).
RSS_GROWTH_BOUND_MB = 400
#: RSS growth allowed when the same 16 sessions move their sliders once more; measured
#: 30-45 MB. Memory that grows with the number of calls (e.g. keeping every rendered
#: frame) shows up here; small per-call leaks would need a longer run.
MOVE_GROWTH_BOUND_MB = 100


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


@contextmanager
def peak_rss(pid: int, start: float):
    """While the block runs, the RSS of ``pid`` is sampled every 50 ms; yields ``[peak]``,
    the highest seen in MB (at least ``start``), updated in place."""
    peak = [start]
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            peak[0] = max(peak[0], rss_mb(pid))
            time.sleep(0.05)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        yield peak
    finally:
        stop.set()
        sampler.join()


@pytest.fixture
def client_env(gradio_env, monkeypatch):
    """This process as a gradio_client confined to the test's folder: Gradio's environment,
    and Python's temp dir, where gradio_client makes a folder for every file it downloads
    and leaves it behind (some 300 empty folders in /tmp per run of these tests)."""
    for key in ("GRADIO_TEMP_DIR", "GRADIO_ANALYTICS_ENABLED", "HF_HUB_DISABLE_TELEMETRY"):
        monkeypatch.setenv(key, gradio_env[key])
    monkeypatch.setattr(tempfile, "tempdir", gradio_env["GRADIO_TEMP_DIR"])
    return gradio_env


def test_sixteen_sessions(app_server, scene_factory, client_env, tmp_path):
    from gradio_client import Client, handle_file
    from gradio_client.exceptions import AppError

    # a small scene cache (about 4 of these scenes), so that eviction happens under load
    # 16 sessions and the warm-up one: over the default cap of 16 live sessions
    server = app_server(
        env={"D2F_APP_CONCURRENCY": "4", "D2F_APP_CACHE_MB": "8", "D2F_APP_MAX_SESSIONS": "20"},
        timeout=180,
    )
    scenes = [
        scene_factory(width=160 + 8 * i, height=120 + 6 * i, seed=i, stem=f"s{i:02d}")
        for i in range(SESSIONS)
    ]
    bad = tmp_path / "not_a_photo.png"
    bad.write_bytes(b"\x00\x01 definitely not a PNG " * 50)
    kind = "disparity (bright = near)"
    options = (0, 0.0, True, True, "Bokeh", "balanced")  # blades ... fusion, view, quality

    def new_client(name: str) -> Client:
        folder = str(tmp_path / f"dl_{name}")
        return Client(server.url, verbose=False, analytics_enabled=False, download_files=folder)

    # warm the server (first renders pay one-off costs), then take the RSS baseline
    warm = new_client("warm")
    warm.predict(handle_file(str(scenes[0].photo)), None, kind, 0.5, F1, *options,
                 api_name="/load", **SOURCE)  # fmt: skip
    rss_before = rss_mb(server.process.pid)

    def check_size(update, size):
        assert Image.open(update["value"]).size == size

    def move_sliders(client: Client, i: int, step: int) -> None:
        """Previews while 'dragging' focus, a full render on 'release', then no blur."""
        from app.settings import blur_px

        scene = scenes[i]
        size = scene.image.shape[1], scene.image.shape[0]
        for f in (0.7, 0.05):  # the focus slider reads near (0) to far (1)
            out = client.predict(f + 0.01 * step, F1, *options, api_name="/preview_focus")
            check_size(out[0], size)
            assert "preview" in out[3]
        n = round(F1 + 0.1 * step, 1)
        out = client.predict(0.05, n, *options, api_name="/render_blur")
        check_size(out[0], size)
        k = blur_px(n, max(size))
        assert (
            f"focus 0.050 (0 = near, 1 = far; disparity 0.950) | f/{n:g}, blur {k:g} px | full"
            in out[3]
        )
        # no blur gives the photo back unchanged: the content check for cross-talk, on
        # the PNG download (the browser's picture is a JPEG); the switch is the last input
        out = client.predict(0.05, n, *options, False, api_name="/render_blur")
        assert Image.open(out[0]["value"]).format == "JPEG"
        download = client.predict("PNG", api_name="/download")
        download = download["value"] if isinstance(download, dict) else download
        final = np.asarray(Image.open(download).convert("RGB"))
        np.testing.assert_array_equal(final, scene.image, err_msg=f"session {i}")

    def open_session(i: int) -> Client:
        scene = scenes[i]
        client = new_client(f"{i:02d}")
        if i % 4 == 0:
            with pytest.raises(AppError, match="not_a_photo.png"):
                client.predict(handle_file(str(bad)), None, kind, 0.5, F1, *options,
                               api_name="/load", **SOURCE)  # fmt: skip
        out = client.predict(handle_file(str(scene.photo)), handle_file(str(scene.disparity)),
                             kind, 0.5, F1, *options, api_name="/load", **SOURCE)  # fmt: skip
        check_size(out[1], (scene.image.shape[1], scene.image.shape[0]))
        assert "your disparity map" in out[4]
        move_sliders(client, i, 0)
        return client

    with peak_rss(server.process.pid, rss_before) as peak:
        t0 = time.perf_counter()
        with ThreadPoolExecutor(SESSIONS) as pool:
            clients = list(pool.map(open_session, range(SESSIONS)))
        first = time.perf_counter() - t0
        rss_first = rss_mb(server.process.pid)
        t0 = time.perf_counter()
        with ThreadPoolExecutor(SESSIONS) as pool:
            list(pool.map(lambda i: move_sliders(clients[i], i, 1), range(SESSIONS)))
        second = time.perf_counter() - t0
    rss_second = rss_mb(server.process.pid)

    print(
        f"16 sessions: open + move {first:.1f} s, move again {second:.1f} s; RSS "
        f"{rss_before:.0f} -> {rss_first:.0f} -> {rss_second:.0f} MB, peak {peak[0]:.0f} MB"
    )
    assert peak[0] - rss_before < RSS_GROWTH_BOUND_MB
    # the same sessions moving sliders again must not keep growing memory
    assert rss_second - rss_first < MOVE_GROWTH_BOUND_MB
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]


#: test_forty_sessions_bounded_memory's server: live sessions at most, scene cache MB; its
#: sessions open in waves of WAVE at once. Sessions are not closed for being idle during the
#: run (tests/test_app_handlers.py::TestSessions checks that on its own): on a loaded
#: 2-core machine a session's next event can wait in the queue for tens of seconds.
MAX_LIVE, CACHE_MB, WAVE, IDLE_S = 8, 96, 6, 3600
#: RSS growth allowed at the peak of the run: the scene cache (96 MB), eight live sessions'
#: display pictures (about 3 MB each at 800x600), the scenes of the renders in flight and
#: malloc's arenas. Measured on the loaded 2-core machine: 323 MB. Before sessions were
#: bounded every session kept its scene, pictures and full frame for an hour: 929 MB.
FORTY_PEAK_BOUND_MB = 550
#: RSS growth allowed once every client has gone: the scene cache and what malloc keeps.
#: Measured: 124 MB; before: 924 MB (nothing was given back).
FORTY_AFTER_BOUND_MB = 300


def test_forty_sessions_bounded_memory(app_server, scene_factory, client_env, tmp_path):
    """44 API sessions, each with its own 800x600 photo, open in waves of six, and their
    clients go away with the photo open (the client's heartbeat ends, as when a tab is
    closed): the app closes their sessions and files at once. Past the cap of eight live
    sessions an upload closes the least recently used photo, whose user gets a message. The
    server's memory stays under a bound; an upload past the size limit is refused. (Before,
    every session stayed for an hour.)"""
    from gradio_client import Client, handle_file
    from gradio_client.exceptions import AppError

    work = tmp_path / "server_tmp"
    work.mkdir()
    server = app_server(
        env={
            "D2F_APP_CACHE_MB": str(CACHE_MB),
            "D2F_APP_MAX_SESSIONS": str(MAX_LIVE),
            "D2F_APP_SESSION_IDLE_S": str(IDLE_S),
            "D2F_APP_MAX_UPLOAD_MB": "8",
            "TMPDIR": str(work),  # the app's per-session folders go here
        },
        timeout=180,  # a start on a loaded 2-core machine
    )
    options = (0, 0.0, True, True, "Bokeh", "balanced")
    kind = "disparity (bright = near)"
    size = (800, 600)

    def new_client(name: str) -> Client:
        folder = str(tmp_path / f"dl_{name}")
        return Client(server.url, verbose=False, analytics_enabled=False, download_files=folder)

    def session_folders() -> list[Path]:
        return [p for root in work.glob("d2f-app-*") for p in root.iterdir()]

    warm = new_client("warm")
    first = scene_factory(*size, seed=100, stem="warm")
    warm.predict(handle_file(str(first.photo)), None, kind, 0.5, F1, *options,
                 api_name="/load", **SOURCE)  # fmt: skip
    # a file over the upload limit is refused before the app sees it
    big = tmp_path / "big.png"
    big.write_bytes(b"\x89PNG" + bytes(9 << 20))
    with pytest.raises((AppError, ValueError), match="(?i)size|large|exceed"):
        warm.predict(handle_file(str(big)), None, kind, 0.5, F1, *options,
                     api_name="/load", **SOURCE)  # fmt: skip
    warm.predict(None, None, kind, 0.5, F1, *options, api_name="/load", **SOURCE)  # closed
    assert session_folders() == []
    rss_before = rss_mb(server.process.pid)

    def open_session(i: int) -> Client:
        scene = scene_factory(*size, seed=i, stem=f"p{i:02d}")
        client = new_client(f"{i:02d}")
        out = client.predict(handle_file(str(scene.photo)), None, kind, 0.5, F1, *options,
                             api_name="/load", **SOURCE)  # fmt: skip
        assert Image.open(out[1]["value"]).size == size  # fetched: no 403
        client.predict(0.5, F1, *options, False, api_name="/render_blur")  # no blur
        download = client.predict("PNG", api_name="/download")
        download = download["value"] if isinstance(download, dict) else download
        final = np.asarray(Image.open(download).convert("RGB"))  # the PNG: exact pixels
        np.testing.assert_array_equal(final, scene.image, err_msg=f"session {i}")
        return client

    def leave(clients: list[Client]) -> None:
        for client in clients:
            client.close()  # stops its heartbeat: Gradio runs the page's unload event
        deadline = time.monotonic() + 60
        while session_folders() and time.monotonic() < deadline:
            time.sleep(0.25)
        assert session_folders() == []

    refused = ""
    with peak_rss(server.process.pid, rss_before) as peak:
        for wave in range(7):
            with ThreadPoolExecutor(WAVE) as pool:
                clients = list(pool.map(open_session, range(WAVE * wave, WAVE * wave + WAVE)))
            assert len(session_folders()) == WAVE
            if wave == 0:
                # six live sessions and the cap at eight: two more open, and the next closes
                # the least recently used one of the first six, whose user is told so
                clients += [open_session(42), open_session(43)]
                clients.append(open_session(44))
                assert len(session_folders()) == MAX_LIVE
                told = []
                for client in clients[:WAVE]:
                    try:
                        client.predict(0.4, F1, *options, False, api_name="/render_blur")
                    except AppError as err:
                        told.append(str(err))
                assert len(told) == 1 and "closed to make room" in told[0], told
                refused = told[0]
            leave(clients)
    rss_after = rss_mb(server.process.pid)
    print(
        f"44 sessions ({size[0]}x{size[1]}, cap {MAX_LIVE}, cache {CACHE_MB} MB): RSS "
        f"{rss_before:.0f} -> peak {peak[0]:.0f} -> {rss_after:.0f} MB; closed to make room: "
        f"{refused!r}"
    )
    assert peak[0] - rss_before < FORTY_PEAK_BOUND_MB
    assert rss_after - rss_before < FORTY_AFTER_BOUND_MB
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
