"""Screenshots of the viewer page with headless Chromium (tests, documentation images).

Chromium runs headless and is driven over the DevTools protocol (a WebSocket; the ``websockets``
package comes with viser): open the page, wait in real time until it is drawn, capture the
viewport. WebGL runs in Chromium's software rasteriser (SwiftShader), so no GPU or display is
needed. Real-time waiting matters: the page is filled by WebSocket messages from the viewer
server, which Chromium's virtual-time budget (``--screenshot``) does not wait for.
"""
from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable

from mipslam.errors import MipslamError

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# A headless browser that starts clean and never reaches out to the network on its own.
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
    "--remote-debugging-port=0",
)
_HIDE_SOFTWARE_WEBGL_NOTICE = """
for (const node of document.querySelectorAll('[class*="Notification-root"]')) {
  if (node.textContent.includes('Software WebGL')) node.style.display = 'none';
}"""
_DEVTOOLS_LINE = re.compile(r"DevTools listening on (ws://\S+)")


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(url: str, out: str | Path, *, width: int = 960, height: int = 640, settle_s: float = 10.0,
               ready: Callable[[], bool] | None = None, timeout_s: float = 120.0) -> Path:
    """Open ``url`` in headless Chromium and write a PNG of the viewport to ``out``.

    The shot is taken ``settle_s`` seconds (real time) after the page has loaded and ``ready()`` (when
    given, e.g. "the viewer server sees a client") has turned true.
    """
    from websockets.sync.client import connect

    chromium = find_chromium()
    if chromium is None:
        raise MipslamError("no Chromium found for the screenshot; install it (Debian: apt-get install chromium)")
    out = Path(out).resolve()
    deadline = time.monotonic() + timeout_s
    with tempfile.TemporaryDirectory(prefix="mipslam-chromium-") as profile:
        process = subprocess.Popen(
            [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env={**os.environ, "HOME": profile})
        try:
            endpoint = _devtools_endpoint(process, deadline)
            with connect(endpoint, max_size=None, open_timeout=max(1.0, deadline - time.monotonic())) as ws:
                session = _Session(ws, deadline)
                target = session.call("Target.createTarget", url="about:blank")["targetId"]
                session.id = session.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
                session.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                             mobile=False)
                session.call("Page.enable")
                session.call("Page.navigate", url=url)
                session.wait_for("Page.loadEventFired")
                while ready is not None and not ready():
                    if time.monotonic() > deadline:
                        raise MipslamError(f"the page {url} did not connect to the viewer within {timeout_s:.0f} s")
                    time.sleep(0.1)
                time.sleep(settle_s)
                # The page's notice that WebGL runs in software concerns this headless browser, not the viewer.
                session.call("Runtime.evaluate", expression=_HIDE_SOFTWARE_WEBGL_NOTICE)
                data = session.call("Page.captureScreenshot", format="png")["data"]
        except (OSError, TimeoutError) as exc:
            raise MipslamError(f"Chromium could not take the screenshot of {url} ({exc})") from None
        finally:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(base64.b64decode(data))
    return out


def _devtools_endpoint(process: subprocess.Popen, deadline: float) -> str:
    """The browser's DevTools WebSocket address, from the line Chromium prints on start."""
    found: list[str] = []

    def read():
        for line in process.stderr:
            match = _DEVTOOLS_LINE.search(line)
            if match and not found:
                found.append(match.group(1))
        # keep draining so Chromium never blocks on a full pipe

    threading.Thread(target=read, daemon=True).start()
    while not found:
        if process.poll() is not None:
            raise MipslamError(f"Chromium exited at start (status {process.returncode})")
        if time.monotonic() > deadline:
            raise MipslamError("Chromium did not start its DevTools endpoint in time")
        time.sleep(0.05)
    return found[0]


class _Session:
    """Minimal DevTools protocol client: numbered calls and waiting for an event."""

    def __init__(self, ws, deadline: float):
        self.ws, self.deadline, self.id, self._next, self._events = ws, deadline, None, 0, []

    def _receive(self) -> dict:
        remaining = self.deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError("no answer from Chromium in time")
        return json.loads(self.ws.recv(timeout=remaining))

    def call(self, method: str, **params) -> dict:
        self._next += 1
        message = {"id": self._next, "method": method, "params": params}
        if self.id is not None and not method.startswith("Target."):
            message["sessionId"] = self.id
        self.ws.send(json.dumps(message))
        while True:
            reply = self._receive()
            if reply.get("id") == self._next:
                if "error" in reply:
                    raise MipslamError(f"Chromium: {method} failed ({reply['error'].get('message')})")
                return reply.get("result", {})
            self._events.append(reply)

    def wait_for(self, event: str) -> dict:
        while True:
            for i, message in enumerate(self._events):
                if message.get("method") == event:
                    return self._events.pop(i)
            self._events.append(self._receive())
