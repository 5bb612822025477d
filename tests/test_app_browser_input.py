"""Every way of setting a slider in the real page ends in the full render, and Download saves
the value on screen (headless Debian Chromium through Playwright).

Gradio sends a slider's ``release`` (the full render) only on pointer-up and when the number
box loses focus; the app's page script ends key presses and Enter the same way. Each case
sets a value, waits for the status line to report a full render of exactly that value, and
then clicks Download and reads the saved file's name
(``..._focus<position>_f<f-number>_K<blur px>.jpg``).
"""

from __future__ import annotations

import numpy as np
import pytest
from _browser import TIMEOUT_MS, click_photo_at, open_app
from _io_writers import lensblur_jpeg
from PIL import Image

from app.settings import blur_px

pytestmark = [pytest.mark.browser, pytest.mark.slow]

#: A full render of the 320x240 test photo takes well under a second; a value that ends in
#: a preview only never reaches the full render, and the wait fails after this long.
FULL_RENDER_WAIT_MS = 10_000

STATUS = "(document.querySelector('#info textarea')?.value ?? '')"


def number_value(page, elem: str) -> str:
    return page.locator(f"#{elem} input[data-testid=number-input]").input_value()


def aperture_name(f_number: str | float, width: int = 320) -> str:
    """The end of a download's name at this f-number on a photo of this long side."""
    n = float(f_number)
    return f"_f{n:g}_K{blur_px(n, width):g}.jpg"


def status_line(page) -> str:
    return page.locator("#info textarea").input_value()


def wait_full_render(page, focus: str | None = None, blur: str | None = None) -> str:
    """Wait until the status line reports a full render at these slider values (the focus
    slider's position, the f-number)."""
    parts = []
    if focus is not None:
        parts.append(f"focus {float(focus):.3f} (0 = near")
    if blur is not None:
        # the aperture, then (after the automatic focus) the subject's focal range
        parts.append(f"f/{float(blur):g}, blur {blur_px(float(blur), 320):g} px")
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        page.wait_for_function(
            f"(parts) => {{ const s = {STATUS}; return s.includes('full render') "
            "&& parts.every(p => s.includes(p)); }",
            arg=parts,
            timeout=FULL_RENDER_WAIT_MS,
        )
    except PlaywrightTimeout:
        status = status_line(page)
        blur_now, focus_now = number_value(page, "blur"), number_value(page, "focus")
        raise AssertionError(
            f"no full render of {parts} in {FULL_RENDER_WAIT_MS} ms; the status reads "
            f"{status!r}, the boxes blur={blur_now} focus={focus_now}"
        ) from None
    return status_line(page)


