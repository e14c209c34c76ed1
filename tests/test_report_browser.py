"""report.html of the bundled example in a real browser: Debian's headless chromium, driven by Selenium through
Debian's chromedriver (no browser download), with every network request blocked. The 3D viewer starts
without a console error, its WebGL canvas draws, the slider changes the drawn key frame, a lesion click
shows its diameter profile, and nothing is fetched. Also the reconstruction's interface for other tools:
the .vtp arrays and qca_sr.dcm.

Needs chromium, chromium-driver (apt) and selenium (dev extra): `.ci/run` installs them. Outside CI the test
skips, saying what is missing; in CI (CI set) a missing piece fails it.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
MAX_REPORT_BYTES = 5 * 1024 * 1024


def _need(ok: bool, why: str):
    if not ok:
        if os.environ.get("CI"):
            pytest.fail(f"{why}: .ci/run installs it, so CI must not skip this test")
        pytest.skip(why)


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    from stages.reconstruct import reconstruct

    out = tmp_path_factory.mktemp("demo")
    reconstruct(REPO / "examples" / "run_a.dcm", REPO / "examples" / "run_b.dcm", out)
    return out


@pytest.fixture(scope="module")
def browser():
    _need(Path(CHROMIUM).exists(), "chromium not installed (apt-get install chromium)")
    _need(Path(CHROMEDRIVER).exists(), "chromedriver not installed (apt-get install chromium-driver)")
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.options import Options
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        _need(False, "selenium not installed (the dev extra)")
    opts = Options()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--window-size=1700,1300",
                # WebGL without a GPU: chromium's software renderer
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                # no way out: an unroutable proxy and no name resolution
                "--proxy-server=127.0.0.1:9", "--host-resolver-rules=MAP * ~NOTFOUND"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    driver.execute_cdp_cmd("Network.enable", {})
    driver.execute_cdp_cmd("Network.setBlockedURLs", {"urls": ["http://*", "https://*", "ws://*", "wss://*", "ftp://*"]})
    yield driver
    driver.quit()


def _canvas_pixels(driver) -> np.ndarray:
    from PIL import Image

    png = driver.find_element("id", "view3d").screenshot_as_png
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.int16)


def _wait(driver, script, timeout=30.0):
    end = time.time() + timeout
    while time.time() < end:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    return driver.execute_script(script)


def test_interface_files_for_other_tools(recon):
    import pydicom
    vtk = pytest.importorskip("vtk")

    page = (recon / "report.html").read_text()
    assert not re.findall(r"<img[^>]*\ssrc=\"(?!data:)", page)
    assert "WebGLRenderer" in page and (recon / "report.html").stat().st_size <= MAX_REPORT_BYTES
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(recon / "graphs_00.vtp"))
    reader.Update()
    poly = reader.GetOutput()
    for name in ("Radius", "MaximumInscribedSphereRadius", "VesselName"):
        assert poly.GetPointData().GetAbstractArray(name) is not None, name
    assert poly.GetCellData().GetArray("CenterlineIds") is not None
    assert poly.GetFieldData().GetAbstractArray("SPACE").GetValue(0) == "LPS"
    sr = pydicom.dcmread(recon / "qca_sr.dcm")
    run_a = pydicom.dcmread(REPO / "examples" / "run_a.dcm", stop_before_pixels=True)
    assert sr.Modality == "SR" and sr.StudyInstanceUID == run_a.StudyInstanceUID


def test_report_in_headless_chromium(recon, browser):
    from selenium.webdriver.common.keys import Keys

    d = browser
    d.get((recon / "report.html").as_uri())
    state = _wait(d, "return document.getElementById('view3d').dataset.state")
    error = d.execute_script("return document.getElementById('viewer-error').textContent")
    assert state == "ready", f"viewer state {state!r}: {error}"

    # the WebGL canvas draws the tree: many pixels differ from the background
    first = _canvas_pixels(d)
    background = np.array([0x11, 0x11, 0x11])
    drawn = np.abs(first - background).sum(-1) > 30
    assert drawn.mean() > 0.01, f"only {drawn.mean():.4f} of the canvas differs from the background"

    # the slider (moved with the keyboard, as a user would) shows the next key frame
    keys = json.loads(d.execute_script("return document.getElementById('model').textContent"))["frames"]
    assert len(keys) >= 2
    overlay_0 = d.find_element("id", "overlay").get_attribute("src")
    d.find_element("id", "frame").send_keys(Keys.ARROW_RIGHT)
    assert _wait(d, "return document.getElementById('view3d').dataset.frame") == keys[1]["key"]
    _wait(d, "return Number(document.getElementById('view3d').dataset.rendered) > 2")
    time.sleep(0.3)
    second = _canvas_pixels(d)
    assert np.abs(second - first).sum(-1).astype(bool).sum() > 50, "the drawn frame did not change"
    assert d.find_element("id", "overlay").get_attribute("src") != overlay_0
    assert d.find_element("id", "frame_label").text == keys[1]["key"]

    # a lesion marker's click shows its diameter profile
    # markers of nearby lesions may overlap, and a later one is drawn over an earlier one: click the last one,
    # which nothing covers, as a user would
    markers = [m for m in d.find_elements("css selector", "#labels .lesion") if m.is_displayed()]
    assert markers, "no lesion marker visible"
    assert d.find_element("id", "lesion-panel").is_displayed() is False
    markers[-1].click()
    panel = d.find_element("id", "lesion-panel")
    assert panel.is_displayed() and panel.get_attribute("data-lesion") == markers[-1].get_attribute("data-lesion")
    assert d.find_elements("css selector", "#lesion-profile svg polyline")
    assert "% diameter stenosis" in d.find_element("id", "lesion-text").text
    # a narrowing the views do not confirm has its own (grey) marker, and its panel says it is not a lesion
    qca = json.loads((recon / "qca.json").read_text())
    unconfirmed = {n["id"] for v in qca["vessels"] for n in v.get("unconfirmed_narrowings", [])}
    for m in markers:
        assert ("unconfirmed" in m.get_attribute("class")) == (m.get_attribute("data-lesion") in unconfirmed)
    if "unconfirmed" in markers[-1].get_attribute("class"):
        assert "Not reported as a lesion" in d.find_element("id", "lesion-text").text

    # play steps through the key frames; reset puts the first view back
    d.find_element("id", "play").click()
    _wait(d, f"return document.getElementById('view3d').dataset.frame !== '{keys[1]['key']}'", timeout=5)
    d.find_element("id", "play").click()
    d.find_element("id", "reset").click()

    # nothing went to the network, and nothing was logged as an error
    requests = [json.loads(e["message"])["message"] for e in d.get_log("performance")]
    urls = [m["params"]["request"]["url"] for m in requests if m.get("method") == "Network.requestWillBeSent"]
    assert urls and all(u.startswith(("file:", "data:", "blob:")) for u in urls), urls
    errors = [e for e in d.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors
