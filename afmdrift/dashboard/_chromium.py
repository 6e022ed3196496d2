"""Drive a headless Chromium over the DevTools protocol: the page test, the benchmark
and the documentation screenshots use it.

Chromium is the system's (Debian package ``chromium``); nothing is downloaded.
The browser runs with a fresh profile and with its background networking,
component updates and sync off, so the only requests it makes are the page's.
Console errors, uncaught exceptions and failed loads are collected in
:attr:`HeadlessChromium.errors`.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import aiohttp

from afmdrift.dashboard._store import DashboardError

__all__ = ["HeadlessChromium", "find_chromium"]

_LISTENING = re.compile(r"DevTools listening on (ws://\S+)")


def find_chromium() -> str | None:
    """Path of the system's Chromium, or ``None``."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


class HeadlessChromium:
    """One headless Chromium with one page, driven through the DevTools protocol.

    Parameters
    ----------
    width_px, height_px : int
        Viewport size.
    executable : str, optional
        Chromium binary (default: :func:`find_chromium`).
    """

    def __init__(
        self, *, width_px: int = 1400, height_px: int = 1700, executable: str | None = None
    ) -> None:
        self.executable = executable or find_chromium()
        if self.executable is None:
            raise DashboardError("chromium is not installed (Debian: apt-get install chromium)")
        self.width_px = width_px
        self.height_px = height_px
        self.errors: list[str] = []
        self._proc: asyncio.subprocess.Process | None = None
        self._profile: tempfile.TemporaryDirectory[str] | None = None
        self._http: aiohttp.ClientSession | None = None
        self._ws: aiohttp.ClientWebSocketResponse | None = None
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._tasks: list[asyncio.Task[None]] = []

    async def start(self) -> None:
        """Launch the browser and attach to its page."""
        assert self.executable is not None
        self._profile = tempfile.TemporaryDirectory(prefix="afmdrift-chromium-")
        self._proc = await asyncio.create_subprocess_exec(
            self.executable,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--disable-default-apps",
            "--disable-extensions",
            "--no-first-run",
            "--no-default-browser-check",
            "--mute-audio",
            f"--user-data-dir={self._profile.name}",
            "--remote-debugging-address=127.0.0.1",
            "--remote-debugging-port=0",
            f"--window-size={self.width_px},{self.height_px}",
            "about:blank",
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        assert self._proc.stderr is not None
        browser_ws = None
        async with asyncio.timeout(30):
            while browser_ws is None:
                line = await self._proc.stderr.readline()
                if not line:
                    raise DashboardError("chromium exited before its DevTools endpoint was up")
                m = _LISTENING.search(line.decode("utf-8", "replace"))
                if m:
                    browser_ws = m.group(1)
        self._tasks.append(asyncio.create_task(self._drain(self._proc.stderr)))
        port = browser_ws.split("//", 1)[1].split("/", 1)[0]
        self._http = aiohttp.ClientSession()
        async with self._http.get(f"http://{port}/json/list") as resp:
            targets = await resp.json()
        page = next(t for t in targets if t.get("type") == "page")
        self._ws = await self._http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0)
        self._tasks.append(asyncio.create_task(self._read()))
        await self.send("Runtime.enable")
        await self.send("Log.enable")
        await self.send("Page.enable")
        await self.send(
            "Emulation.setDeviceMetricsOverride",
            width=self.width_px,
            height=self.height_px,
            deviceScaleFactor=1,
            mobile=False,
        )

    async def _drain(self, stream: asyncio.StreamReader) -> None:
        while await stream.readline():
            pass

    async def _read(self) -> None:
        assert self._ws is not None
        async for msg in self._ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            doc = json.loads(msg.data)
            if "id" in doc:
                fut = self._pending.pop(doc["id"], None)
                if fut is not None and not fut.done():
                    fut.set_result(doc)
                continue
            self._event(doc.get("method", ""), doc.get("params", {}))
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(DashboardError("chromium closed the DevTools connection"))

    def _event(self, method: str, params: dict[str, Any]) -> None:
        if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            args = params.get("args", [])
            text = " ".join(str(a.get("value", a.get("description", ""))) for a in args)
            self.errors.append(f"console.{params['type']}: {text}")
        elif method == "Runtime.exceptionThrown":
            detail = params.get("exceptionDetails", {})
            exc = detail.get("exception", {}).get("description") or detail.get("text", "")
            self.errors.append(f"exception: {exc}")
        elif method == "Log.entryAdded":
            entry = params.get("entry", {})
            if entry.get("level") == "error":
                self.errors.append(f"log: {entry.get('text', '')} {entry.get('url', '')}".strip())

    async def send(self, method: str, **params: Any) -> dict[str, Any]:
        """One DevTools command; its ``result``."""
        assert self._ws is not None
        ident = next(self._ids)
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[ident] = fut
        await self._ws.send_str(json.dumps({"id": ident, "method": method, "params": params}))
        doc = await asyncio.wait_for(fut, 30)
        if "error" in doc:
            raise DashboardError(f"DevTools {method}: {doc['error'].get('message')}")
        result: dict[str, Any] = doc.get("result", {})
        return result

    async def goto(self, url: str) -> None:
        """Navigate the page to ``url``."""
        await self.send("Page.navigate", url=url)

    async def evaluate(self, expression: str) -> Any:
        """Value of a JavaScript expression in the page (promises are awaited)."""
        result = await self.send(
            "Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True
        )
        if "exceptionDetails" in result:
            raise DashboardError(f"page script failed: {result['exceptionDetails'].get('text')}")
        return result.get("result", {}).get("value")

    async def wait_for(self, expression: str, *, timeout_s: float, interval_s: float = 0.02) -> Any:
        """Poll ``expression`` until it is truthy; its value.

        Raises
        ------
        TimeoutError
            Still falsy after ``timeout_s``.
        """
        async with asyncio.timeout(timeout_s):
            while True:
                with contextlib.suppress(DashboardError):
                    value = await self.evaluate(expression)
                    if value:
                        return value
                await asyncio.sleep(interval_s)

    async def screenshot(self, path: str | Path) -> Path:
        """PNG of the whole page."""
        metrics = await self.send("Page.getLayoutMetrics")
        size = metrics.get("cssContentSize") or metrics.get("contentSize") or {}
        height = int(size.get("height", self.height_px))
        result = await self.send(
            "Page.captureScreenshot",
            format="png",
            captureBeyondViewport=True,
            clip={"x": 0, "y": 0, "width": self.width_px, "height": height, "scale": 1},
        )
        out = Path(path)
        await asyncio.to_thread(out.write_bytes, base64.b64decode(result["data"]))
        return out

    async def close(self) -> None:
        """Close the page connection, stop the browser, remove its profile."""
        if self._ws is not None:
            await self._ws.close()
        if self._http is not None:
            await self._http.close()
        if self._proc is not None and self._proc.returncode is None:
            self._proc.terminate()
            try:
                await asyncio.wait_for(self._proc.wait(), 10)
            except TimeoutError:
                self._proc.kill()
                await self._proc.wait()
        for task in self._tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        if self._profile is not None:
            self._profile.cleanup()

    async def __aenter__(self) -> HeadlessChromium:
        try:
            await self.start()
        except BaseException:
            await self.close()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
