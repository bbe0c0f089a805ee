"""End to end in a real browser: Debian's chromium, headless, driven by selenium against ``pihim live``.

Skipped when selenium, chromium or chromedriver is missing (no browser is ever downloaded). Set
``PIHIM_SCREENSHOT_DIR`` to keep the screenshot.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

selenium = pytest.importorskip("selenium")
pytest.importorskip("uvicorn")
from selenium import webdriver  # noqa: E402
from selenium.webdriver.chrome.service import Service  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402

import pihim  # noqa: E402
from pihim.camera.frames import read_frame  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER), reason="needs Debian's chromium and chromium-driver")


def _wait(cond, timeout, what):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _start(source: str, captures: Path) -> tuple[str, subprocess.Popen]:
    """``pihim live --source SOURCE`` on a free port, in its own process; returns its URL and process."""
    env = {**os.environ, "PYTHONPATH": str(Path(pihim.__file__).resolve().parents[1])}  # the pihim imported here
    size = ["--size", "640x512"] if source == "synthetic" else []  # a folder's frames have their own size
    cmd = [sys.executable, "-m", "pihim", "live", "--source", source, *size, "--port", "0",
           "--captures", str(captures), "--duration", "120", "--json", "--fps", "15"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    line = proc.stderr.readline()  # "pihim live: ... at http://127.0.0.1:PORT/ (Ctrl-C to stop)"
    m = re.search(r"(http://127\.0\.0\.1:\d+/)", line)
    if m is None:
        proc.kill()
        raise AssertionError(f"server did not start: {line}{proc.stderr.read()}")
    return m.group(1), proc


@pytest.fixture
def server(tmp_path):
    """``pihim live --source synthetic`` on a free port."""
    url, proc = _start("synthetic", tmp_path / "captures")
    yield url, proc, tmp_path / "captures"
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def _driver(tmp_path: Path) -> webdriver.Chrome:
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                f"--user-data-dir={tmp_path / 'chrome'}", "--window-size=1400,760"):
        opts.add_argument(arg)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)


def test_page_shows_frames_and_captures_a_raw_frame(server, tmp_path):
    url, proc, captures = server
    driver = _driver(tmp_path)
    try:
        driver.get(url)
        frames = _wait(lambda: int(driver.execute_script("return document.body.dataset.frames || 0")) >= 10, 60,
                       "10 frames in the page")
        assert frames
        for name in ("s0", "dolp", "aop"):  # 640x512 raw -> 320x256 super-pixels, shown whole
            _wait(lambda n=name: driver.execute_script(f"return document.getElementById('img-{n}').naturalWidth")
                  == 320, 20, f"the {name} preview decoded at 320 px")
        assert driver.find_element(By.ID, "conn").text == "live"
        assert driver.find_element(By.ID, "exposure").text.endswith("µs")
        assert "%" in driver.find_element(By.ID, "saturated").text
        # a DoLP figure; "- (saturated)" for the two frames after each 10x brightness step of the synthetic source
        # (the simulated camera's actuation latency), so wait for a frame that is not one of them
        _wait(lambda: re.match(r"^\d\.\d\d", driver.find_element(By.ID, "dolp").text), 20, "a DoLP figure")
        # frames keep coming
        n0 = int(driver.execute_script("return document.body.dataset.frames"))
        _wait(lambda: int(driver.execute_script("return document.body.dataset.frames")) >= n0 + 5, 20,
              "5 more frames")
        driver.find_element(By.ID, "label").send_keys("e2e")
        driver.find_element(By.ID, "capture").click()
        raw_name = _wait(lambda: driver.execute_script("return document.body.dataset.lastCapture || ''"), 30,
                         "the capture result")
        assert raw_name.endswith("-e2e.tiff")
        assert driver.find_element(By.ID, "capture-result").text.startswith("saved ")
        shot = tmp_path / "live.png"
        driver.save_screenshot(str(shot))
        if os.environ.get("PIHIM_SCREENSHOT_DIR"):
            shutil.copy(shot, Path(os.environ["PIHIM_SCREENSHOT_DIR"]) / "pihim-live.png")
    finally:
        driver.quit()
    raw = read_frame(captures / raw_name)
    assert raw.data.shape == (512, 640) and raw.data.dtype == np.uint16
    rec = json.loads((captures / raw_name.replace(".tiff", ".json")).read_text())
    assert rec["raw_file"] == raw_name and rec["label"] == "e2e"
    # Ctrl-C stops the server cleanly: session JSON on stdout, 130, no traceback
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert json.loads(out.strip().splitlines()[-1])["captures"] == 1


def test_page_shows_a_bad_frame_while_serving(tmp_path):
    """A frame of the wrong size in a replayed folder: the page shows the error, frames keep coming."""
    import tifffile

    from .conftest import mosaic

    d = tmp_path / "replay"
    d.mkdir()
    for k in range(3):
        tifffile.imwrite(d / f"f{k}.tiff", mosaic(shape=(64, 80), value=1000 + 500 * k))
    tifffile.imwrite(d / "f3.tiff", mosaic(shape=(32, 40)))
    url, proc = _start(str(d), tmp_path / "captures")
    driver = _driver(tmp_path)
    try:
        driver.get(url)
        _wait(lambda: "f3.tiff: frame is 40x32 (WxH) but the stream is 80x64; skipped"
              in driver.find_element(By.ID, "error").text, 60, "the error banner")
        n0 = int(driver.execute_script("return document.body.dataset.frames || 0"))
        _wait(lambda: int(driver.execute_script("return document.body.dataset.frames")) >= n0 + 10, 30,
              "frames after the error")
        assert driver.find_element(By.ID, "conn").text == "live"
    finally:
        driver.quit()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 143 and "Traceback" not in err
    assert json.loads(out.strip().splitlines()[-1])["frames_skipped"] >= 1
