"""Headless Chromium driven through the DevTools protocol over a pipe (no websocket, no extra package).

``--remote-debugging-pipe`` makes Chromium read protocol commands from file descriptor 3 and
write replies and events to descriptor 4, each a JSON message ended by a NUL byte. The browser
runs in its own process group, killed (SIGKILL) when the :class:`Browser` closes, whatever
happened: no process outlives a test.
"""

from __future__ import annotations

import base64
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

__all__ = ["Browser", "drawn_fraction", "figures_drawn", "find_chromium", "INSTALL_HINT"]

INSTALL_HINT = ("no Chromium found (looked for chromium, chromium-browser, google-chrome, and $CHROMIUM); "
                "install it with `apt-get install chromium` (Debian/Ubuntu) to run the report's browser test")


def find_chromium() -> str | None:
    """Path of a Chromium-family browser, or None."""
    for name in (os.environ.get("CHROMIUM", ""), "chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        if name and (path := shutil.which(name)):
            return path
    return None


#: Run in the child: put the pipe ends on fds 3 and 4 (as --remote-debugging-pipe expects), then exec the browser.
_EXEC_WITH_PIPE = """import fcntl, os, sys
r, w = (fcntl.fcntl(int(fd), fcntl.F_DUPFD, 10) for fd in sys.argv[1:3])
os.dup2(r, 3, inheritable=True)
os.dup2(w, 4, inheritable=True)
os.execv(sys.argv[3], sys.argv[3:])
"""


class Browser:
    """One headless browser with one page; every call times out after ``timeout`` seconds."""

    def __init__(self, executable: str, *, timeout: float = 30.0, width: int = 1200, height: int = 900) -> None:
        self.timeout = timeout
        self.events: list[dict[str, Any]] = []
        self._profile = tempfile.mkdtemp(prefix="starlog-chromium-")
        self._stderr = open(Path(self._profile) / "stderr.txt", "wb")  # noqa: SIM115 - closed in close()
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        args = [executable, "--headless=new", "--remote-debugging-pipe", "--no-sandbox", "--disable-gpu",
                "--no-first-run", "--no-default-browser-check", "--disable-extensions", "--mute-audio",
                "--disable-background-networking", "--disable-dev-shm-usage", f"--user-data-dir={self._profile}",
                f"--window-size={width},{height}", "about:blank"]
        self.process = subprocess.Popen(
            [sys.executable, "-c", _EXEC_WITH_PIPE, str(to_browser_r), str(from_browser_w), *args], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._stderr,
            pass_fds=(to_browser_r, from_browser_w), start_new_session=True)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._replies: dict[int, queue.Queue[dict[str, Any]]] = {}
        self._events: queue.Queue[dict[str, Any]] = queue.Queue()
        self._next_id = 0
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        try:
            target = self.call("Target.createTarget", url="about:blank")["targetId"]
            self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            for domain in ("Page", "Runtime", "Log"):
                self.call(f"{domain}.enable", session=True)
            self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                      deviceScaleFactor=1, mobile=False)
        except BaseException:
            self.close()
            raise

    def _stderr_tail(self) -> str:
        self._stderr.flush()
        text = (Path(self._profile) / "stderr.txt").read_text(errors="replace")[-2000:]
        return f"; its stderr ends with:\n{text}" if text else ""

    def _read(self) -> None:
        buffer = b""
        with os.fdopen(self._from_browser, "rb", buffering=0) as pipe:
            while True:
                block = pipe.read(1 << 16)
                if not block:
                    return
                buffer += block
                *messages, buffer = buffer.split(b"\0")
                for raw in messages:
                    message = json.loads(raw)
                    if "id" in message:
                        self._replies.setdefault(message["id"], queue.Queue()).put(message)
                    else:
                        self._events.put(message)

    def call(self, method: str, *, session: bool = False, **params: Any) -> dict[str, Any]:
        """Send one command and wait for its reply (an error reply raises RuntimeError)."""
        with self._lock:
            self._next_id += 1
            ident = self._next_id
            self._replies.setdefault(ident, queue.Queue())
        message: dict[str, Any] = {"id": ident, "method": method, "params": params}
        if session:
            message["sessionId"] = self.session
        try:
            os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        except BrokenPipeError:
            raise RuntimeError(f"Chromium exited (status {self.process.poll()}){self._stderr_tail()}") from None
        try:
            reply = self._replies[ident].get(timeout=self.timeout)
        except queue.Empty:
            raise TimeoutError(f"Chromium did not answer {method} within {self.timeout} s{self._stderr_tail()}") from None
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply.get("result", {})

    def wait_for(self, method: str) -> dict[str, Any]:
        """Wait for the next event named ``method`` (events seen meanwhile are kept in :attr:`events`)."""
        deadline = time.monotonic() + self.timeout
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"no {method} event within {self.timeout} s")
            try:
                event = self._events.get(timeout=remaining)
            except queue.Empty:
                continue
            self.events.append(event)
            if event.get("method") == method:
                return event

    def drain(self) -> None:
        """Move the events received so far into :attr:`events`."""
        while True:
            try:
                self.events.append(self._events.get_nowait())
            except queue.Empty:
                return

    def open(self, path: Path) -> None:
        """Load a local file and wait for its load event."""
        self.call("Page.navigate", session=True, url=path.resolve().as_uri())
        self.wait_for("Page.loadEventFired")

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression!r} threw: {result['exceptionDetails']}")
        return result["result"].get("value")

    def errors(self) -> list[str]:
        """Console errors, uncaught exceptions and error log entries seen so far."""
        self.drain()
        out = []
        for event in self.events:
            method, params = event.get("method"), event.get("params", {})
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description", ""))) for a in params["args"]))
            elif method == "Runtime.exceptionThrown":
                out.append("exception: " + json.dumps(params["exceptionDetails"])[:500])
            elif method == "Log.entryAdded" and params["entry"].get("level") == "error":
                out.append(f"log: {params['entry'].get('text')} ({params['entry'].get('url', '')})")
        return out

    def screenshot(self, x: float, y: float, width: float, height: float) -> np.ndarray:
        """The page's pixels in a box (page coordinates, CSS px) as a BGR array."""
        data = self.call("Page.captureScreenshot", session=True, format="png", captureBeyondViewport=True,
                         clip={"x": x, "y": y, "width": width, "height": height, "scale": 1})["data"]
        image = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            raise RuntimeError("Chromium's screenshot is not a PNG")
        return image

    def close(self) -> None:
        """Kill the browser's whole process group and remove its profile."""
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        try:
            self.process.wait(timeout=10)
            deadline = time.monotonic() + 10
            while self.alive() and time.monotonic() < deadline:  # the renderers die a moment later
                time.sleep(0.05)
        finally:
            for fd in (self._to_browser,):
                try:
                    os.close(fd)
                except OSError:
                    pass
            self._stderr.close()
            shutil.rmtree(self._profile, ignore_errors=True)

    def alive(self) -> bool:
        """Whether any process of the browser's process group still exists."""
        try:
            os.killpg(self.process.pid, 0)
        except ProcessLookupError:
            return False
        return True

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


