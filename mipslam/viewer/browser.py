"""Screenshots of the viewer page with headless Chromium (tests, documentation images).

WebGL runs in Chromium's software rasteriser (SwiftShader), so no GPU or display is needed.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from mipslam.errors import MipslamError

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# Flags for a headless browser that starts clean and never reaches out to the network on its own.
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
)


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(url: str, out: str | Path, *, width: int = 960, height: int = 640, wait_ms: int = 8000,
               timeout_s: float = 120.0) -> Path:
    """Load ``url`` in headless Chromium, let it run ``wait_ms`` (virtual time) and write a PNG to ``out``."""
    chromium = find_chromium()
    if chromium is None:
        raise MipslamError("no Chromium found for the screenshot; install it (Debian: apt-get install chromium)")
    out = Path(out).resolve()
    with tempfile.TemporaryDirectory(prefix="mipslam-chromium-") as profile:
        command = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                   f"--virtual-time-budget={wait_ms}", f"--screenshot={out}", url]
        try:
            result = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s,
                                    env={**os.environ, "HOME": profile})
        except subprocess.TimeoutExpired:
            raise MipslamError(f"Chromium did not finish the screenshot of {url} within {timeout_s:.0f} s") from None
    if result.returncode != 0 or not out.is_file():
        tail = (result.stderr or "").strip().splitlines()[-1:] or ["no output"]
        raise MipslamError(f"Chromium could not take the screenshot of {url} (exit {result.returncode}: {tail[0]})")
    return out
