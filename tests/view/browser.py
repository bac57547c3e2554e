"""A recording in Rerun's web viewer under headless Chromium (Debian's `chromium`), driven
over the DevTools protocol on a pipe (no driver, no extra package): serve an .rrd with
`rerun --serve-web`, load the page, take screenshots until the view stands still.
Used by tests/view/test_web_viewer.py and benchmarks/webview.py."""

from __future__ import annotations

import base64
import contextlib
import fcntl
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
RERUN = Path(sys.executable).parent / "rerun"


class Browser:
    """Headless Chromium with the DevTools protocol on file descriptors 3 and 4."""

    def __init__(self, width: int = 1600, height: int = 1000) -> None:
        assert CHROMIUM is not None
        self._profile = tempfile.TemporaryDirectory(prefix="gcs-chromium-")
        to_browser, to_us = os.pipe(), os.pipe()
        # Chromium reads commands on fd 3 and answers on fd 4: move our pipe ends out of
        # the way, then put the browser's ends exactly there for the child to inherit.
        high = [fcntl.fcntl(f, fcntl.F_DUPFD, 100) for f in (*to_browser, *to_us)]
        for f in (*to_browser, *to_us):
            os.close(f)
        read_cmd, self._write, self._read, write_out = high
        saved = [fcntl.fcntl(f, fcntl.F_DUPFD, 100) if _is_open(f) else -1 for f in (3, 4)]
        os.dup2(read_cmd, 3)
        os.dup2(write_out, 4)
        try:
            self.proc = subprocess.Popen(
                [
                    CHROMIUM,
                    "--headless=new",
                    "--no-sandbox",
                    "--enable-unsafe-swiftshader",
                    "--use-angle=swiftshader",
                    f"--window-size={width},{height}",
                    "--remote-debugging-pipe",
                    f"--user-data-dir={self._profile.name}",
                    "about:blank",
                ],
                pass_fds=(3, 4),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,
            )
        finally:
            for fd, old in zip((3, 4), saved, strict=True):
                if old >= 0:
                    os.dup2(old, fd)
                    os.close(old)
                else:
                    os.close(fd)
            os.close(read_cmd)
            os.close(write_out)
        self._buf = b""
        self._id = 0
        self._session = ""
        self._attach()

    def _attach(self) -> None:
        """Attach to the page (again, after the page replaced itself)."""
        pages = [t for t in self.call("Target.getTargets")["targetInfos"] if t["type"] == "page"]
        target = {"targetId": pages[0]["targetId"], "flatten": True}
        self._session = str(self.call("Target.attachToTarget", target)["sessionId"])
        self.call("Page.enable", session=True)

    def call(self, method: str, params: dict[str, Any] | None = None, session: bool = False) -> Any:
        """One DevTools command; its result (events in between are skipped)."""
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = self._session
        os.write(self._write, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self._buf:
                chunk = os.read(self._read, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"chromium closed the DevTools pipe during {method}")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            answer = json.loads(raw)
            if answer.get("id") == self._id:
                if "error" in answer:
                    raise RuntimeError(f"{method}: {answer['error']}")
                return answer["result"]

    def open(self, url: str) -> None:
        self.call("Page.navigate", {"url": url}, session=True)

    def screenshot(self) -> bytes:
        try:
            data = self.call("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        except RuntimeError as exc:
            if "Not attached" not in str(exc):
                raise
            self._attach()
            data = self.call("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        return base64.b64decode(data)

    def close(self) -> None:
        os.close(self._write)
        os.close(self._read)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)  # the browser and its helpers
        self.proc.wait()
        self._profile.cleanup()


def _is_open(fd: int) -> bool:
    try:
        os.fstat(fd)
    except OSError:
        return False
    return True


@contextlib.contextmanager
def served(rrd: Path, timeout_s: float = 60.0) -> Iterator[str]:
    """`rerun --serve-web` of a recording on free ports; yields the page's URL (read from
    what the server prints)."""
    proc = subprocess.Popen(
        [str(RERUN), "--serve-web", "--web-viewer-port", "0", "--port", "0", str(rrd)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "NO_COLOR": "1", "RUST_LOG": "info"},
        start_new_session=True,  # the entry point runs the server as a child: end both
    )
    try:
        assert proc.stdout is not None
        url = ""
        end = time.monotonic() + timeout_s
        for line in proc.stdout:
            if "connect at " in line:
                url = line.split("connect at ", 1)[1].split()[0]
                break
            if time.monotonic() > end:
                break
        assert url, "rerun --serve-web printed no address"
        yield url
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=10)


def load_until_steady(
    url: str,
    timeout_s: float = 90.0,
    interval_s: float = 1.0,
    width: int = 1600,
    visited: str | None = None,
) -> tuple[bytes, float]:
    """Open url and take a screenshot every interval_s until STEADY_SHOTS in a row are the
    same and drawn (a page still blank while the viewer loads does not count): the viewer
    has loaded everything and stopped drawing. That screenshot and the seconds it took;
    an AssertionError at the timeout. visited: a page the browser loads the same way
    first, untimed (a browser that has opened the viewer before: its code compiled and
    cached)."""
    browser = Browser(width=width)
    try:
        if visited is not None:
            _steady(browser, visited, timeout_s, interval_s)
        return _steady(browser, url, timeout_s, interval_s)
    finally:
        browser.close()


STEADY_SHOTS = 3
"""Screenshots in a row that must be the same: on a loaded machine the viewer can draw
its layout and then wait over a second for the recording's data (two in a row then
caught a page with empty panels)."""


def _steady(browser: Browser, url: str, timeout_s: float, interval_s: float) -> tuple[bytes, float]:
    start = time.monotonic()
    browser.open(url)
    previous = b""
    same = 1
    while time.monotonic() - start < timeout_s:
        time.sleep(interval_s)  # a polling interval, not a wait for a process
        shot = browser.screenshot()
        same = same + 1 if shot == previous else 1
        if same >= STEADY_SHOTS and drawn(shot):
            return shot, time.monotonic() - start - (STEADY_SHOTS - 1) * interval_s
        previous = shot
    raise AssertionError(f"the view never stood still in {timeout_s:.0f} s")


DRAWN_COLOURS = 200
"""Distinct colours above which a screenshot shows a drawn view, not a blank page."""


def drawn(png: bytes) -> bool:
    img = decode_png(png)
    return len(np.unique(img.reshape(-1, 3), axis=0)) > DRAWN_COLOURS


def decode_png(data: bytes) -> np.ndarray:
    """A PNG as an RGB array [height, width, 3]."""
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