def saved_name(page) -> str:
    """Click Download once it is enabled; the name of the file the browser saves."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    button = page.locator("button#download, #download button").first
    try:
        page.wait_for_function(
            "() => { const b = document.querySelector('button#download, #download button');"
            " return b && !b.disabled; }",
            timeout=FULL_RENDER_WAIT_MS,
        )
    except PlaywrightTimeout:
        status = status_line(page)
        raise AssertionError(
            f"Download still disabled after {FULL_RENDER_WAIT_MS} ms; the status reads "
            f"{status!r}, the button {button.inner_text()!r}"
        ) from None
    with page.expect_download(timeout=TIMEOUT_MS) as info:
        button.click()
    return info.value.suggested_filename


def test_every_input_ends_in_the_full_render(
    app_server, chromium_launch_options, two_plane_scene, tmp_path
):
    from playwright.sync_api import sync_playwright

    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, errors=errors, accept_downloads=True)
            page.set_input_files("#input input[type=file]", str(two_plane_scene.photo))
            page.wait_for_function(f"() => {STATUS}.includes('full render')")
            # the aperture's info line is set by an event of its own after the upload's
            # render; text typed while it redraws the slider can be lost
            page.wait_for_function(
                "() => document.querySelector('#blur').innerText.includes('on this')",
                timeout=TIMEOUT_MS,
            )

            # 1. an f-number typed into the aperture slider's number box, then Enter
            box = page.locator("#blur input[data-testid=number-input]")
            box.click()
            box.fill("4")
            box.press("Enter")
            wait_full_render(page, blur="4")
            assert box.evaluate("el => el === document.activeElement")  # focus stays
            assert saved_name(page).endswith(aperture_name(4))  # _f4_K5.6.jpg

            # 2. arrow keys on the focused focus slider (key-up ends the change)
            track = page.locator("#focus input[type=range]")
            track.focus()
            for _ in range(3):
                track.press("ArrowRight")
            focus = number_value(page, "focus")
            wait_full_render(page, focus=focus, blur="4")
            assert f"_focus{float(focus):.3f}{aperture_name(4)}" in saved_name(page)

            # 3. End on the focused aperture slider: f/22
            blur_track = page.locator("#blur input[type=range]")
            blur_track.focus()
            blur_track.press("End")
            wait_full_render(page, blur="22")
            assert saved_name(page).endswith(aperture_name(22))

            # 4. a click on the aperture track (pointer-up: Gradio's own release)
            bb = blur_track.bounding_box()
            page.mouse.click(bb["x"] + bb["width"] * 0.25, bb["y"] + bb["height"] / 2)
            page.wait_for_function(
                "() => parseFloat(document.querySelector("
                "'#blur input[data-testid=number-input]').value) < 11"
            )
            blur = number_value(page, "blur")
            wait_full_render(page, blur=blur)
            assert saved_name(page).endswith(aperture_name(blur))

            # 5. a drag released at a value: the full render follows, Download saves it
            start = bb["x"] + bb["width"] * (float(blur) - 1.0) / 21.0
            y = bb["y"] + bb["height"] / 2
            page.mouse.move(start, y)
            page.mouse.down()
            for k in range(1, 6):
                page.mouse.move(start + bb["width"] * 0.08 * k, y)
                page.wait_for_timeout(30)
            page.mouse.up()
            blur = number_value(page, "blur")
            wait_full_render(page, blur=blur)
            assert saved_name(page).endswith(aperture_name(blur))

            # 6. a value typed, then Download clicked at once (the box loses focus): the
            # button waits for the full render of the value on screen, never the old file.
            # The typed value's preview is shown, or dropped when the full render of the same
            # value started first (this photo's renders take some 15 ms): either way the
            # status line names the value
            box.click()
            box.fill("2")
            page.wait_for_function(f"() => {STATUS}.includes('f/2, blur 11.1 px')")
            button = page.locator("button#download, #download button").first
            status = page.evaluate(f"() => {STATUS}")
            if "f/2, blur 11.1 px" in status and "| preview render" in status:
                assert button.is_disabled()
            # a real click on the button, disabled while a preview is shown: the box loses
            # focus (release), no file
            bb = button.bounding_box()
            page.mouse.click(bb["x"] + bb["width"] / 2, bb["y"] + bb["height"] / 2)
            wait_full_render(page, blur="2")
            assert saved_name(page).endswith(aperture_name(2))  # _f2_K11.1.jpg
        finally:
            browser.close()
    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]


PHOTO_SIZE = """() => { const img = document.querySelector('#input img');
    return img && img.complete ? [img.naturalWidth, img.naturalHeight] : null; }"""


def test_failed_upload_leaves_one_state(
    app_server, chromium_launch_options, two_plane_scene, tmp_path
):
    """After an upload that cannot be read, the photo panel shows the photo that is loaded
    (or nothing, on a fresh page), the result is unchanged and the status line keeps the
    error after the toast has gone."""
    from playwright.sync_api import sync_playwright

    server = app_server()
    bad = tmp_path / "notes.jpg"
    bad.write_text("this is a shopping list, not a photo\n" * 10)
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url)
            page.set_input_files("#input input[type=file]", str(two_plane_scene.photo))
            page.wait_for_function(f"() => {STATUS}.includes('full render')")
            result_src = page.evaluate(
                "() => document.querySelector('#result img')?.getAttribute('src')"
            )
            assert page.evaluate(PHOTO_SIZE) == [320, 240]

            page.set_input_files("#input input[type=file]", str(bad))
            page.locator(".toast-body.error", has_text="notes.jpg").first.wait_for()
            page.wait_for_function(f"() => {STATUS}.startsWith('Error: notes.jpg')")
            # the panel shows the loaded photo again, not the broken file
            page.wait_for_function(f"() => JSON.stringify(({PHOTO_SIZE})()) === '[320,240]'")
            status = status_line(page)
            assert "not an image" in status and "Still showing scene" in status
            # the summary says it too: the status line waits behind "Advanced"
            assert page.locator("#summary").inner_text().startswith("Error: notes.jpg")
            assert result_src == page.evaluate(
                "() => document.querySelector('#result img')?.getAttribute('src')"
            )
            page.locator(".toast-body.error").first.wait_for(state="detached", timeout=60_000)
            assert status_line(page) == status
            # the photo still renders (the slider drives the session's photo)
            box = page.locator("#focus input[data-testid=number-input]")
            box.fill("0.2")
            box.press("Enter")
            page.wait_for_function(f"() => {STATUS}.includes('focus 0.200 (0 = near')")

            # a fresh page, "Advanced" closed as a user finds it: nothing loaded, so nothing is
            # shown but the error, in the summary
            page = open_app(browser, server.url, details=False)
            assert page.locator("#info textarea").count() == 0
            page.set_input_files("#input input[type=file]", str(bad))
            page.wait_for_function(
                "() => (document.querySelector('#summary')?.innerText ?? '')"
                ".startsWith('Error: notes.jpg')"
            )
            page.wait_for_function("() => !document.querySelector('#input img[src]')")
            assert page.locator("button#download, #download button").first.is_disabled()
        finally:
            browser.close()
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]


#: Mean red minus mean blue of the photo panel's picture inside a box given as fractions of
#: its size (read from a canvas): the test photo's subject is warm, its negative cool.
PANEL_WARMTH = """(box) => { const img = document.querySelector('#input img');
    const w = img.naturalWidth, h = img.naturalHeight;
    const c = document.createElement('canvas'); c.width = w; c.height = h;
    const g = c.getContext('2d'); g.drawImage(img, 0, 0);
    const x0 = Math.round(box[0] * w), y0 = Math.round(box[1] * h);
    const d = g.getImageData(x0, y0, Math.round(box[2] * w) - x0, Math.round(box[3] * h) - y0).data;
    let r = 0, b = 0;
    for (let i = 0; i < d.length; i += 4) { r += d[i]; b += d[i + 2]; }
    return (r - b) / (d.length / 4); }"""


def test_lens_blur_panel_shows_the_original(
    app_server, chromium_launch_options, scene_factory, tmp_path
):
    """A Google Lens Blur upload: the photo panel changes from the file's main picture (here
    the negative of the original, 320x240) to the embedded all-in-focus original the app
    renders from (640x480, rendered at the main picture's 320x240); setting the panel does
    not load the photo again, and a click on the subject focuses on it."""
    from playwright.sync_api import sync_playwright

    scene = scene_factory(width=640, height=480)
    main = 255 - np.asarray(Image.fromarray(scene.image).resize((320, 240)))
    x0, y0, x1, y1 = scene.box
    z = np.full((240, 320), 4.0, np.float32)
    z[y0 // 2 : y1 // 2, x0 // 2 : x1 // 2] = 1.0  # the subject 1 m away, the rest 4 m
    path = tmp_path / "PXL_lensblur.jpg"
    path.write_bytes(lensblur_jpeg(scene.image, main, z, near=1.0, far=4.0))
    box = [x0 / 640, y0 / 480, x1 / 640, y1 / 480]  # the subject, as fractions of the photo

    server = app_server()
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url)
            page.set_input_files("#input input[type=file]", str(path))
            page.wait_for_function(f"() => {STATUS}.includes('full render')")
            page.wait_for_function(
                "() => (document.querySelector('#input img')?.getAttribute('src') ?? '')"
                ".includes('d2f-rendered-from-')"
            )
            page.wait_for_function(f"() => JSON.stringify(({PHOTO_SIZE})()) === '[320,240]'")
            # the subject is warm in the original and cool in the file's main picture
            assert page.evaluate(PANEL_WARMTH, box) > 20
            status = status_line(page)
            assert "depth embedded in the photo" in status

            # a click on the subject in the panel focuses on it: the focus slider's near end
            img = page.locator("#input img")
            rect = img.bounding_box()
            scale = min(rect["width"] / 320, rect["height"] / 240)
            left = rect["x"] + (rect["width"] - 320 * scale) / 2
            top = rect["y"] + (rect["height"] - 240 * scale) / 2
            nx, ny = scene.near_point
            page.mouse.click(left + nx / 2 * scale, top + ny / 2 * scale)
            page.wait_for_function(f"() => {STATUS}.includes('focused on the click')")
            status = status_line(page)
            focus = float(status.split("focus ")[1].split(" ")[0])
            assert focus == pytest.approx(0.0, abs=0.02), status
            assert float(page.locator("#focus input[data-testid=number-input]").input_value()) == (
                pytest.approx(0.0, abs=0.02)
            )
        finally:
            browser.close()
    log = server.log.read_text()
    assert log.count("loaded PXL_lensblur") == 1, log[-3000:]  # the panel's update loads nothing
    assert "Traceback" not in log, log[-3000:]


def test_heic_upload_shows_and_clicks(
    app_server, chromium_launch_options, two_plane_scene, tmp_path
):
    """A HEIC upload, which Chromium cannot show: the photo panel shows a JPEG of the decoded
    photo (a loaded image, not a broken one), the focus goes to the subject found, and a click
    on the panel refocuses."""
    from playwright.sync_api import sync_playwright

    pillow_heif = pytest.importorskip("pillow_heif")
    pillow_heif.register_heif_opener()
    path = tmp_path / "IMG_0001.HEIC"
    Image.fromarray(two_plane_scene.image).save(path, format="HEIF", quality=95)

    server = app_server()
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url)
            # with the type a phone's file carries (Playwright names no type for .HEIC, and
            # Gradio's image input then drops the file)
            heic = {"name": path.name, "mimeType": "image/heic", "buffer": path.read_bytes()}
            page.set_input_files("#input input[type=file]", files=[heic])
            page.wait_for_function(f"() => {STATUS}.includes('full render')")
            assert "focus on the subject at" in status_line(page)
            page.wait_for_function(f"() => JSON.stringify(({PHOTO_SIZE})()) === '[320,240]'")
            src = page.evaluate("() => document.querySelector('#input img').getAttribute('src')")
            assert "d2f-rendered-from-" in src and not src.lower().endswith(".heic")

            nx, ny = two_plane_scene.near_point
            click_photo_at(page, nx, ny)
            page.wait_for_function(f"() => {STATUS}.includes('focused on the click')")
            status = status_line(page)
            # the click lands on the photo where it was made (the panel is the photo's size)
            x, y = status.split("focused on the click at (")[1].split(")")[0].split(", ")
            assert abs(float(x) - nx) <= 2 and abs(float(y) - ny) <= 2, status
        finally:
            browser.close()
    log = server.log.read_text()
    assert log.count("loaded IMG_0001") == 1, log[-3000:]  # the panel's update loads nothing
    assert "Traceback" not in log, log[-3000:]


def test_examples_above_the_fold(app_server, chromium_launch_options):
    """At 1400x900 a newcomer sees the examples, the photo panel and both sliders without
    scrolling, and Download is disabled on the empty page."""
    from playwright.sync_api import sync_playwright

    server = app_server()
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url)
            thumbs = page.locator(".gallery-item, [data-testid=examples] button")
            thumbs.first.wait_for()
            boxes = {
                "first example": thumbs.first.bounding_box(),
                "photo": page.locator("#input").bounding_box(),
                "focus slider": page.locator("#focus input[type=range]").bounding_box(),
                "blur slider": page.locator("#blur input[type=range]").bounding_box(),
            }
            below = {
                k: b["y"] + b["height"] for k, b in boxes.items() if b["y"] + b["height"] > 900
            }
            assert not below, f"below the fold at 1400x900: {below}"
            assert page.locator("button#download, #download button").first.is_disabled()
        finally:
            browser.close()
