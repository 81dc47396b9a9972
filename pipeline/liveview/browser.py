"""A headless Chromium driven over the DevTools protocol (loopback only), for the live view's tests and
benchmark: open the page, read values from it while it runs, take a screenshot, kill the browser.

The browser is started with ``--remote-debugging-port=0`` (it picks a free port and writes it into
``DevToolsActivePort`` in its profile folder) and a fresh profile; the protocol runs over a WebSocket
(aiohttp's client) in a thread of its own. Every call has a timeout.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from roomcap.core.errors import InputError


def find_chromium() -> str | None:
    """The Chromium (or Chrome) executable on PATH, None when there is none."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


class HeadlessBrowser:
    """``with HeadlessBrowser(profile_dir) as b: b.open(url); b.evaluate("1+1"); b.screenshot(png)``."""

    def __init__(
        self, profile_dir: str | Path, size_wh: tuple[int, int] = (1600, 1100), chromium: str | None = None
    ):
        self.exe = chromium or find_chromium()
        if self.exe is None:
            raise InputError("no Chromium found: apt-get install chromium (the CI installs it).")
        self.profile = Path(profile_dir)
        self.size = size_wh
        self.proc: subprocess.Popen[bytes] | None = None
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="cdp", daemon=True)
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._ws: Any = None
        self._session: Any = None
        self.page_errors: list[str] = []  # uncaught exceptions and console.error calls of the page

    def __enter__(self) -> HeadlessBrowser:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self, timeout_s: float = 30.0) -> None:
        self.profile.mkdir(parents=True, exist_ok=True)
        port_file = self.profile / "DevToolsActivePort"
        port_file.unlink(missing_ok=True)
        flags = [
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-background-timer-throttling",
            "--disable-renderer-backgrounding",
            "--remote-debugging-address=127.0.0.1",
            "--remote-debugging-port=0",
            f"--user-data-dir={self.profile}",
            f"--window-size={self.size[0]},{self.size[1]}",
            "--hide-scrollbars",
            "about:blank",
        ]
        self.proc = subprocess.Popen([self.exe, *flags], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t0 = time.monotonic()
        while not port_file.exists() or len(port_file.read_text().split()) < 2:
            if time.monotonic() - t0 > timeout_s or self.proc.poll() is not None:
                self.close()
                raise RuntimeError("headless Chromium did not start (no DevToolsActivePort)")
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        self._thread.start()
        self._run(self._connect(port), timeout_s)

    def _run(self, coro: Any, timeout_s: float) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout_s)

    async def _connect(self, port: int) -> None:
        import aiohttp  # lazy: loads aiohttp

        self._session = aiohttp.ClientSession()
        for _ in range(100):
            async with self._session.get(f"http://127.0.0.1:{port}/json/list") as r:
                pages = [t for t in await r.json(content_type=None) if t.get("type") == "page"]
            if pages:
                break
            await asyncio.sleep(0.05)
        self._ws = await self._session.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0)
        self._loop.create_task(self._read())
        await self._call("Runtime.enable", {})  # the page's exceptions and console errors: page_errors

    async def _read(self) -> None:
        async for msg in self._ws:
            m = json.loads(msg.data)
            if m.get("method") == "Runtime.exceptionThrown":
                d = m["params"]["exceptionDetails"]
                self.page_errors.append(str(d.get("exception", {}).get("description") or d.get("text")))
            elif m.get("method") == "Runtime.consoleAPICalled" and m["params"].get("type") == "error":
                self.page_errors.append(" ".join(str(a.get("value", "")) for a in m["params"]["args"]))
            fut = self._waiting.pop(m.get("id", -1), None)
            if fut is not None and not fut.done():
                fut.set_result(m)

    async def _call(self, method: str, params: dict[str, Any]) -> Any:
        i = next(self._ids)
        fut = self._loop.create_future()
        self._waiting[i] = fut
        await self._ws.send_str(json.dumps({"id": i, "method": method, "params": params}))
        m = await fut
        if "error" in m:
            raise RuntimeError(f"{method}: {m['error']}")
        return m.get("result", {})

    def call(self, method: str, params: dict[str, Any] | None = None, timeout_s: float = 30.0) -> Any:
        """One DevTools protocol command; its result."""
        return self._run(self._call(method, params or {}), timeout_s)

    def open(self, url: str) -> None:
        self.call("Page.navigate", {"url": url})

    def evaluate(self, expression: str, timeout_s: float = 10.0) -> Any:
        """The value of a JavaScript expression in the page."""
        r = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True}, timeout_s)
        return r.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float = 30.0, poll_s: float = 0.1) -> Any:
        """Evaluate until the expression is truthy; its value, or None after ``timeout_s``."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout_s:
            v = self.evaluate(expression)
            if v:
                return v
            time.sleep(poll_s)
        return None

    def screenshot(self, path: str | Path) -> Path:
        r = self.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True})
        Path(path).write_bytes(base64.b64decode(r["data"]))
        return Path(path)

    def kill(self) -> None:
        """Kill the browser process at once (SIGKILL), as a crash or a closed laptop would."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def close(self) -> None:
        self.kill()
        if self._thread.is_alive():

            async def _close() -> None:
                if self._session is not None:
                    await self._session.close()

            try:
                self._run(_close(), 5.0)
            except Exception:  # noqa: BLE001 - closing after a kill: nothing to keep
                pass
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5.0)
