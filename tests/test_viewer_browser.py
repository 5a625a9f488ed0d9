"""The viewer in a real browser: Debian's chromium (headless, SwiftShader WebGL)
driven by Playwright.  Loads the page, finds the controls, checks the canvas
shows the model, drags the threshold slider and checks the server re-carved
and the picture changed, and looks through a camera.

Set ORGANLAB_UPDATE_SCREENSHOT=1 to refresh docs/img/viewer.png from this test.
"""

import io
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not os.path.exists(CHROMIUM), reason=f"{CHROMIUM} missing: 'make test' installs Debian's chromium as root"),
]


def _until(cond, timeout=60.0, step=0.2):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if cond():
            return True
        time.sleep(step)
    return False


def _canvas(page):
    """RGB pixels of the 3D canvas left of the GUI panel, (H, W, 3) uint8."""
    from PIL import Image

    box = page.locator("canvas").first.bounding_box()
    panel = page.get_by_text("Reconstruction", exact=True).first.bounding_box()
    right = min(box["x"] + box["width"], panel["x"] - 20)
    clip = {"x": box["x"], "y": box["y"] + 200, "width": right - box["x"], "height": box["height"] - 200}
    png = page.screenshot(clip=clip)  # below the top-left notice
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def _changed(a, b, tol=30):
    return np.abs(a.astype(int) - b.astype(int)).max(axis=2) > tol


def _settle(page, seconds=2.5):
    page.wait_for_timeout(int(seconds * 1000))


def _drawn(page, until, timeout=60.0):
    """The canvas once ``until(picture)`` holds (a model hidden, shown again or replaced: each is drawn in one
    frame), polled every 0.25 s; on timeout the last picture, for the caller's assertion to judge.  Replaces
    fixed waits of 2.5-4 s before one screenshot (11.5 s in all): the picture, not a clock, says it was drawn."""
    t0 = time.monotonic()
    while True:
        now = _canvas(page)
        if until(now) or time.monotonic() - t0 > timeout:
            return now
        page.wait_for_timeout(250)


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from organlab.synthetic import with_true_cameras
    from organlab.viewer import SessionViewer

    s = with_true_cameras("sample_sessions/aaa_phantom", tmp_path_factory.mktemp("browser") / "aaa")
    v = SessionViewer(s, voxel_size=2.0, views=range(0, 36, 2), port=0)
    assert v.wait(timeout=180), v.errors
    yield v
    v.stop()


@pytest.fixture(scope="module")
def page(app, tmp_path_factory):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(tmp_path_factory.mktemp("chromium-profile")), executable_path=CHROMIUM, args=ARGS, headless=True,
            viewport={"width": 1280, "height": 800},
        )
        try:
            pg = ctx.new_page()
            pg.set_default_timeout(90_000)
            pg.goto(app.url)
            pg.get_by_text("Threshold", exact=True).wait_for()
            assert _until(lambda: len(app.live.server.get_clients()) == 1)
            _settle(pg, 5)
            yield pg
        finally:
            ctx.close()


def test_page_shows_controls_and_model(app, page, tmp_path):
    for label in ("Threshold", "Voxel size (mm)", "Method", "Hull", "Colour threshold", "Tolerance (views)", "Re-run"):
        assert page.get_by_text(label, exact=True).count() >= 1, label
    assert page.get_by_text("Volume").count() >= 1 and page.get_by_text("Agreement").count() >= 1
    shown = _canvas(page)
    if os.environ.get("ORGANLAB_UPDATE_SCREENSHOT"):
        close = page.locator("button.mantine-Notification-closeButton")
        if close.count():
            close.first.click()
            _settle(page, 1)
        page.screenshot(path=str(tmp_path / "viewer.png"))
        shutil.copy(tmp_path / "viewer.png", Path(__file__).parents[1] / "docs" / "img" / "viewer.png")
    # hide the model: the pixels that change are the model's
    app.live.set_visible("mesh", False)
    hidden = _drawn(page, lambda now: _changed(shown, now).sum() > 3000)
    app.live.set_visible("mesh", True)
    model = _changed(shown, hidden)
    h, w = model.shape
    # the specimen covers ~3 % of the canvas region at the initial framing
    # (measured 16.5 k px of 600 x 940); a blank or unframed scene gives none
    assert model.sum() > 3000, model.sum()
    rows, cols = np.nonzero(model)
    assert 0.2 * w < cols.mean() < 0.8 * w and rows.mean() < 0.8 * h  # roughly centred
    # and it is back
    back = _drawn(page, lambda now: _changed(now, hidden).sum() > 0.9 * model.sum())
    assert _changed(back, hidden).sum() > 0.9 * model.sum()


