"""``d2f-app``'s start-up lines: its own address, no advice about options it does not have."""

from __future__ import annotations

import time

import pytest


@pytest.mark.slow
def test_start_up_names_the_address_and_no_share_option(app_server):
    server = app_server()  # answers HTTP: started
    deadline = time.monotonic() + 30
    while f"serving at {server.url}/" not in server.log.read_text():
        if time.monotonic() > deadline:
            server.stop()
            pytest.fail(f"no 'serving at {server.url}/' line: {server.log.read_text()[-2000:]}")
        time.sleep(0.2)
    server.stop()  # its output flushed to the log
    text = server.log.read_text()
    assert "share=True" not in text, text
    assert "Traceback" not in text, text
