"""The viewer panel in a real browser: ``ns-viewer --load-config`` on a tiny trained run (CPU),
headless Chromium driven by selenium. Save a view, edit the downloaded PNG, upload it, apply,
and see the render turn towards the edit; a text upload shows an error and the viewer keeps
rendering and serving. Pick mode: click the red sphere with a green colour set, see it turn green
and the blue one stay, undo; a click on the background is an error and the viewer keeps serving.

The set-up installs Debian's ``chromium`` + ``chromium-driver`` and selenium when they are
missing; the test skips (saying why) only where they cannot be installed."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from virgi_ns.io.camera_json import read_camera_json

from viewer_run import train_tiny
from virgi_scene import make_scene

pytestmark = pytest.mark.slow

CHROMIUM, DRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
FLAGS = ("--headless --no-sandbox --disable-gpu --disable-quic --no-first-run --disable-background-networking "
         "--disable-component-update --disable-sync --window-size=1280,1000").split()
EDIT_RGB = np.array([0.1, 0.8, 0.15], dtype=np.float32)
# Starts ns-viewer; attaches the panel itself only where the model does not hold one yet.
LAUNCH = """
import sys
from virgi_ns.nerfstudio.model import VirgiModel
from virgi_ns.nerfstudio.viewer.panel import VirgiPanel
_populate = VirgiModel.populate_modules
def populate(self):
    _populate(self)
    if getattr(self, "viewer_panel", None) is None:
        self.viewer_panel = VirgiPanel(self)
