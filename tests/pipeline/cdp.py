"""A minimal headless-Chromium driver over the DevTools protocol (for the inspection page's tests).

Uses the Debian ``chromium`` package and ``websocket-client`` (the ``test`` extra); the browser runs
with the network closed, in a fresh profile, and is killed on :meth:`Browser.close`.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def chromium_path() -> str | None:
    """The Chromium executable, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def screenshot(url: str, out: str | Path, size: tuple[int, int] = (1400, 900)) -> Path:
    """PNG screenshot of a page by ``chromium --screenshot``."""
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([chromium_path(), *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
                        f"--window-size={size[0]},{size[1]}", f"--screenshot={out}", url],
                       capture_output=True, timeout=120, check=True)
    return Path(out)


class Browser:
    """One headless Chromium with one page, driven by DevTools protocol commands."""

    def __init__(self, size: tuple[int, int] = (1400, 900)):
        import websocket

        self.profile = tempfile.mkdtemp(prefix="pv-chromium-")
        self.proc = subprocess.Popen([chromium_path(), *CHROMIUM_FLAGS, f"--user-data-dir={self.profile}",
                                      f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
                                      "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.time() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            if time.time() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not open its DevTools port")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
        page = next(t for t in targets if t["type"] == "page")
        version = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/version", timeout=10))
        # no Origin header: Chromium refuses DevTools connections from origins it was not told to allow
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=30, suppress_origin=True)
        self.browser_ws = websocket.create_connection(version["webSocketDebuggerUrl"], timeout=30,
                                                      suppress_origin=True)
        self._id = 0

    def _send(self, ws, method: str, **params):
        self._id += 1
        ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            msg = json.loads(ws.recv())
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def command(self, method: str, **params) -> dict:
        """A DevTools command on the page."""
        return self._send(self.ws, method, **params)

    def browser_command(self, method: str, **params) -> dict:
        """A DevTools command on the browser (e.g. ``Browser.setDownloadBehavior``)."""
        return self._send(self.browser_ws, method, **params)

    def open(self, url: str, ready: str = "window.polyvecPage !== undefined", timeout: float = 30) -> None:
        """Navigate and wait until the JavaScript expression ``ready`` is true."""
        self.command("Page.navigate", url=url)
        deadline = time.time() + timeout
        while not self.eval(f"document.readyState === 'complete' && ({ready})"):
            if time.time() > deadline:
                raise TimeoutError(f"{url} did not become ready")
            time.sleep(0.1)

    def eval(self, expression: str):
        """Value of a JavaScript expression (JSON-able)."""
        r = self.command("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def click(self, x: float, y: float) -> None:
        """A left mouse click at viewport coordinates."""
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.command("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left",
                         buttons=0 if kind == "mouseMoved" else 1, clickCount=0 if kind == "mouseMoved" else 1)

    def click_selector(self, selector: str) -> None:
        """Click the centre of the element matching a CSS selector."""
        r = self.eval(f"(() => {{const b = document.querySelector({json.dumps(selector)}).getBoundingClientRect();"
                      f"return [b.x + b.width / 2, b.y + b.height / 2]}})()")
        self.click(*r)

    def close(self) -> None:
        """Close the connections, end the browser process and remove its profile."""
        for ws in (getattr(self, "ws", None), getattr(self, "browser_ws", None)):
            if ws is not None:
                ws.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        shutil.rmtree(self.profile, ignore_errors=True)
