"""The facewire command in child processes, as a user runs it in a shell.

:class:`Facewire` starts ``python -m facewire ARGS`` (optionally behind a prefix such as
``ip netns exec NS``) and reads its output lines as they come, so a test can wait for what
the command says ("a receiver joined; sending") instead of sleeping.
"""

from __future__ import annotations

import os
import queue
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import cv2

FACEWIRE = [sys.executable, "-m", "facewire"]
TIMEOUT_S = 90.0


def environment() -> dict[str, str]:
    return dict(os.environ, PYOPENGL_PLATFORM="egl", PYTHONUNBUFFERED="1")


class Facewire:
    """``facewire ARGS`` running in its own process."""

    def __init__(
        self, *args: str, prefix: Sequence[str] = (), cwd: Path | None = None, name: str = ""
    ) -> None:
        self.name = name or args[0]
        self.args = [*prefix, *FACEWIRE, *args]
        self.process = subprocess.Popen(
            self.args,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=environment(),
            cwd=cwd,
        )
        self.lines: list[str] = []
        self.stderr: list[str] = []
        self._new: queue.Queue[str | None] = queue.Queue()
        self._readers = [
            threading.Thread(target=self._read, args=(self.process.stdout, True), daemon=True),
            threading.Thread(target=self._read, args=(self.process.stderr, False), daemon=True),
        ]
        for reader in self._readers:
            reader.start()

    def _read(self, stream: object, is_stdout: bool) -> None:
        for line in stream:  # type: ignore[attr-defined]
            line = line.rstrip("\n")
            if is_stdout:
                self.lines.append(line)
                self._new.put(line)
            else:
                self.stderr.append(line)
        if is_stdout:
            self._new.put(None)

    def expect(self, text: str, timeout_s: float = TIMEOUT_S) -> str:
        """Wait for an output line containing ``text``; returns it."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = self._new.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"{self.name} did not say {text!r}: {self.output()}") from None
            if line is None:
                self._new.put(None)  # stays ended for the next expect
                raise AssertionError(f"{self.name} ended without {text!r}: {self.output()}")
            if text in line:
                return line

    def signal(self, sig: int = signal.SIGTERM) -> None:
        self.process.send_signal(sig)

    def wait(self, timeout_s: float = TIMEOUT_S) -> int:
        try:
            code = self.process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(
                f"{self.name} did not end in {timeout_s:g} s: {self.output()}"
            ) from None
        for reader in self._readers:
            reader.join(timeout=10)
        return code

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)

    def output(self) -> str:
        return "\n".join(
            [f"$ {' '.join(self.args)}", *self.lines, *(f"stderr: {e}" for e in self.stderr)]
        )


def run_facewire(*args: str, timeout_s: float = TIMEOUT_S) -> subprocess.CompletedProcess[str]:
    """``facewire ARGS`` to its end."""
    return subprocess.run(
        [*FACEWIRE, *args], capture_output=True, text=True, env=environment(), timeout=timeout_s
    )


def hang_up(*processes: Facewire) -> None:
    """SIGTERM each in turn, as Ctrl-C would, and check it ended cleanly."""
    for process in processes:
        process.signal(signal.SIGTERM)
        assert process.wait() == 0, process.output()


def kill_all(*processes: Facewire | None) -> None:
    """Whatever is still running (a test's clean-up)."""
    for process in processes:
        if process is not None:
            process.kill()


def all_end_well(*processes: Facewire) -> None:
    """Wait for each to end with status 0 (its output in the failure); kill what is left."""
    try:
        for process in processes:
            assert process.wait() == 0, process.output()
    finally:
        for process in processes:
            process.kill()


def sent_frames(line: str) -> tuple[int, str]:
    """From ``send``'s last line, "sent N frames (WHY[, M left out: ...]); said bye": the
    input's frames it read (N sent and M left out by a machine too busy for them), and WHY."""
    match = re.fullmatch(
        r"sent (\d+) frames \(([^,)]+)(?:, (\d+) left out: this machine was behind)?\); said bye",
        line,
    )
    assert match, line
    return int(match[1]) + int(match[3] or 0), match[2]


def free_ports(count: int) -> int:
    """The first of ``count`` consecutive TCP ports that are free on 127.0.0.1 now."""
    for _ in range(200):
        base = random.randrange(20000, 60000)
        sockets = []
        try:
            for port in range(base, base + count):
                s = socket.socket()
                sockets.append(s)
                s.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
        finally:
            for s in sockets:
                s.close()
    raise RuntimeError("no free ports")


def count_frames(path: Path) -> int:
    """Frames OpenCV decodes from ``path`` (0 if it cannot open it: e.g. an MP4 without its
    index, as a writer killed before closing leaves)."""
    capture = cv2.VideoCapture(str(path))
    frames = 0
    try:
        while capture.read()[0]:
            frames += 1
    finally:
        capture.release()
    return frames


def wait_for_file(path: Path, size: int, process: Facewire, timeout_s: float = TIMEOUT_S) -> None:
    """Until ``path`` has at least ``size`` bytes (a recording that frames are going into)."""
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and path.stat().st_size >= size):
        assert process.process.poll() is None, f"{process.name} ended: {process.output()}"
        assert time.monotonic() < deadline, f"{path} stayed under {size} bytes"
        time.sleep(0.1)