VirgiModel.populate_modules = populate
from nerfstudio.scripts.viewer.run_viewer import entrypoint
sys.argv = ["ns-viewer"] + sys.argv[1:]
entrypoint()
"""


def _install_browser() -> None:
    if not (Path(CHROMIUM).exists() and Path(DRIVER).exists()):
        if shutil.which("apt-get") is None:
            pytest.skip("chromium is not installed and there is no apt-get to install it")
        try:
            subprocess.run(["apt-get", "install", "-y", "chromium", "chromium-driver"], check=True,
                           capture_output=True, timeout=900)
        except (subprocess.SubprocessError, OSError) as e:
            pytest.skip(f"cannot install chromium + chromium-driver with apt-get: {type(e).__name__}")
        if not (Path(CHROMIUM).exists() and Path(DRIVER).exists()):
            pytest.skip("apt-get ran but chromium / chromedriver are still missing")
    try:
        import selenium  # noqa: F401
    except ImportError:
        r = subprocess.run([sys.executable, "-m", "pip", "install", "selenium"], capture_output=True, timeout=600)
        if r.returncode != 0:
            pytest.skip("selenium is not installed and pip cannot install it")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def viewer(tmp_path_factory):
    _install_browser()
    root = tmp_path_factory.mktemp("viewer_browser")
    scene = make_scene(root / "scene")
    cfg, _ = train_tiny(scene, steps=20, output_dir=root / "outputs")
    config = cfg.get_base_dir() / "config.yml"
    port = _free_port()
    log = open(root / "viewer.log", "w")
    proc = subprocess.Popen([sys.executable, "-c", LAUNCH, "--load-config", str(config),
                             "--viewer.websocket-port", str(port), "--viewer.websocket-host", "127.0.0.1"],
                            stdout=log, stderr=subprocess.STDOUT, cwd=root, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 240
        while True:
            if proc.poll() is not None:
                pytest.fail(f"ns-viewer exited ({proc.returncode}):\n{(root / 'viewer.log').read_text()[-3000:]}")
            try:
                urllib.request.urlopen(url, timeout=2).read()
                break
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail(f"ns-viewer did not start:\n{(root / 'viewer.log').read_text()[-3000:]}")
                time.sleep(0.5)
        yield url, cfg.get_base_dir(), root
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


@pytest.fixture
def browser(viewer, tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in FLAGS + [f"--user-data-dir={tmp_path / 'profile'}"]:
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    driver.execute_cdp_cmd("Browser.setDownloadBehavior", {"behavior": "allow", "downloadPath": str(downloads)})
    try:
        yield driver, downloads
    finally:
        driver.quit()


def _wait(what: str, check, timeout: float = 60.0, every: float = 0.25):
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(every)


def _screenshot(driver, path: Path) -> np.ndarray:
    driver.save_screenshot(str(path))
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0


def _render_region(driver, shot: np.ndarray) -> np.ndarray:
    """The part of the page that shows the render: the canvas, left of the control panel."""
    from selenium.webdriver.common.by import By

    dpr = float(driver.execute_script("return window.devicePixelRatio"))
    c = driver.find_element(By.TAG_NAME, "canvas").rect
    panel = driver.find_element(By.XPATH, "//*[normalize-space(text())='Connected']").rect
    x1 = int(min(c["x"] + c["width"], panel["x"] - 20) * dpr)
    y0, y1 = int(c["y"] * dpr), int((c["y"] + c["height"]) * dpr)
    return shot[y0:y1, int(c["x"] * dpr) : x1]


def _scene_pixels(region: np.ndarray) -> np.ndarray:
    """Pixels that differ from the background colour (the region's top-left corner)."""
    bg = region[:4, :4].reshape(-1, 3).mean(0)
    return region[np.abs(region - bg).max(-1) > 0.08]


def _open_panel(driver, url: str, shows: str):
    """Open the viewer at ``url`` and wait until its connected VIRGi panel shows ``shows``; returns (the
    page's text, the panel button with a label): what the browser tests read and press."""
    from selenium.webdriver.common.by import By

    driver.get(url)

    def body() -> str:
        return driver.find_element(By.TAG_NAME, "body").text

    def button(label: str):
        return driver.find_element(By.XPATH, f"//button[normalize-space()='{label}']")

    _wait("the VIRGi panel", lambda: shows in body() and "Connected" in body(), 90)
    return body, button


def test_save_upload_apply_in_the_browser(viewer, browser, tmp_path):
    from selenium.webdriver.common.by import By

    url, run_dir, _ = viewer
    driver, downloads = browser
    body, button = _open_panel(driver, url, "Save this view")
    def rendered():
        px = _scene_pixels(_render_region(driver, _screenshot(driver, tmp_path / "0.png")))
        return (px,) if len(px) > 500 else None

    (before,) = _wait("a first render", rendered, 90, 0.5)

    # save the view: the PNG and its camera arrive as downloads and sit in the run directory
    button("Save this view").click()
    png = _wait("the saved view's download", lambda: next(iter(downloads.glob("view_*.png")), None))
    js = _wait("the camera's download", lambda: next(iter(downloads.glob("view_*.json")), None))
    _wait("complete downloads", lambda: not list(downloads.glob("*.crdownload")))
    assert png.read_bytes() == (run_dir / "views" / png.name).read_bytes()
    spec = read_camera_json(js)
    assert json.loads(js.read_text())["image"] == png.name
    saved = np.asarray(Image.open(png).convert("RGB"), dtype=np.float32) / 255.0
    assert saved.shape == (spec.height, spec.width, 3)

    # edit it "in an image editor": every scene pixel becomes green; upload, apply
    mask = np.abs(saved - saved[0, 0]).max(-1) > 0.05
    assert mask.mean() > 0.05
    edited = saved.copy()
    edited[mask] = EDIT_RGB
    edited_path = tmp_path / f"{png.stem}_edited.png"
    Image.fromarray((edited * 255 + 0.5).astype(np.uint8)).save(edited_path)
    driver.find_element(By.CSS_SELECTOR, "input[type=file]").send_keys(str(edited_path))
    _wait("the upload to be accepted", lambda: "ready for" in body())
    button("Apply edit").click()
    _wait("the edit", lambda: "edit 1 applied" in body() or "Error" in body(), 120)
    assert "Error" not in body(), body()

    def greener():
        region = _render_region(driver, _screenshot(driver, tmp_path / "1.png"))
        px = _scene_pixels(region)
        ok = len(px) > 500 and np.abs(px - EDIT_RGB).mean() < 0.5 * np.abs(before - EDIT_RGB).mean()
        return (px,) if ok else None

    (after,) = _wait("the render to move towards the edit", greener, 60, 0.5)
    assert np.abs(after - EDIT_RGB).mean() < 0.5 * np.abs(before - EDIT_RGB).mean()
    assert "1: " + edited_path.name in body()  # the edit is listed with its toggle

    # a text file: the panel says so, the page keeps rendering and the server keeps serving
    note = tmp_path / "notes.txt"
    note.write_text("this is not a picture")
    driver.find_element(By.CSS_SELECTOR, "input[type=file]").send_keys(str(note))
    _wait("the error", lambda: "Error: notes.txt is not an image" in body())
    region = _render_region(driver, _screenshot(driver, tmp_path / "2.png"))
    px = _scene_pixels(region)
    assert len(px) > 0.5 * len(after) and np.abs(px - EDIT_RGB).mean() < 0.5 * np.abs(before - EDIT_RGB).mean()
    button("Save this view").click()
    _wait("a second saved view", lambda: len(list(downloads.glob("view_*.png"))) == 2)


def _checkbox(driver, label: str):
    from selenium.webdriver.common.by import By

    return driver.find_element(By.XPATH, f"//*[normalize-space(text())='{label}']/ancestor::*"
                                         f"[.//input[@type='checkbox']][1]//input[@type='checkbox']")


def _text_input(driver, label: str):
    from selenium.webdriver.common.by import By

    return driver.find_element(By.XPATH, f"//*[normalize-space(text())='{label}']/ancestor::*"
                                         f"[.//input[not(@type='checkbox')]][1]//input[not(@type='checkbox')]")


def _set_input(driver, element, text: str) -> None:
    """Set a React-controlled input to ``text`` at once (typing would send every partial colour)."""
    driver.execute_script(
        "const set = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set;"
        "set.call(arguments[0], arguments[1]);"
        "arguments[0].dispatchEvent(new Event('input', {bubbles: true}));"
        "arguments[0].dispatchEvent(new Event('change', {bubbles: true}));"
        "arguments[0].blur();", element, text)


def _press(driver, element) -> None:
    """Click a panel element from script: a pointer click scrolls the page to it, and the render
    region is then no longer where the canvas's rectangle says in the screenshot."""
    driver.execute_script("arguments[0].click()", element)


def _click_render(driver, shot_xy: tuple[int, int]) -> None:
    """Click the canvas at a screenshot pixel (device pixels, page coordinates)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    driver.execute_script("window.scrollTo(0, 0)")
    dpr = float(driver.execute_script("return window.devicePixelRatio"))
    canvas = driver.find_element(By.TAG_NAME, "canvas")
    r = canvas.rect
    dx = shot_xy[0] / dpr - (r["x"] + r["width"] / 2)
    dy = shot_xy[1] / dpr - (r["y"] + r["height"] / 2)
    ActionChains(driver).move_to_element_with_offset(canvas, int(dx), int(dy)).click().perform()


def test_pick_in_the_browser(viewer, browser, tmp_path):
    from selenium.webdriver.common.by import By

    url, run_dir, _ = viewer
    driver, _ = browser
    body, button = _open_panel(driver, url, "Pick mode")
    if list((run_dir / "edits").glob("edit_*.pt")):  # another test's edits: start from the unedited run
        _press(driver, button("Reset"))
        _wait("the reset", lambda: "reset: removed" in body(), 60)
    seen: dict = {}

    def spheres(name: str):
        """(screenshot, region offset, region, red sphere mask, blue sphere mask) once both show."""
        driver.execute_script("window.scrollTo(0, 0)")
        dpr = float(driver.execute_script("return window.devicePixelRatio"))
        shot = _screenshot(driver, tmp_path / name)
        region = _render_region(driver, shot)
        c = driver.find_element(By.TAG_NAME, "canvas").rect
        red = (region[..., 0] > region[..., 2] + 0.2) & (region.max(-1) > 0.2)
        blue = (region[..., 2] > region[..., 0] + 0.2) & (region.max(-1) > 0.2)
        ok = red.sum() > 300 and blue.sum() > 300
        seen.update(region=region.shape, red=int(red.sum()), blue=int(blue.sum()))
        return (region, (int(c["x"] * dpr), int(c["y"] * dpr)), red, blue) if ok else None

    _wait("both spheres rendered", lambda: spheres("p0.png"), 90, 0.5)
    time.sleep(2.0)  # the full-resolution frame
    got = spheres("p0.png")
    assert got is not None, seen
    region0, (ox, oy), red, blue = got
    green = np.array([0.125, 0.75, 0.25], dtype=np.float32)

    # Pick mode on, the colour set, a click on the middle of the red sphere
    _press(driver, _checkbox(driver, "Pick mode"))
    _wait("Pick mode", lambda: "click on the render" in body(), 30)
    _set_input(driver, _text_input(driver, "New colour"), "#20c040")
    ys, xs = np.nonzero(red)
    k = int(((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2).argmin())
    _click_render(driver, (ox + int(xs[k]), oy + int(ys[k])))
    _wait("the pick", lambda: "pick at" in body() or "Error" in body(), 120)
    assert "Error" not in body(), body()
    _wait("the commit", lambda: "committed from the pick" in body() or "Error" in body(), 180)
    assert "Error" not in body(), body()
    assert list((run_dir / "edits").glob("edit_*_selection.png"))

    def turned():
        region = _render_region(driver, _screenshot(driver, tmp_path / "p1.png"))
        if region.shape != region0.shape:
            return None
        was = np.abs(region0[red] - green).mean()
        ok = np.abs(region[red] - green).mean() < 0.6 * was
        return (region,) if ok else None

    (region1,) = _wait("the red sphere to turn green", turned, 60, 0.5)
    assert np.abs(region1[blue] - region0[blue]).mean() < 0.05  # the other sphere stays

    # a click on the background: one line in the panel, nothing saved, the viewer keeps serving
    n_files = len(list((run_dir / "edits").iterdir()))
    _click_render(driver, (ox + 3, oy + 3))
    _wait("the background error", lambda: "background" in body(), 60)
    assert len(list((run_dir / "edits").iterdir())) == n_files
    _press(driver, _checkbox(driver, "Pick mode"))
    _wait("Pick mode off", lambda: "Pick mode off" in body(), 30)

    # undo restores the render
    _press(driver, button("Undo"))

    def restored():
        region = _render_region(driver, _screenshot(driver, tmp_path / "p2.png"))
        ok = region.shape == region0.shape and np.abs(region[red] - region0[red]).mean() < 0.03
        return (region,) if ok else None

    _wait("the render to come back", restored, 60, 0.5)
