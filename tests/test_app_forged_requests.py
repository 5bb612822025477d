"""Forged and malformed requests to the real app server get a clear error and one log line.

``python -m app`` is started as the other app tests start it, and requests that no page
sends are made over raw HTTP (Gradio's ``/gradio_api/call/<name>`` protocol): file paths
that were never uploaded (missing, path traversal), a path inside the server's cache that
Gradio never stored, values of the wrong type, too few inputs, a render in a session
with no photo, an event that does not exist. Each caller must get an error naming the
reason; the server log must hold exactly one line per refused request, naming the reason,
and no traceback. A real upload still works afterwards.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

KIND = "disparity (bright = near)"
#: The inputs of /load after the photo and the depth map (depth_kind ... blur_on): focus
#: 0.5 (near 0, far 1), f/2.8.
REST = [KIND, 0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", "auto", "", True]
#: The inputs of the renders: focus ... blur_on, the focal range, and the page's photo id
#: ("": none named, as from an API client).
RENDER = [0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", True, 0.0, ""]


def file_data(path: str, name: str = "photo.jpg") -> dict:
    return {"path": path, "orig_name": name, "meta": {"_type": "gradio.FileData"}}


def post(url: str, body: dict) -> tuple[int, dict]:
    req = urllib.request.Request(
        url, json.dumps(body).encode(), headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.load(r)
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read() or b"{}")


def call(server_url: str, api: str, data: list, session_hash: str = "forged") -> tuple[str, dict]:
    """One event through ``/gradio_api/call/<api>``: ``(sse event, its data)``, where the
    event is ``complete`` or ``error``; a request refused before the queue gives
    ``("http <status>", body)``."""
    status, body = post(
        f"{server_url}/gradio_api/call/{api}", {"data": data, "session_hash": session_hash}
    )
    if status != 200:
        return f"http {status}", body
    url = f"{server_url}/gradio_api/call/{api}/{body['event_id']}"
    with urllib.request.urlopen(url, timeout=120) as r:
        stream = r.read().decode()
    event = data_line = None
    for line in stream.splitlines():
        if line.startswith("event:"):
            event = line.split(":", 1)[1].strip()
        elif line.startswith("data:") and event in ("complete", "error"):
            data_line = line.split(":", 1)[1].strip()
    assert event in ("complete", "error"), stream
    return event, json.loads(data_line) if data_line else {}


def upload(server_url: str, path: Path) -> str:
    """Upload a file as the page does; return its path on the server."""
    boundary = "d2f-forged-requests"
    body = (
        (
            f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="{path.name}"'
            f"\r\nContent-Type: application/octet-stream\r\n\r\n"
        ).encode()
        + path.read_bytes()
        + f"\r\n--{boundary}--\r\n".encode()
    )
    req = urllib.request.Request(
        f"{server_url}/gradio_api/upload",
        body,
        headers={"Content-Type": f"multipart/form-data; boundary={boundary}"},
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.load(r)[0]


def test_forged_requests_get_one_log_line(app_server, gradio_env, two_plane_scene):
    server = app_server()
    url = server.url
    cache = gradio_env["GRADIO_TEMP_DIR"]
    photo = upload(url, two_plane_scene.photo)
    assert Path(photo).is_relative_to(cache)

    # (api, inputs, what the caller and the one log line must both name)
    cases = [
        ("load", [file_data("/nonexistent/x.jpg"), None, *REST], "/nonexistent/x.jpg"),
        ("load", [file_data("../../../../../../etc/passwd"), None, *REST], "/etc/passwd"),
        ("load", [file_data(photo), file_data("/etc/shadow", "d.png"), *REST], "/etc/shadow"),
        ("load", [file_data(f"{cache}/gone.jpg", "gone.jpg"), None, *REST], "not an upload"),
        ("load", ["/etc/hostname", None, *REST], "(got str)"),
        ("load", [file_data(photo)], "needed: 15, got: 1"),
        ("load", [file_data(photo), None, KIND, "near", *REST[2:]], "focus='near'"),
        ("load", [file_data(photo), None, *REST[:7], 3, *REST[8:]], "Unknown view 3"),
        ("render_focus", ["x", *RENDER[1:]], "Expected a float"),
        ("view", ["Bogus"], "'Bogus'"),
        ("render", RENDER, "no photo is loaded"),  # a session that never loaded one
        ("no_such_event", [], "no_such_event"),
    ]
    for api, data, reason in cases:
        event, answer = call(url, api, data)
        assert event in ("error", "http 404"), (api, reason, event, answer)
        message = answer.get("error") or ""
        assert reason in message, (api, reason, answer)
        assert "Traceback" not in message

    # an event index that does not exist, through the queue as the page sends events
    status, answer = post(
        f"{url}/gradio_api/queue/join", {"data": [], "fn_index": 9999, "session_hash": "forged"}
    )
    assert status == 404 and "function index 9999" in answer["error"]

    # the server still serves a real upload, in a session of its own
    event, answer = call(url, "load", [file_data(photo, "scene.png"), None, *REST], "honest")
    assert event == "complete", answer
    assert any("full render" in item for item in answer if isinstance(item, str)), answer

    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
    refused = [line for line in log.splitlines() if "refused" in line]
    assert len(refused) == len(cases) + 1, "\n".join(refused)
    for _, _, reason in cases:
        assert sum(reason in line for line in refused) == 1, (reason, refused)
    assert sum("function index 9999" in line for line in refused) == 1
