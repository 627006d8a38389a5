"""A real browser and the real ``sowgate dashboard`` process, for tests and the benchmark.

Debian's headless chromium (``/usr/bin/chromium``: ``make test`` installs it with apt where
missing) driven by Playwright for Python pointed at that executable: no browser download.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from tests.helpers import eventually, sowgate_argv
from tests.mosquitto import free_port, port_open

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]


def find_chromium() -> str:
    for candidate in (CHROMIUM, shutil.which("chromium") or ""):
        if candidate and Path(candidate).exists():
            return candidate
    raise RuntimeError("chromium not found: `make test` installs it, or apt-get install chromium")


@contextlib.asynccontextmanager
async def browser_page(
    url: str | None = None, *, width: int = 1400, height: int = 1000,
    http_credentials: Any = None,  # {"username": ..., "password": ...}
) -> AsyncIterator[Any]:
    """A page of a fresh headless chromium (at ``url`` once loaded), closed after the block."""
    from playwright.async_api import async_playwright

    async with async_playwright() as pw:
        browser = await pw.chromium.launch(executable_path=find_chromium(), args=CHROMIUM_ARGS)
        try:
            page = await browser.new_page(viewport={"width": width, "height": height},
                                          http_credentials=http_credentials)
            if url is not None:
                await page.goto(url)
            yield page
        finally:
            await browser.close()


class DashboardProcess:
    """``sowgate dashboard --config FILE --listen 127.0.0.1:PORT`` in its own process."""

    def __init__(self, config: Path, log: Path, port: int | None = None) -> None:
        self.config = config
        self.port = port or free_port()
        self.log = log
        self.proc: asyncio.subprocess.Process | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    async def start(self) -> None:
        with self.log.open("ab") as out:
            self.proc = await asyncio.create_subprocess_exec(
                *sowgate_argv("dashboard", "--config", str(self.config),
                              "--listen", f"127.0.0.1:{self.port}"),
                stdin=asyncio.subprocess.DEVNULL, stdout=out, stderr=out,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        proc = self.proc
        await eventually(
            lambda: proc.returncode is not None or port_open(self.port), 20.0,
            "the dashboard listening", detail=lambda: self.log.read_text(errors="replace"),
        )
        assert proc.returncode is None, self.log.read_text(errors="replace")

    async def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None or proc.returncode is not None:
            return
        proc.terminate()
        try:
            await asyncio.wait_for(proc.wait(), 10.0)
        except TimeoutError:
            proc.kill()
            await proc.wait()


@contextlib.asynccontextmanager
async def dashboard_process(config: Path, log: Path) -> AsyncIterator[DashboardProcess]:
    dash = DashboardProcess(config, log)
    await dash.start()
    try:
        yield dash
    finally:
        await dash.stop()
