"""A headless Chromium driven over the DevTools protocol, for the web view's tests.

Debian's `chromium` package, started with a fresh profile and a debugging port on
loopback; commands go over its websocket (the `websockets` package viser brings).
Enough to load a page, read its state with JavaScript, click, drag and take screenshots.
"""

from __future__ import annotations

import base64
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class Browser:
    def __init__(self, width: int = 1400, height: int = 900) -> None:
        from websockets.sync.client import connect

        if CHROMIUM is None:
            raise RuntimeError("chromium is not installed (apt-get install chromium)")
        self.profile = tempfile.mkdtemp(prefix="chromium-")
        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu-sandbox",
             "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
             "--no-first-run", "--no-default-browser-check", "--disable-extensions",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile}", f"--window-size={width},{height}",
             "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True)  # its own process group: the launcher script forks
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().count("\n") >= 1):
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("chromium did not start")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        targets = json.loads(_http_get(f"http://127.0.0.1:{port}/json/list"))
        page = next(t for t in targets if t["type"] == "page")
        self.ws = connect(page["webSocketDebuggerUrl"], max_size=64 * 2**20)
        self._ids = itertools.count(1)
        self.events: list[dict] = []  # the protocol's events, as they came (Network.*, ...)
        self.call("Page.enable")
        self.call("Runtime.enable")

    def call(self, method: str, **params) -> dict:
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            # generous: a page rendering WebGL in software on a loaded machine can take a
            # minute to answer (a screenshot waits for the next frame it draws)
            msg = json.loads(self.ws.recv(timeout=180))
            if "method" in msg:
                self.events.append(msg)
                del self.events[:-5000]
            elif msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def js(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                      awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"javascript failed: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 20.0, poll_s: float = 0.1):
        """Evaluate until truthy; the value (or the last one, after a timeout)."""
        deadline = time.monotonic() + timeout_s
        value = None
        while time.monotonic() < deadline:
            try:
                value = self.js(expression)
            except RuntimeError as exc:  # the page being swapped under a navigation
                if "navigated or closed" not in str(exc) and "context" not in str(exc):
                    raise
                value = None
            if value:
                return value
            time.sleep(poll_s)
        return value

    def text(self) -> str:
        return self.js("document.body ? document.body.innerText : \"\"") or ""

    def screenshot(self, path: Path | None = None) -> bytes:
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            Path(path).write_bytes(png)
        return png

    def mouse(self, kind: str, x: float, y: float, buttons: int = 1, modifiers: int = 0) -> None:
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left",
                  buttons=buttons, clickCount=1, modifiers=modifiers)

    def click(self, x: float, y: float) -> None:
        self.mouse("mouseMoved", x, y, buttons=0)
        self.mouse("mousePressed", x, y)
        self.mouse("mouseReleased", x, y, buttons=0)

    def drag(self, x0, y0, x1, y1, modifiers: int = 0, steps: int = 8) -> None:
        self.mouse("mouseMoved", x0, y0, buttons=0, modifiers=modifiers)
        self.mouse("mousePressed", x0, y0, modifiers=modifiers)
        for k in range(1, steps + 1):
            t = k / steps
            self.mouse("mouseMoved", x0 + (x1 - x0) * t, y0 + (y1 - y0) * t,
                       modifiers=modifiers)
            time.sleep(0.02)
        self.mouse("mouseReleased", x1, y1, buttons=0, modifiers=modifiers)

    def click_text(self, selector: str, text: str) -> None:
        """Click (as a user, with the mouse) the element matching selector whose text is
        text."""
        r = self.js(f"""(() => {{
            const e = [...document.querySelectorAll({selector!r})]
                .find(e => e.innerText.trim() === {text!r});
            if (!e) return null;
            const r = e.getBoundingClientRect();
            return [r.left + r.width / 2, r.top + r.height / 2]; }})()""")
        assert r is not None, f"no {selector} reading {text!r} on the page"
        self.click(*r)

    def type_into(self, label: str, text: str) -> None:
        """Type into the text input labelled `label`, as a user would, and press Enter."""
        r = self.js(f"""(() => {{
            const l = [...document.querySelectorAll('label, div, span, p')]
                .find(e => e.childElementCount === 0 && e.innerText.trim() === {label!r});
            const i = l && [...document.querySelectorAll(
                    'input[type=text], input:not([type])')]
                .find(i => l.compareDocumentPosition(i) & Node.DOCUMENT_POSITION_FOLLOWING);
            if (!i) return null;
            const r = i.getBoundingClientRect();
            return [r.left + r.width / 2, r.top + r.height / 2]; }})()""")
        assert r is not None, f"no input labelled {label!r}"
        self.click(*r)
        self.js("document.activeElement.select && document.activeElement.select()")
        self.call("Input.insertText", text=text)
        for kind in ("keyDown", "keyUp"):
            self.call("Input.dispatchKeyEvent", type=kind, key="Enter", code="Enter",
                      windowsVirtualKeyCode=13)

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:  # noqa: BLE001 - closing what may be gone
            pass
        try:
            os.killpg(self.proc.pid, signal.SIGTERM)  # the group this browser started
            self.proc.wait(5)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        shutil.rmtree(self.profile, ignore_errors=True)


def _http_get(url: str) -> str:
    import urllib.request

    with urllib.request.urlopen(url, timeout=10) as r:  # loopback only
        return r.read().decode()
