"""Screenshots of a web page in headless Chromium, driven over the DevTools protocol.

Used to check the viewer in a real browser (tests, CI): Chromium is started with a fresh profile, the
page is loaded, and screenshots are taken until ``ready(image)`` accepts one or time runs out.
Needs only a ``chromium`` binary (``scripts/install-browser.sh``) and the ``websockets`` package that
viser already depends on.
"""

from __future__ import annotations

import base64
import io
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

BROWSER_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-default-apps",
    "--disable-extensions",
    "--no-first-run",
    "--no-default-browser-check",
    "--disable-quic",
    "--disable-dev-shm-usage",
    "--remote-allow-origins=*",
]


def find_browser() -> str | None:
    """Path of a Chromium/Chrome binary ($RMAVATAR_CHROMIUM first), or None."""
    explicit = os.environ.get("RMAVATAR_CHROMIUM")
    if explicit:
        return explicit if os.path.isfile(explicit) and os.access(explicit, os.X_OK) else None
    for name in BROWSER_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(url: str, width: int = 640, height: int = 480, timeout: float = 60.0,
               ready: Callable[[np.ndarray], bool] | None = None, browser: str | None = None,
               settle: float = 1.0, steps: Sequence[Callable[[], object]] = ()) -> list[np.ndarray]:
    """Load ``url`` in headless Chromium and return screenshots [H,W,3] uint8.

    Screenshots are taken every ``settle`` seconds until ``ready(image)`` is true (then one more after
    ``settle``, so a page still drawing is not caught mid-frame) or ``timeout`` passes; that is the first
    image. Then each of ``steps`` is called (e.g. to move the viewer's camera from Python) and another
    screenshot is taken ``settle`` seconds later: one image per step follows.
    """
    browser = browser or find_browser()
    if browser is None:
        raise FileNotFoundError("no chromium binary found (run scripts/install-browser.sh)")
    profile = tempfile.mkdtemp(prefix="rmavatar-chromium-")
    cmd = [browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
           f"--window-size={width},{height}", "about:blank"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        port = _devtools_port(Path(profile), proc, timeout=30.0)
        ws_url = _page_websocket(port)
        return _drive(ws_url, url, width, height, timeout, ready, settle, steps)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)


def _devtools_port(profile: Path, proc: subprocess.Popen, timeout: float) -> int:
    marker = profile / "DevToolsActivePort"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode(errors="replace")[-2000:] if proc.stderr else ""
            raise RuntimeError(f"chromium exited with code {proc.returncode}: {err}")
        if marker.exists():
            lines = marker.read_text().split()
            if lines:
                return int(lines[0])
        time.sleep(0.1)
    raise TimeoutError("chromium did not open its DevTools port")


def _page_websocket(port: int) -> str:
    deadline = time.monotonic() + 10.0
    while True:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as resp:
            targets = json.load(resp)
        pages = [t for t in targets if t.get("type") == "page"]
        if pages:
            return pages[0]["webSocketDebuggerUrl"]
        if time.monotonic() > deadline:
            raise RuntimeError("chromium has no page target")
        time.sleep(0.1)


def _drive(ws_url, url, width, height, timeout, ready, settle, steps) -> list[np.ndarray]:
    from PIL import Image
    from websockets.sync.client import connect

    ids = itertools.count(1)
    with connect(ws_url, max_size=None, open_timeout=10) as ws:

        def call(method: str, **params):
            msg_id = next(ids)
            ws.send(json.dumps({"id": msg_id, "method": method, "params": params}))
            while True:  # skip events until our reply
                reply = json.loads(ws.recv(timeout=30))
                if reply.get("id") == msg_id:
                    if "error" in reply:
                        raise RuntimeError(f"DevTools {method}: {reply['error']}")
                    return reply.get("result", {})

        def shot() -> np.ndarray:
            data = call("Page.captureScreenshot", format="png")["data"]
            return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

        call("Page.enable")
        call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        call("Page.navigate", url=url)
        deadline = time.monotonic() + timeout
        image = None
        while time.monotonic() < deadline:
            time.sleep(settle)
            try:
                image = shot()
            except RuntimeError:  # the page is still being attached while it loads
                continue
            if ready is not None and ready(image):
                time.sleep(settle)
                image = shot()
                break
        if image is None:
            raise TimeoutError(f"could not take a screenshot of {url} within {timeout} s")
        images = [image]
        for step in steps:
            step()
            time.sleep(settle)
            images.append(shot())
        return images
