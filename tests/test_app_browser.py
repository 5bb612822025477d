"""The real app in headless Chromium (Playwright, sync API), driven like a user would.

Starts ``python -m app`` on a free localhost port with a tiny random-init checkpoint,
uploads a generated photo whose near subject and far background are known (with its
disparity map), opens the aperture to f/1, clicks the subject and then the background (the
focus slider moves to its near end, then to its far end), drags the aperture slider to f/22,
switches to the defocus view, and uploads a file that is not an image. Screenshots go to the test's
tmp dir (``<tmp_path>/screens/NN_<step>.png``).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from _browser import (
    changed_result,
    click_photo_at,
    fetch_image,
    open_app,
    wait_full_result,
    wait_new_result,
)

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def focus_value(page) -> float:
    return float(page.locator("#focus input[data-testid=number-input]").input_value())


def test_refocus_in_browser(
    app_server, chromium_launch_options, scene_factory, sharpness, tmp_path
):
    from playwright.sync_api import sync_playwright

    server = app_server()
    screens = tmp_path / "screens"
    screens.mkdir()
    shots: list[Path] = []

    def shot(page, name: str) -> None:
        path = screens / f"{len(shots):02d}_{name}.png"
        page.screenshot(path=str(path), full_page=True)
        shots.append(path)

    # 960 px wide: f/1 blurs it by K = 66.7 px (0.0694 px per px of the long side), enough
    # for the tiny random model, whose fusion keeps much of the sharp input under ~30 px
    scene = scene_factory(width=960, height=720)
    x0, y0, x1, y1 = scene.box
    subject = (x0 + 12, y0 + 12, x1 - 12, y1 - 12)
    background = (x1 + 12, 12, scene.image.shape[1] - 4, scene.image.shape[0] - 4)
    errors: list[str] = []

    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, height=1000, errors=errors)
            download = page.locator("button#download, #download button").first
            assert download.is_disabled()  # nothing to save before a render

            # 0. a bundled example renders (network disparity of the tiny random model)
            page.locator(".gallery-item, [data-testid=examples] button").first.click()
            src = wait_new_result(page, None)
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.startsWith('512x512 px')"
            )
            download.wait_for(state="visible")
            page.wait_for_function(
                "() => { const b = document.querySelector('button#download, #download button');"
                " return b && !b.disabled; }"
            )
            shot(page, "example")

            # 1. the photo, then its disparity map (which replaces the network's map)
            page.set_input_files("#input input[type=file]", str(scene.photo))
            src = wait_new_result(page, src)
            # no depth and no focal plane in the file: the slider moves to the subject found
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.includes("
                "'focus on the subject at')"
            )
            photo_focus = focus_value(page)
            page.get_by_text("Your own depth map (optional)").click()
            page.set_input_files("#depth input[type=file]", str(scene.disparity))
            src = wait_new_result(page, src)
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.includes('your disparity')"
            )
            shot(page, "uploaded")
            start_focus = focus_value(page)

            # the widest aperture, typed: f/1 and its blur in px on this photo
            box = page.locator("#blur input[data-testid=number-input]")
            box.fill("1")
            box.press("Enter")
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.includes("
                "'f/1, blur 66.7 px | full render')"
            )
            src = wait_new_result(page, src)

            # 2. click the near subject: the focus slider goes to its near end (0), the
            # subject becomes sharp
            click_photo_at(page, *scene.near_point)
            page.wait_for_function(
                "() => parseFloat(document.querySelector("
                "'#focus input[data-testid=number-input]').value) < 0.05"
            )
            src = wait_full_result(page, src)
            near = fetch_image(page, src)
            near_focus = focus_value(page)
            shot(page, "focused_near")

            # 3. click the far background: the slider goes to its far end (1), the
            # background becomes sharp
            click_photo_at(page, *scene.far_point)
            page.wait_for_function(
                "() => parseFloat(document.querySelector("
                "'#focus input[data-testid=number-input]').value) > 0.95"
            )
            src = wait_full_result(page, src)
            far = fetch_image(page, src)
            far_focus = focus_value(page)
            shot(page, "focused_far")

            # a depth map without a focal plane keeps the slider where it was
            assert start_focus == pytest.approx(photo_focus)
            assert "cached scene" not in page.locator("#info textarea").input_value()
            assert near_focus == pytest.approx(0.0, abs=0.02)  # the slider's left: near
            assert far_focus == pytest.approx(1.0, abs=0.02)
            assert near.shape == far.shape == scene.image.shape
            assert sharpness(near, subject) > 2 * sharpness(far, subject)
            assert sharpness(far, background) > 2 * sharpness(near, background)
            assert sharpness(far, background) > 0.8 * sharpness(scene.image, background)

            # 4. the defocus map with its colour legend (focused far, f/1)
            page.locator("#view").get_by_text("Defocus", exact=True).click()
            src = wait_new_result(page, src)
            page.wait_for_selector("#legend >> text=in focus")
            defocus = fetch_image(page, src)
            # background in focus: dark end of magma; the subject far from it (66.7 px across
            # at full resolution): about halfway up the scale
            dark = defocus[background[1] : background[3], background[0] : background[2]].mean()
            assert dark < 40
            assert defocus[subject[1] : subject[3], subject[0] : subject[2]].mean() > dark + 60
            top = page.locator("#legend").inner_text()
            assert "px or more across" in top and "render pass" not in top
            shot(page, "defocus_view")

            page.locator("#view").get_by_text("Bokeh", exact=True).click()
            src = wait_new_result(page, src)

            # 5. drag the aperture slider to its right end (f/22): the out-of-focus subject
            # gets sharper (K = 0.0694 * 960 / 22 = 3 px)
            f_before = float(page.locator("#blur input[data-testid=number-input]").input_value())
            track = page.locator("#blur input[type=range]").bounding_box()
            ymid = track["y"] + track["height"] / 2
            start_x = track["x"] + track["width"] * (f_before - 1.0) / 21.0
            page.mouse.move(start_x, ymid)
            page.mouse.down()
            for k in range(1, 11):
                page.mouse.move(start_x + (track["x"] + track["width"] - start_x) * k / 10, ymid)
                page.wait_for_timeout(30)
            page.mouse.up()
            page.wait_for_function(
                "() => parseFloat(document.querySelector("
                "'#blur input[data-testid=number-input]').value) > 20"
            )
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.includes('full render')"
                " && /f\\/2[0-2](\\.\\d)?, blur [0-9.]+ px/.test("
                "document.querySelector('#info textarea').value)"
            )
            src = changed_result(page, src)
            dragged = fetch_image(page, src)
            f_after = float(page.locator("#blur input[data-testid=number-input]").input_value())
            assert f_before == 1.0 and f_after > 20
            assert sharpness(dragged, subject) > 2 * sharpness(far, subject)
            shot(page, "aperture_dragged")

            # 6. a file that is not an image gets a clear error, not a traceback
            bad = tmp_path / "notes.jpg"
            bad.write_text("this is a shopping list, not a photo\n" * 10)
            page.set_input_files("#input input[type=file]", str(bad))
            toast = page.locator(".toast-body.error", has_text="notes.jpg").first
            toast.wait_for()
            text = toast.inner_text()
            shot(page, "bad_upload")
            assert "notes.jpg" in text and "not an image" in text
            assert "Traceback" not in text

            # 7. the session's photo survived: the focus slider still renders it
            number = page.locator("#focus input[data-testid=number-input]")
            number.fill("0.5")
            number.press("Enter")
            page.wait_for_function(
                "() => document.querySelector('#info textarea').value.includes("
                "'focus 0.500 (0 = near, 1 = far; disparity 0.500) | f/22, blur 3 px | full')"
            )
            src = changed_result(page, src)
            assert fetch_image(page, src).shape[:2] == scene.image.shape[:2]
        finally:
            browser.close()

    assert not errors, errors
    assert all(p.stat().st_size > 0 for p in shots)
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