def test_threshold_slider_recarves(app, page):
    before = app.result
    gen = app.worker.generation
    label = page.get_by_text("Threshold", exact=True).first
    slider_id = label.get_attribute("for")
    thumb = page.locator(f'[id="{slider_id}"] [role="slider"]')
    track = page.locator(f'[id="{slider_id}"]').bounding_box()
    picture = _canvas(page)
    tb = thumb.bounding_box()
    page.mouse.move(tb["x"] + tb["width"] / 2, tb["y"] + tb["height"] / 2)
    page.mouse.down()
    target_x = track["x"] + 0.55 * track["width"]  # about 45 grey levels
    page.mouse.move(target_x, tb["y"] + tb["height"] / 2, steps=8)
    page.mouse.up()
    value = float(thumb.get_attribute("aria-valuenow"))
    assert 35.0 < value < 55.0
    # the server re-carved with the slider's value and showed the newest result
    assert _until(lambda: app.worker.generation > gen and app.settings.threshold == value, 30)
    assert app.wait(timeout=120) and not app.errors
    assert app.result.generation > before.generation and app.result.settings.threshold == value
    assert app.result.mesh.volume < 0.9 * before.mesh.volume  # measured 62 % at 45
    assert "auto" not in str(app.controls.auto.value) and app.controls.auto.value is False
    shown = f"{app.result.mesh.volume / 1000:.2f}"
    after = _drawn(page, lambda now: _changed(picture, now).sum() > 1500 and shown in page.locator("body").inner_text())
    # the smaller hull changes the picture (measured 6.2 k px changed)
    assert _changed(picture, after).sum() > 1500
    assert shown in page.locator("body").inner_text()


def test_automatic_threshold_checkbox(app, page):
    gen = app.worker.generation
    box_id = page.get_by_text("Automatic threshold", exact=True).first.get_attribute("for")
    page.locator(f'[id="{box_id}"]').click()
    assert _until(lambda: app.worker.generation > gen and app.settings.threshold is None, 30)
    assert app.wait(timeout=120) and app.result.settings.threshold is None
    # back to the per-view automatic thresholds: the hull of the first run
    # (measured 101 % of the reference volume with these 18 views)
    assert app.result.agreement.min() > 0.95


def test_look_through_camera(app, page):
    page.get_by_text("Look through camera", exact=True).click()
    j = int(app.controls.view.value)
    client = next(iter(app.live.server.get_clients().values()))
    assert _until(lambda: np.allclose(client.camera.position, app.cameras[j].center, atol=1e-3), 20)
    assert "/look" in app.live.server.scene._handle_from_node_name
    _settle(page, 3)
    if os.environ.get("ORGANLAB_UPDATE_SCREENSHOT"):
        page.screenshot(path=str(Path(__file__).parents[1] / "docs" / "img" / "viewer_look.png"))
    looking = _canvas(page)
    assert looking.std() > 10  # the (undistorted) photo fills the view behind the model
    # the model is drawn in front of the photo, from the camera's pose
    app.live.set_visible("mesh", False)
    assert _changed(looking, _drawn(page, lambda now: _changed(looking, now).sum() > 3000)).sum() > 3000
    app.live.set_visible("mesh", True)
    page.get_by_text("Leave camera view", exact=True).click()
    assert _until(lambda: "/look" not in app.live.server.scene._handle_from_node_name, 20)


def test_click_a_frustum_looks_through_it(app, page):
    from organlab.viewer._scene import camera_pose

    j = 4
    cam = app.cameras[j]
    wxyz, pos, _, _ = camera_pose(cam)
    client = next(iter(app.live.server.get_clients().values()))
    with client.atomic():  # stand 250 mm behind view j's camera, looking the same way
        client.camera.position = pos - 250.0 * cam.R[2]
        client.camera.wxyz = wxyz
        client.camera.fov = np.deg2rad(30.0)
    _settle(page, 3)
    box = page.locator("canvas").first.bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)  # on frustum j
    assert _until(lambda: int(app.controls.view.value) == j, 20)
    assert _until(lambda: np.allclose(client.camera.position, cam.center, atol=1e-3), 20)
    assert f"view **{app.view_ids[j]}**" in app.controls.view_info.content
    page.get_by_text("Leave camera view", exact=True).click()
