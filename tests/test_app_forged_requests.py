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

from pathlib import Path

import pytest
from _forged import call, file_data, post, upload

pytestmark = pytest.mark.slow

KIND = "disparity (bright = near)"
#: The inputs of /load after the photo and the depth map (depth_kind ... blur_on): focus
#: 0.5 (near 0, far 1), f/2.8.
REST = [KIND, 0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", "auto", "", True]
#: The inputs of the renders: focus ... blur_on, the focal range, and the page's photo id
#: ("": none named, as from an API client).
RENDER = [0.5, 2.8, 0, 0.0, True, True, "Bokeh", "balanced", True, 0.0, ""]


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
