"""A client cannot make the real app server open a file that was not uploaded to it.

The photo and depth inputs of ``/load`` are taken raw, so Gradio does not check a payload
that carries no ``meta``. A forged ``{"path": ...}`` naming a photo elsewhere on the server,
a folder, a missing path or a device is sent raw over HTTP and through ``gradio_client``;
each must be refused with the same message, which names no path, and no pixel of the file
may come back (in the event's outputs or through ``/download``). Uploads and the bundled
samples still load.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from test_app_forged_requests import REST, call, upload

from app.uploads import NOT_AN_UPLOAD, UploadGate

pytestmark = pytest.mark.slow


@pytest.fixture
def secret(tmp_path: Path) -> Path:
    """A photo on the server outside Gradio's cache, with pixels no other file has."""
    rng = np.random.default_rng(7)
    path = tmp_path / "secret" / "private.png"
    path.parent.mkdir()
    Image.fromarray(rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)).save(path)
    return path


def forged(server_tmp: Path, secret: Path, cache: str) -> dict[str, str]:
    """Paths a client names without uploading them: what each one is on the server."""
    planted = Path(cache) / ("0" * 64) / "planted.png"  # in the cache, not stored by Gradio
    planted.parent.mkdir(parents=True, exist_ok=True)
    planted.write_bytes(secret.read_bytes())
    link = Path(cache) / "link.png"  # in the cache, pointing out of it
    link.symlink_to(secret)
    return {
        "an image elsewhere": str(secret),
        "a folder": str(secret.parent),
        "a missing path": str(secret.parent / "missing.png"),
        "a device": "/dev/zero",
        "a file planted in the cache": str(planted),
        "a link in the cache": str(link),
        "a relative path": "../" * 12 + str(secret).lstrip("/"),
    }


def _no_pixels_of(secret: Path, answer) -> None:
    """No output of the event is a picture of ``secret``."""
    text = json.dumps(answer)
    assert str(secret) not in text and secret.name not in text
    for item in answer if isinstance(answer, list) else [answer]:
        if isinstance(item, dict) and item.get("path"):
            with Image.open(item["path"]) as im:
                assert im.size != (128, 96), item


def test_forged_paths_are_refused_alike(app_server, gradio_env, secret, two_plane_scene):
    server = app_server()
    cache = gradio_env["GRADIO_TEMP_DIR"]
    cases = forged(Path(cache), secret, cache)
    messages = {}
    for what, path in cases.items():
        for name, payload in (("photo", [{"path": path}, None]), ("depth", None)):
            if name == "depth":  # a real upload with a forged depth map
                photo = upload(server.url, two_plane_scene.photo)
                payload = [{"path": photo, "meta": {"_type": "gradio.FileData"}}, {"path": path}]
            event, answer = call(server.url, "load", [*payload, *REST], f"{what}-{name}")
            assert event == "error", (what, name, answer)
            messages[what, name] = answer.get("error")
            _no_pixels_of(secret, answer)
        # the download of that session holds nothing
        event, answer = call(server.url, "download", ["PNG"], f"{what}-photo")
        files = [a for a in answer if isinstance(a, dict) and (a.get("value") or a.get("path"))]
        assert event == "error" or not files, answer
    # one message whatever the path is; for the depth input Gradio's own check of the
    # payload answers first, the same for every path
    assert {m for (_, n), m in messages.items() if n == "photo"} == {NOT_AN_UPLOAD}, messages
    assert len({m for (_, n), m in messages.items() if n == "depth"}) == 1, messages

    # the same through gradio_client: a payload without meta is passed on as it is
    from gradio_client import Client
    from gradio_client.exceptions import AppError

    client = Client(server.url, verbose=False, analytics_enabled=False)
    for what in ("an image elsewhere", "a folder", "a missing path"):
        with pytest.raises(AppError) as err:
            client.predict({"path": cases[what]}, None, *REST, api_name="/load")
        assert str(err.value) == NOT_AN_UPLOAD, (what, err.value)

    # an upload is loaded, and so is a bundled sample
    photo = upload(server.url, two_plane_scene.photo)
    event, answer = call(server.url, "load", [{"path": photo}, None, *REST], "honest")
    assert event == "complete", answer
    from app.panels import SAMPLES_DIR

    sample = sorted(SAMPLES_DIR.glob("*.jpg"))[0]
    event, answer = call(server.url, "load", [{"path": str(sample)}, None, *REST], "sample")
    assert event == "complete", answer
    log = server.log.read_text()
    assert "Traceback" not in log
    assert str(secret) not in log


def test_gate_known_answers(tmp_path):
    cache = tmp_path / "cache"
    samples = tmp_path / "samples"
    for folder in (cache / "abc", samples):
        folder.mkdir(parents=True)
    stored, planted, sample = cache / "abc" / "a.png", cache / "abc" / "b.png", samples / "s.jpg"
    for f in (stored, planted, sample):
        f.write_bytes(b"x")
    (cache / "abc" / "dir.png").mkdir()

    class Blocks:
        temp_file_sets = [{str(stored), str(cache / "abc" / "dir.png")}]

    gate = UploadGate([samples], cache_dir=cache)
    assert not gate.allows(str(stored))  # nothing is known before bind
    assert gate.allows(str(sample))
    gate.bind(Blocks())
    assert gate.allows(str(stored)) and gate.allows(str(sample))
    assert gate.check(str(stored)) == str(stored)
    for bad in (
        str(planted),
        str(cache / "abc" / "dir.png"),
        str(samples),
        str(samples / ".." / "cache" / "abc" / "b.png"),
        "abc/a.png",
        "",
        None,
        {"path": str(stored)},
        str(stored) + "\0",
        "/" + "a" * 5000,
    ):
        assert not gate.allows(bad), bad
    with pytest.raises(PermissionError, match="not an upload"):
        gate.check(str(planted))
