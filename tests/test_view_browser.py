"""The viewer in a real browser (issue 14): Debian's chromium + chromium-driver driven by selenium on 127.0.0.1.
A frame arrives and is not blank, lowering the exposure brightens the page's frame, switching the map changes
it. Skipped only where chromium or chromedriver is not installed (.ci/run installs them with apt-get)."""
import io
import shutil
import time

import numpy as np
import pytest
from PIL import Image

from retinexgs.demo.synthetic import make_demo_scene
from retinexgs.train.runner import train_run
from polling import wait_until

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="chromium / chromedriver not installed")

TINY = ["steps=2", "checkpoint.every=2", "log.tensorboard=false", "model.sh_degree=0", "model.max_init_points=800",
        "decomposer.method=lime", "loss.enhance_from=1"]
WIDTH, HEIGHT, PANEL = 900, 700, 560  # window; the GUI panel lies right of x = PANEL


def _wait(cond, seconds=30.0):
    return wait_until(cond, seconds, 0.1)


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    from selenium import webdriver  # required wherever chromium is: the test extra installs it

    from retinexgs.viewer.server import view_run

    root = tmp_path_factory.mktemp("browser")
    scene = make_demo_scene(root / "scene", n_train=2, n_test=1, width=48, height=36, n_points=800)
    train_run(scene, root / "run", ["demo"], TINY, "cpu", progress=False, log=lambda m: None)
    logs = []
    viewer = view_run(root / "run", port=0, device="cpu", log=logs.append, block=False)
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={WIDTH},{HEIGHT}",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):
        options.add_argument(arg)
    options.binary_location = CHROMIUM
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(DRIVER))
    try:
        driver.get(viewer.url)
        yield driver, viewer, logs
    finally:
        driver.quit()
        viewer.stop()


def scene_pixels(driver) -> np.ndarray:
    """The page's 3D view (left of the panel, below the notification corner) as float RGB."""
    shot = np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"), dtype=np.float64)
    return shot[200:, :PANEL]


def settle(viewer, frames_before):
    """Wait for a new frame and for the full-resolution redraw after it, then for the browser to show it."""
    assert _wait(lambda: viewer.frames > frames_before)
    time.sleep(1.0)


def set_number(driver, label, value):
    """Type ``value`` into the number box of the GUI row labelled ``label``."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    row = driver.find_element(By.XPATH,
                              f"//*[normalize-space(text())='{label}']/ancestor::*[.//input[@type='text']][1]")
    box = row.find_element(By.XPATH, ".//input[@type='text']")
    box.send_keys(Keys.CONTROL, "a")
    box.send_keys(str(value), Keys.ENTER)


def test_frame_arrives_exposure_brightens_and_map_switches(page):
    from selenium.webdriver.common.by import By

    driver, viewer, logs = page
    settle(viewer, 0)
    before = scene_pixels(driver)
    assert before.std() > 3 and before.mean() > 2, "the browser shows a blank frame"

    frames = viewer.frames
    set_number(driver, "Exposure", 0.3)
    settle(viewer, frames)
    brighter = scene_pixels(driver)
    assert brighter.mean() > before.mean() + 1, (before.mean(), brighter.mean(), logs)

    frames = viewer.frames
    driver.find_element(By.XPATH, "//input[@role='combobox' and @value='enhanced']").click()
    _wait(lambda: driver.find_elements(By.XPATH, "//*[@role='option' and normalize-space()='depth']"), 5)
    driver.find_element(By.XPATH, "//*[@role='option' and normalize-space()='depth']").click()
    settle(viewer, frames)
    depth = scene_pixels(driver)
    assert np.abs(depth - brighter).mean() > 2, logs
    assert not any("failed" in m for m in logs), logs