#: Each ``figure.fig``'s name and the page box of its SVG (page coordinates, CSS px), as JSON.
_FIGURE_BOXES = ("JSON.stringify([...document.querySelectorAll('figure.fig')].map(f => {"
                 "const r = f.querySelector('svg').getBoundingClientRect();"
                 "return {name: f.dataset.figure, x: r.x + scrollX, y: r.y + scrollY, w: r.width, h: r.height};}))")


def drawn_fraction(image: np.ndarray) -> float:
    """Fraction of pixels unlike the box's most common colour (0 for a blank box)."""
    flat = image.reshape(-1, image.shape[-1]).astype(np.int32)
    colors, counts = np.unique(flat, axis=0, return_counts=True)
    background = colors[np.argmax(counts)]
    return float(np.mean(np.abs(flat - background).sum(axis=1) > 24))


def figures_drawn(browser: Browser, page: Path) -> dict[str, float]:
    """Each figure's drawn fraction in the rendered page (every figure's box larger than 50 x 50 px)."""
    browser.open(page)
    boxes = json.loads(browser.evaluate(_FIGURE_BOXES))
    drawn = {}
    for box in boxes:
        assert box["w"] > 50 and box["h"] > 50, box
        drawn[box["name"]] = drawn_fraction(browser.screenshot(box["x"], box["y"], box["w"], box["h"]))
    return drawn
