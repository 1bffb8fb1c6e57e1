"""Opens an HTML file in a real headless browser: Chromium and its chromedriver from the Debian
packages (`chromium`, `chromium-driver`; scripts/test.sh installs them), driven by Selenium
with the driver given explicitly, so Selenium Manager never tries to download one.

`open_page` returns what a person would see: the screenshot of the whole page and, for every
<img>, whether the browser loaded and decoded it (`complete` and a natural width > 0)."""
import io
import os
import shutil
from dataclasses import dataclass

import numpy as np
from PIL import Image
from selenium import webdriver
from selenium.webdriver.chrome.service import Service

CHROMIUM = os.environ.get("CHROMIUM_BIN") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = os.environ.get("CHROMEDRIVER_BIN") or shutil.which("chromedriver") or "/usr/bin/chromedriver"


@dataclass
class Page:
    title: str
    screenshot: np.ndarray  # H x W x 3, uint8
    images: list  # [(src, loaded, natural_width, natural_height)]
    svgs: int
    tables: int


def open_page(path, width=1400):
    for exe in (CHROMIUM, CHROMEDRIVER):
        assert os.access(exe, os.X_OK), (
            f"{exe} is missing: the report's browser test needs Chromium and chromedriver "
            "(Debian: apt-get install chromium chromium-driver; scripts/test.sh installs them)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              f"--window-size={width},1000", "--allow-file-access-from-files"):
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(executable_path=CHROMEDRIVER), options=opts)
    try:
        driver.get(f"file://{os.path.abspath(path)}")
        # `driver.get` returns after the load event: every eager <img> has loaded or failed.
        images = driver.execute_script(
            "return Array.from(document.images).map(i => "
            "[i.getAttribute('src'), i.complete && i.naturalWidth > 0, i.naturalWidth, i.naturalHeight]);")
        svgs = driver.execute_script("return document.querySelectorAll('svg polyline').length;")
        tables = driver.execute_script("return document.querySelectorAll('table').length;")
        height = driver.execute_script("return document.documentElement.scrollHeight;")
        driver.set_window_size(width, min(int(height) + 100, 16000))
        png = driver.get_screenshot_as_png()
        title = driver.title
    finally:
        driver.quit()
    shot = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    return Page(title, shot, [tuple(i) for i in images], int(svgs), int(tables))
