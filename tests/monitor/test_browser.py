"""The monitor page in headless Chromium (selenium with the system chromedriver): during a fake-rig scan
and during a replay the orientation, the level trace, the sphere and the running reconstruction update,
and the page says what it shows (skipped without chromium and chromedriver: apt-get install chromium
chromium-driver)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import httpx
import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

from monitor_helpers import SCAN_OVERRIDES
from dipnet.monitor.replay import Replay
from dipnet.monitor.server import Monitor
from dipnet.monitor.worker import ReconWorker
from script_modules import SCRIPTS
from test_server import free_port, running

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")

pytestmark = [pytest.mark.browser, pytest.mark.slow, pytest.mark.seen_first,
              pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None,
                                 reason="chromium or chromedriver not installed "
                                        "(apt-get install chromium chromium-driver)")]


@pytest.fixture
def browser():
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
                 "--disable-dev-shm-usage", "--window-size=1400,2200"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


def wait_for(driver, script: str, timeout: float = 120.0, what: str = ""):
    """Poll ``script`` (JavaScript returning a value) in the page until it is truthy; returns it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what or script}; "
                         f"page: {driver.find_element('tag name', 'body').text[:1500]}")


def readings(driver) -> int:
    return int(driver.execute_script("return +document.body.dataset.readings || 0"))


def check_updates(driver, url: str, mode: str) -> None:
    """The page follows the scan: the mode, more readings, a new orientation, the trace, the sphere, a
    reconstruction, no JavaScript error."""
    if driver.current_url != url:
        driver.get(url)
    wait_for(driver, f"return document.body.dataset.mode === '{mode}'", what=f"mode {mode}")
    wait_for(driver, "return +document.body.dataset.readings > 0", what="a first reading")
    first_readings, first_orientation = readings(driver), driver.find_element("id", "orientation").text
    wait_for(driver, f"return +document.body.dataset.readings > {first_readings}", what="more readings")
    wait_for(driver, f"return document.getElementById('orientation').textContent !== {first_orientation!r}",
             what="the next orientation")
    wait_for(driver, "const gd = document.getElementById('trace'); "
                     "return gd.data.length && gd.data[0].name === 'measured' && gd.data[0].y.length > 0",
             what="the new dip's level trace")
    statuses = driver.execute_script("return document.getElementById('sphere').data.map(t => t.name);")
    assert any(s.startswith("done") for s in statuses), statuses
    wait_for(driver, "return +document.body.dataset.recon >= 1", what="a running reconstruction")
    assert driver.execute_script("return document.getElementById('recon3d').data[0].type") == "mesh3d"
    assert driver.execute_script("return document.getElementById('slices').data.length") == 6
    assert "from " in driver.find_element("id", "recon-info").text
    wait_for(driver, "const gd = document.getElementById('trace'); return gd.data.length === 2",
             what="the predicted trace")
    errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
    assert errors == []


def test_the_page_follows_a_fake_rig_scan(browser, tmp_path):
    """``scripts/scan.py monitor=true``: the scan and, beside it, the monitor process."""
    port = free_port()
    run = tmp_path / "scan"
    # 10 dips of ~7 s: the monitor process and the page (plotly.js) come up within the first dips on a loaded machine
    command = [sys.executable, str(SCRIPTS / "scan.py"), f"hydra.run.dir={run}", *SCAN_OVERRIDES[1:], "n_dips=10",
               "protocol.settle_s=0.25", "sensor.device.timeout=10", "monitor=true", f"monitor_port={port}"]
    scan = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = f"http://127.0.0.1:{port}/"
        deadline = time.monotonic() + 60
        while True:                                                  # the monitor process starts beside the scan
            try:
                httpx.get(url + "api/state").raise_for_status()
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline and scan.poll() is None, "the monitor did not come up"
                time.sleep(0.3)
        check_updates(browser, url, "live")
        assert "MPos" in browser.find_element("id", "report").text      # the controller's status report
    finally:
        output = scan.communicate(timeout=300)[0]
    assert scan.returncode == 0, output
    assert "monitor stopped; to look at the scan again: python scripts/monitor.py" in output


def test_the_page_follows_a_replay(browser, recorded_scan, tmp_path):
    target = tmp_path / "replay" / "rawscan.jsonl"
    replay = Replay(recorded_scan, target, speed=1.0)
    raw_span = replay.raw.orientations[-1].time_s[-1] - replay.raw.orientations[0].time_s[0]
    replay.speed = raw_span / 40.0                                   # the recording in about 40 s
    monitor = Monitor(target, replay=True, worker=ReconWorker(target, every=2, resolution=16, nice=0))
    monitor.start()
    try:
        with running(monitor) as (_, url):
            browser.get(url + "/")
            wait_for(browser, "return document.body.dataset.mode", what="the page")   # before the replay starts
            replay.start()
            check_updates(browser, url + "/", "replay")
            assert "replay of a recorded scan" in browser.find_element("id", "banner").text
    finally:
        replay.stop()
        monitor.close()
