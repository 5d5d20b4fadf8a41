"""Headless Chromium driven over the DevTools protocol: load a page, run a script in it, click,
take a screenshot, and list every request the page made. Used by the viewer's browser tests and
its benchmark (flows/bench/viewer.py); nothing here is needed to run the viewer.

Chromium runs with no GPU (WebGL through its software rasteriser), no sandbox (containers), no
background network, a fresh profile, and a host resolver that resolves no name but localhost, so
a page that tried to reach the network would fail and show it in :attr:`Chromium.requests`.
The protocol goes over the ``websockets`` client (a dependency of viser).
"""

from __future__ import annotations

import base64
import functools
import io
import itertools
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

#: Debian's package; ``chromium-browser`` / ``google-chrome`` elsewhere
BINARIES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--no-default-browser-check",
    "--hide-scrollbars",
    "--mute-audio",
    # WebGL on the software rasteriser (recent Chromium wants it asked for explicitly)
    "--enable-unsafe-swiftshader",
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
)


class ChromiumError(RuntimeError):
    """Chromium could not be started or did not answer."""


@functools.cache
def find_chromium() -> str | None:
    """Path of a Chromium binary on PATH that runs (``--version`` answers: Ubuntu's ``chromium``
    package is a stub that asks for a snap), or None."""
    for name in BINARIES:
        path = shutil.which(name)
        if path is None:
            continue
        try:
            ran = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if ran.returncode == 0 and ("Chromium" in ran.stdout or "Chrome" in ran.stdout):
            return path
    return None


class Chromium:
    """One headless Chromium with one page. ``with Chromium() as b: b.goto(url); b.screenshot()``."""

    def __init__(self, width: int = 1280, height: int = 800, binary: str | None = None):
        from websockets.sync.client import connect

        binary = binary or find_chromium()
        if binary is None:
            raise ChromiumError(f"no Chromium on PATH (looked for {', '.join(BINARIES)})")
        self.profile = Path(tempfile.mkdtemp(prefix="mobileocc-chromium-"))
        self.proc = subprocess.Popen(
            [
                binary,
                *FLAGS,
                f"--user-data-dir={self.profile}",
                "--remote-debugging-port=0",
                f"--window-size={width},{height}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self._ids = itertools.count(1)
        self.events: list[dict] = []
        try:
            port = self._devtools_port(timeout_s=60.0)
            page = self._page_target(port)
            self.ws = connect(page, max_size=None, open_timeout=30)
            self.call("Page.enable")
            self.call("Runtime.enable")
            self.call("Network.enable")
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, timeout_s: float) -> int:
        path = self.profile / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise ChromiumError(f"chromium exited at start (status {self.proc.returncode})")
            if path.exists():
                text = path.read_text().split()
                if text:
                    return int(text[0])
            time.sleep(0.1)
        raise ChromiumError(f"chromium wrote no {path.name} within {timeout_s:.0f} s")

    @staticmethod
    def _page_target(port: int) -> str:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
            targets = json.load(r)
        pages = [t for t in targets if t.get("type") == "page"]
        if not pages:
            raise ChromiumError("chromium has no page target")
        return pages[0]["webSocketDebuggerUrl"]

    def call(self, method: str, timeout_s: float = 300.0, **params):
        """Send one protocol command and return its result (events meanwhile are kept)."""
        ident = next(self._ids)
        self.ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        deadline = time.monotonic() + timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ChromiumError(f"{method}: no answer within {timeout_s:.0f} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == ident:
                if "error" in msg:
                    raise ChromiumError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if "method" in msg:
                self.events.append(msg)

    @property
    def requests(self) -> list[str]:
        """URLs of every request the page started (Network.requestWillBeSent), in order."""
        return [
            e["params"]["request"]["url"]
            for e in self.events
            if e.get("method") == "Network.requestWillBeSent"
        ]

    def goto(self, url: str, timeout_s: float = 120.0) -> None:
        """Open ``url`` and wait for its load event."""
        seen = len(self.events)
        self.call("Page.navigate", url=url)
        self.wait_event("Page.loadEventFired", timeout_s, since=seen)

    def wait_event(self, method: str, timeout_s: float, since: int = 0) -> dict:
        """The first event ``method`` at or after position ``since`` of :attr:`events`, read
        from the connection until it comes (ChromiumError after ``timeout_s``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            for e in self.events[since:]:
                if e.get("method") == method:
                    return e
            since = len(self.events)
            left = deadline - time.monotonic()
            if left <= 0:
                raise ChromiumError(f"no {method} within {timeout_s:.0f} s")
            try:
                msg = json.loads(self.ws.recv(timeout=left))
            except TimeoutError:
                continue
            if "method" in msg:
                self.events.append(msg)

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (promises awaited)."""
        res = self.call(
            "Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True
        )
        if "exceptionDetails" in res:
            raise ChromiumError(f"script failed: {res['exceptionDetails'].get('text')}")
        return res.get("result", {}).get("value")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB of the page as shown now."""
        from PIL import Image

        data = self.call("Page.captureScreenshot", format="png")["data"]
        return np.array(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))

    def wait_for(self, predicate, timeout_s: float, interval_s: float = 0.5):
        """Call ``predicate()`` until it returns something other than None or False; returns
        it, or raises ChromiumError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            value = predicate()
            if value is not None and value is not False:
                return value
            if time.monotonic() > deadline:
                raise ChromiumError(f"condition not met within {timeout_s:.0f} s")
            time.sleep(interval_s)

    def cpu_seconds(self) -> float:
        """CPU time (user + system) used so far by Chromium's processes (the browser and its
        renderer, GPU and utility children), from /proc; 0.0 where /proc is not there."""
        import os

        ticks = os.sysconf("SC_CLK_TCK")
        stats = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                except OSError:
                    continue
                stats[int(entry.name)] = (int(fields[1]), int(fields[11]) + int(fields[12]))
        tree, total, grew = {self.proc.pid}, 0, True
        while grew:
            grew = False
            for pid, (ppid, _) in stats.items():
                if ppid in tree and pid not in tree:
                    tree.add(pid)
                    grew = True
        for pid in tree:
            total += stats.get(pid, (0, 0))[1]
        return total / ticks

    def close(self) -> None:
        ws = getattr(self, "ws", None)
        if ws is not None:
            try:
                ws.close()
            except Exception:
                pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
