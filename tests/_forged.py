"""Requests that no page sends, made to the real app server over raw HTTP (Gradio's
``/gradio_api/call/<name>`` protocol and its upload route): the helpers of the forged-request
tests."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path


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
