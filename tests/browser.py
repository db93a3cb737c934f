"""A page in headless Chromium (Debian's ``chromium``), driven over the DevTools protocol:
open it, wait until a JavaScript condition holds, read values from the page and take
screenshots.

As a script it runs where a test cannot reach in itself (another network namespace)::

    python tests/browser.py URL --out FOLDER [--shots N] [--gap S]

and prints one JSON line: ``{"looks": [{"shot": PNG path, "page": {...}}, ...]}``, or
``{"error": "..."}`` with exit status 1. :func:`unavailable` says why Chromium cannot run
here (None if it can).
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import itertools
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp

WINDOW = (1100, 700)  # CSS pixels; the device pixel ratio is 1
START_TIMEOUT_S = 60.0
PAGE_TIMEOUT_S = 60.0

#: The live view's page is ready once the picture has come and the figures have been filled.
READY = """(() => {
  const img = document.getElementById("picture");
  const frames = document.getElementById("frames");
  return img !== null && frames !== null && img.complete && img.naturalWidth > 0
    && Number(frames.textContent) >= 15;  // half a second: the rates have pictures to count
})()"""

#: What the live view's page shows, read from its elements.
READ = """(() => {
  const text = (id) => document.getElementById(id).textContent;
  const box = (el) => { const r = el.getBoundingClientRect();
    return {x: r.x, y: r.y, width: r.width, height: r.height}; };
  const kbps = {};
  for (const cell of document.querySelectorAll("[id^=kbps-]")) {
    kbps[cell.id.slice(5)] = cell.textContent;
  }
  const cells = {};
  for (const id of ["fps", "latency", "frames", "size", "kbps-geometry", "kbps-total"]) {
    const cell = document.getElementById(id);
    if (cell) cells[id] = box(cell);
  }
  const img = document.getElementById("picture");
  return {status: text("status"), fps: text("fps"), latency: text("latency"),
          frames: text("frames"), size: text("size"), kbps: kbps, cells: cells,
          picture: box(img), natural: [img.naturalWidth, img.naturalHeight],
          ratio: window.devicePixelRatio};
})()"""


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def unavailable() -> str | None:
    """Why headless Chromium cannot run here, or None."""
    path = chromium()
    if path is None:
        return "no chromium (Debian package chromium; scripts/install-system-deps.sh --test)"
    try:
        done = subprocess.run(
            [path, "--headless", "--no-sandbox", "--dump-dom", "data:text/html,<p>ok"],
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT_S,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"chromium does not run: {exc}"
    if "<p>ok</p>" not in done.stdout:
        return f"chromium does not run: {done.stderr.strip().splitlines()[-1:]}"
    return None


@dataclass
class Look:
    """One screenshot (PNG file) and what the page showed at that moment."""

    shot: Path
    page: dict[str, Any]


class _DevTools:
    """One page target's DevTools connection."""

    def __init__(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        self.ws = ws
        self._ids = itertools.count(1)

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        n = next(self._ids)
        await self.ws.send_json({"id": n, "method": method, "params": params})
        while True:
            message = await self.ws.receive_json(timeout=PAGE_TIMEOUT_S)
            if message.get("id") == n:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    async def evaluate(self, expression: str) -> Any:
        result = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"the page's script failed: {result['exceptionDetails']}")
        return result["result"].get("value")


def _start(profile: Path) -> tuple[subprocess.Popen[bytes], int]:
    path = chromium()
    if path is None:
        raise RuntimeError("no chromium")
    process = subprocess.Popen(
        [
            path, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
            "--no-default-browser-check", "--disable-extensions", "--hide-scrollbars",
            "--force-device-scale-factor=1", f"--window-size={WINDOW[0]},{WINDOW[1]}",
            f"--user-data-dir={profile}", "--remote-debugging-port=0", "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    port_file = profile / "DevToolsActivePort"
    deadline = time.monotonic() + START_TIMEOUT_S
    while True:
        if port_file.exists() and (lines := port_file.read_text().split()) and len(lines) >= 2:
            return process, int(lines[0])
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            raise RuntimeError("chromium did not open its DevTools port")
        time.sleep(0.1)


async def _look(url: str, out: Path, shots: int, gap_s: float, port: int, ready: str) -> list[Look]:
    async with aiohttp.ClientSession() as http:
        async with http.get(f"http://127.0.0.1:{port}/json/list") as r:
            targets = await r.json()
        page = next(t for t in targets if t["type"] == "page")
        async with http.ws_connect(page["webSocketDebuggerUrl"], max_msg_size=0) as ws:
            tools = _DevTools(ws)
            await tools.call("Page.enable")
            await tools.call("Page.navigate", url=url)
            deadline = time.monotonic() + PAGE_TIMEOUT_S
            while not await tools.evaluate(ready):
                if time.monotonic() > deadline:
                    state = await tools.evaluate("document.body ? document.body.innerText : ''")
                    raise RuntimeError(f"the page did not get ready: {state!r}")
                await asyncio.sleep(0.2)
            looks = []
            for i in range(shots):
                if i:
                    await asyncio.sleep(gap_s)
                shown = await tools.evaluate(READ)
                png = await tools.call("Page.captureScreenshot", format="png")
                shot = out / f"page-{i}.png"
                shot.write_bytes(base64.b64decode(png["data"]))
                looks.append(Look(shot, shown))
            return looks


def look_at(
    url: str, out: Path, shots: int = 2, gap_s: float = 1.5, ready: str = READY
) -> list[Look]:
    """Open ``url`` in headless Chromium, wait until the live view's page is ready (the
    JavaScript ``ready`` is true), then take ``shots`` screenshots ``gap_s`` apart into
    ``out`` with what the page showed at each."""
    with tempfile.TemporaryDirectory(prefix="facewire-chromium-") as profile:
        process, port = _start(Path(profile))
        try:
            return asyncio.run(_look(url, out, shots, gap_s, port, ready))
        finally:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("url")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--shots", type=int, default=2)
    parser.add_argument("--gap", type=float, default=1.5)
    args = parser.parse_args()
    try:
        looks = look_at(args.url, args.out, args.shots, args.gap)
    except (RuntimeError, OSError, aiohttp.ClientError, TimeoutError) as exc:
        print(json.dumps({"error": f"{type(exc).__name__}: {exc}"}))
        return 1
    print(json.dumps({"looks": [{"shot": str(look.shot), "page": look.page} for look in looks]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
