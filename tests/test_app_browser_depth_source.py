"""The "Depth source" control in the real page (headless Debian Chromium through Playwright).

A generated photo is uploaded (no depth in the file: the shipped network's map). The test
opens the "Depth source" accordion and switches to a second source that needs no network:
a tiny, randomly initialised DPT depth model saved with ``save_pretrained`` into a tmp
folder and typed into the model box (when ``transformers`` is installed and the page offers
it), else the user's own depth map. Each switch must name the source in the status line and
show a different picture; switching back to the network must show the first picture again,
from the scene cache.
"""

from __future__ import annotations

import numpy as np
import pytest
from _browser import fetch_image, open_app, wait_new_result
from _tiny_hub import save_dpt

from d2f_core.depth import sources as depth_sources

pytestmark = [pytest.mark.browser, pytest.mark.slow]

STATUS = "(document.querySelector('#info textarea')?.value ?? '')"


def wait_status(page, *parts: str) -> str:
    """Wait until the status line reports a full render and holds every one of ``parts``."""
    page.wait_for_function(
        f"(parts) => {{ const s = {STATUS}; return s.includes('full render') "
        "&& parts.every(p => s.includes(p)); }",
        arg=list(parts),
    )
    return page.locator("#info textarea").input_value()


def test_depth_source_in_browser(app_server, chromium_launch_options, two_plane_scene, tmp_path):
    from playwright.sync_api import sync_playwright

    server = app_server("--allow-any-depth-model")  # a folder typed in: local use
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, height=1000, errors=errors)

            # the photo carries no depth: automatic means the shipped network
            page.set_input_files("#input input[type=file]", str(two_plane_scene.photo))
            src = wait_new_result(page, None)
            status = wait_status(page, "depth: shipped network (d2f)")
            network = fetch_image(page, src)

            page.get_by_text("Depth source", exact=True).click()
            radio = page.locator("#depth_source")
            radio.get_by_text("Shipped network alone (offline, fastest)").wait_for(state="visible")
            hub_offered = radio.get_by_text("Hugging Face model", exact=False).count() > 0
            # the server runs in this environment: offered exactly when transformers is there
            assert hub_offered == depth_sources.hub_available()
            if hub_offered:
                folder = tmp_path / "tiny-dpt"
                save_dpt(folder)
                # the name first: choosing the source loads at once with the box's value
                page.locator("#hub_model textarea, #hub_model input").first.fill(str(folder))
                radio.get_by_text("Hugging Face model", exact=False).click()
                source = f"depth: transformers:{folder} (relative inverse depth)"
            else:
                # without transformers, the user's own map is the other offline source
                assert not page.locator("#hub_model").is_visible()
                page.get_by_text("Your own depth map (optional)").click()
                page.set_input_files("#depth input[type=file]", str(two_plane_scene.disparity))
                wait_status(page, "depth: your disparity map")
                src = page.evaluate(
                    "() => document.querySelector('#result img').getAttribute('src')"
                )
                radio.get_by_text("Your depth map (below)").click()
                source = "depth: your disparity map"
            src = wait_new_result(page, src)
            status = wait_status(page, source)
            other = fetch_image(page, src)
            assert "cached scene" not in status
            assert other.shape == network.shape == two_plane_scene.image.shape
            # another map, another focus and blur: a visibly different picture
            assert np.abs(other - network).mean() > 2.0

            # back to the network: named again, the first picture again, from the cache
            radio.get_by_text("Shipped network alone (offline, fastest)").click()
            src = wait_new_result(page, src)
            status = wait_status(page, "depth: shipped network (d2f)", "cached scene")
            again = fetch_image(page, src)
            assert np.abs(again - network).max() <= 1
            assert "Error" not in status
        finally:
            browser.close()

    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
