"""The focus and blur brushes in the real page (headless Chromium): paint with the green
brush over a part of the background that the map blurs, Apply, and it is sharp; it stays
sharp when the aperture changes; the red brush blurs a part of the subject in focus; Clear
paint gives the picture without paint again. The status line's command names the masks."""

from __future__ import annotations

import re

import numpy as np
import pytest
from _browser import (
    changed_result,
    click_photo_at,
    fetch_image,
    open_app,
    result_src,
    wait_status,
)
from PIL import Image

pytestmark = [pytest.mark.browser, pytest.mark.slow]

WIDTH, HEIGHT = 960, 720
#: the subject, near (0.85), before a wall far away (0.1)
SUBJECT = (120, 160, 400, 560)
#: where the green brush paints (photo pixels x0, y0, x1, y1), on the wall
PAINT = (560, 160, 880, 340)


def _write_scene(folder):
    rng = np.random.default_rng(5)
    cells = rng.integers(30, 226, size=(HEIGHT // 2, WIDTH // 2, 3), dtype=np.uint8)
    image = cells.repeat(2, 0).repeat(2, 1)
    disparity = np.full((HEIGHT, WIDTH), 0.1, np.float32)
    x0, y0, x1, y1 = SUBJECT
    disparity[y0:y1, x0:x1] = 0.85
    photo, depth = folder / "wall.png", folder / "wall_disparity.png"
    Image.fromarray(image).save(photo)
    Image.fromarray((disparity * 255).round().astype(np.uint8)).save(depth)
    return photo, depth, image


def _brushes(page) -> None:
    """Open or close the brushes' panel: the editor is closed while the app renders (open,
    it exports and uploads its images again at each new picture, app/paint_bench.py)."""
    page.get_by_text("Brushes: keep sharp / blur").click()


def _picture(page, old_src):
    src = changed_result(page, old_src)
    return src, fetch_image(page, src)


def _canvas_geometry(page) -> tuple[float, float, float]:
    """``(left, top, zoom)``: where photo pixel (0, 0) is on the page and the zoom the editor
    shows (its "NN%"), the photo drawn centred on the canvas."""
    box = page.locator("#paint canvas").first.bounding_box()
    zoom_text = page.locator("#paint").get_by_text(re.compile(r"^\d+%$")).first.inner_text()
    zoom = float(zoom_text.rstrip("%")) / 100.0
    return (
        box["x"] + (box["width"] - WIDTH * zoom) / 2,
        box["y"] + (box["height"] - HEIGHT * zoom) / 2,
        zoom,
    )


def _paint(page, rect, rows: int = 8) -> None:
    """Strokes across ``rect`` (photo pixels), row after row, with the tool selected."""
    x0, y0, x1, y1 = rect
    viewport = page.viewport_size
    ox, oy, zoom = _canvas_geometry(page)
    for y in np.linspace(y0 + 10, y1 - 10, rows):
        ax, ay = ox + (x0 + 10.5) * zoom, oy + (y + 0.5) * zoom
        bx = ox + (x1 - 9.5) * zoom
        assert 0 < ay < viewport["height"] and 0 < bx < viewport["width"], "canvas off screen"
        page.mouse.move(ax, ay)
        page.mouse.down()
        # the editor draws a straight segment between two pointer events: a stroke across is
        # its two ends and its middle (each event redraws the canvas: 0.2-0.3 s here)
        for t in (0.5, 1.0):
            page.mouse.move(ax + (bx - ax) * t, ay)
        page.mouse.up()


def test_brushes_keep_sharp_and_blur(app_server, chromium_launch_options, sharpness, tmp_path):
    from playwright.sync_api import sync_playwright

    photo, depth, image = _write_scene(tmp_path)
    x0, y0, x1, y1 = PAINT
    inside = (x0 + 40, y0 + 30, x1 - 40, y1 - 30)  # the paint's inside, away from its rim
    wall = (560, 440, 880, 660)  # wall never painted
    sx0, sy0, sx1, sy1 = SUBJECT
    subject_left, subject_right = (
        (sx0 + 20, sy0 + 20, 240, sy1 - 20),
        (290, sy0 + 20, sx1 - 20, sy1 - 20),
    )
    server = app_server()
    errors: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(**chromium_launch_options)
        try:
            page = open_app(browser, server.url, height=1300, errors=errors)
            # with the brushes' panel open, every new picture makes the editor export and
            # upload its images again (tens of MB in the page, app/paint_bench.py): on a
            # loaded machine an action waits for the page for tens of seconds
            page.set_default_timeout(150_000)
            page.set_input_files("#input input[type=file]", str(photo))
            wait_status(page, "full render")
            page.get_by_text("Your own depth map (optional)").click()
            page.set_input_files("#depth input[type=file]", str(depth))
            wait_status(page, "your disparity map")
            old = result_src(page)
            click_photo_at(page, (sx0 + sx1) // 2, (sy0 + sy1) // 2)
            info = wait_status(page, "focused on the click", "full render")
            src, plain = _picture(page, old)
            assert sharpness(plain, inside) < 0.5 * sharpness(image, inside)
            assert sharpness(plain, subject_left) >= 0.95 * sharpness(image, subject_left)

            # 1. the green brush over the wall, applied: the painted wall is sharp, the rest
            # as before, and the command names the mask
            page.get_by_text("Brushes: keep sharp / blur").click()
            page.wait_for_selector("#paint canvas")
            page.wait_for_function(
                "() => [...document.querySelectorAll('#paint *')].some("
                "e => /^\\d+%$/.test(e.textContent.trim()))"
            )
            page.locator("#paint canvas").first.scroll_into_view_if_needed()
            page.locator("#paint button[aria-label=Brush]").click()
            _paint(page, PAINT)
            page.locator("#paint_apply").click()
            _brushes(page)  # closed
            info = wait_status(page, "painted:", "full render", old=info)
            assert "--sharp-mask " in info and "--blur-mask" not in info
            mask_path = re.search(r"--sharp-mask (\S+)", info).group(1)
            mask = np.asarray(Image.open(mask_path)) > 0
            assert mask.shape == (HEIGHT, WIDTH)
            ys, xs = np.nonzero(mask)
            # the strokes cover the painted rectangle (the brush's width around each row)
            assert xs.min() <= x0 + 20 and xs.max() >= x1 - 20, (xs.min(), xs.max())
            assert ys.min() <= y0 + 20 and ys.max() >= y1 - 20, (ys.min(), ys.max())
            assert not mask[wall[1] :, :].any() and not mask[:, :sx1].any()
            ix0, iy0, ix1, iy1 = inside
            assert mask[iy0:iy1, ix0:ix1].all()  # rows of strokes with no gap between them

            src, painted = _picture(page, src)
            assert sharpness(painted, inside) >= 0.9 * sharpness(image, inside)
            assert sharpness(painted, subject_left) >= 0.95 * sharpness(image, subject_left)
            assert sharpness(painted, wall) == pytest.approx(sharpness(plain, wall), rel=0.05)
            # 2. another aperture: the paint stays
            box = page.locator("#blur input[data-testid=number-input]")
            box.click()
            box.fill("2")
            box.press("Enter")
            info = wait_status(page, "f/2,", "painted:", "full render", old=info)
            src, f2 = _picture(page, src)
            assert sharpness(f2, inside) >= 0.9 * sharpness(image, inside)
            # the unpainted wall: less blurred than at f/1.4, still blurred
            assert sharpness(plain, wall) < sharpness(f2, wall) < 0.9 * sharpness(image, wall)

            # 3. the red brush over the subject's right part: blurred, its left part sharp
            _brushes(page)  # open again
            page.locator("#paint canvas").first.scroll_into_view_if_needed()
            page.locator("#paint button[aria-label=Color]").click()
            # the palette's swatches: green (keep sharp), red (blur)
            page.locator("#paint button.color").nth(1).click()
            page.locator("#paint button[aria-label=Brush]").click()
            # 16 rows: strokes 25 px apart overlap (8 rows, 51 px apart, left stripes of the
            # subject between them unpainted, and so sharp)
            _paint(page, (290, sy0 + 10, sx1 + 30, sy1 - 10), rows=16)
            page.locator("#paint_apply").click()
            _brushes(page)  # closed
            info = wait_status(page, "% blurred", "full render", "--blur-mask", old=info)
            blur_path = re.search(r"--blur-mask (\S+)", info).group(1)
            blur_mask = np.asarray(Image.open(blur_path)) > 0
            rx0, ry0, rx1, ry1 = subject_right
            assert blur_mask[ry0:ry1, rx0:rx1].all()  # the measured part is painted whole
            src, red = _picture(page, src)
            # blurred as the far wall is (the red paint sends it to the far end of the depth):
            # under a tenth of its detail left (measured 4.1 %, the wall 2.0 %: beside the
            # sharp left part the far layer's blur is drawn from one side only)
            assert sharpness(red, subject_right) < 0.1 * sharpness(image, subject_right)
            assert sharpness(red, subject_left) >= 0.9 * sharpness(image, subject_left)
            assert sharpness(red, inside) >= 0.9 * sharpness(image, inside)

            # 4. cleared: the picture without paint, the canvas back to the photo
            _brushes(page)  # open again
            page.locator("#paint_clear").click()
            _brushes(page)  # closed
            info = wait_status(page, "full render", absent="painted:", old=info)
            assert "--sharp-mask" not in info
            src, cleared = _picture(page, src)
            assert sharpness(cleared, inside) < 0.85 * sharpness(image, inside)
            assert sharpness(cleared, inside) < 1.1 * sharpness(cleared, wall)
            assert sharpness(cleared, subject_right) >= 0.95 * sharpness(image, subject_right)
        finally:
            browser.close()
    assert not errors, errors
    log = server.log.read_text()
    assert "Traceback" not in log, log[-3000:]
