"""Open a page of tools/js in headless Chromium (Debian's chromium + chromium-driver) and return window.t2bsResult."""

from __future__ import annotations

import functools
import http.server
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import pytest

JS = Path(__file__).resolve().parents[1] / "tools" / "js"
CHROMEDRIVER = "/usr/bin/chromedriver"


def node_modules() -> Path:
    """tools/js/node_modules with the validator, three and three-vrm (npm install when missing; skip without node)."""
    if shutil.which("node") is None:
        pytest.skip("node is not installed (scripts/setup.sh installs it with the system packages)")
    needed = ("gltf-validator", "three", "@pixiv/three-vrm")
    if not all((JS / "node_modules" / n).exists() for n in needed):
        if shutil.which("npm") is None:
            pytest.skip("npm is not installed")
        subprocess.run(["npm", "install", "--no-audit", "--no-fund", "--silent"], cwd=JS, check=True, timeout=300)
    return JS / "node_modules"


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {
        **http.server.SimpleHTTPRequestHandler.extensions_map,
        ".js": "text/javascript",
        ".mjs": "text/javascript",
        ".glb": "model/gltf-binary",
        ".vrm": "model/gltf-binary",
    }

    def log_message(self, *args):  # keep pytest output clean
        pass


def run_page(page: str, files: dict[str, Path], query: str, tmp_path: Path, timeout: float = 60) -> dict:
    """Serve tools/js with ``files`` (served name -> path) copied in, open ``page?query``, return its result."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None or not Path(CHROMEDRIVER).exists():
        pytest.skip("Debian's chromium + chromium-driver are not installed (scripts/setup.sh installs them)")
    node_modules()
    webdriver = pytest.importorskip("selenium.webdriver", reason="pip install selenium (the test extra)")
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.support.ui import WebDriverWait

    served = []
    for name, path in files.items():  # dot files next to the page: never committed
        shutil.copy(path, JS / name)
        served.append(JS / name)
    handler = functools.partial(_QuietHandler, directory=str(JS))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        "--disable-dev-shm-usage",
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        f"--user-data-dir={tempfile.mkdtemp(prefix='t2bs-chrome-', dir=tmp_path)}",
    ):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    try:
        driver.get(f"http://127.0.0.1:{server.server_address[1]}/{page}?{query}")
        return WebDriverWait(driver, timeout).until(lambda d: d.execute_script("return window.t2bsResult || null"))
    finally:
        driver.quit()
        server.shutdown()
        for p in served:
            p.unlink(missing_ok=True)
