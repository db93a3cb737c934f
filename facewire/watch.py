"""Watching a call as it comes in: ``--view HOST:PORT`` serves a page with the live picture
and the call's figures (receiver/live_view.py), ``--window`` opens a window where a display
exists (receiver/window.py). ``receive`` and ``call`` take both.

Without a display ``--window`` ends the command before the call starts, with one line and
exit status 1: the person asked to see the call, and a call they cannot see is not what they
asked for (``--view`` works anywhere). Closing the window hangs up, as Ctrl-C does.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Callable
from typing import Any

logger = logging.getLogger(__name__)

#: Hosts that mean every interface: the URL printed names this machine instead.
_EVERY_INTERFACE = {"0.0.0.0", "::"}


def add_watch_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--view",
        metavar="HOST:PORT",
        help="serve a live view of the call on http://HOST:PORT/ (0.0.0.0 for every "
        "interface; port 0 takes a free one)",
    )
    p.add_argument(
        "--window", action="store_true", help="show the call in a window (needs a display)"
    )


def check_watch_arguments(args: argparse.Namespace) -> None:
    """What can be said wrong before anything starts: ValueError or RuntimeError, one line."""
    from facewire.receiver.live_view import parse_view_address
    from facewire.receiver.window import NoDisplay, display_problem

    if args.view is not None:
        parse_view_address(args.view)
    if args.window and (problem := display_problem()) is not None:
        raise NoDisplay(f"cannot open a window: {problem} (--view HOST:PORT works without one)")


def wants_watching(args: argparse.Namespace) -> bool:
    return args.view is not None or args.window


class Watchers:
    """The live view and the window a command asked for, from construction to :meth:`close`.

    :attr:`sink` goes to the receive loop (None when nothing watches), :meth:`tell` says a
    line to the person at the terminal and on the page, :meth:`stop` adds "the window was
    closed" to a stop request.
    """

    def __init__(self, args: argparse.Namespace, tell: Callable[[str], None]) -> None:
        from facewire.receiver.live_view import LiveView, parse_view_address
        from facewire.receiver.window import Window

        check_watch_arguments(args)
        self._tell = tell
        self.view: LiveView | None = None
        self.window: Window | None = None
        try:
            if args.view is not None:
                host, port = parse_view_address(args.view)
                self.view = LiveView(host, port)
                tell(f"live view on {_url_to_open(self.view)}")
            if args.window:
                self.window = Window("facewire: the other end")
                tell("showing the call in a window (closing it hangs up)")
        except BaseException:
            self.close()
            raise
        sinks: list[Any] = [s for s in (self.view, self.window) if s is not None]
        self.sink: Callable[[Any, Any], None] | None = None
        if len(sinks) == 1:
            self.sink = sinks[0]
        elif sinks:

            def both(frame: Any, report: Any) -> None:
                for sink in sinks:
                    sink(frame, report)

            self.sink = both

    def tell(self, line: str) -> None:
        self._tell(line)
        if self.view is not None:
            self.view.event(line)

    def stop(self, stop: Callable[[], bool]) -> Callable[[], bool]:
        window = self.window
        if window is None:
            return stop
        return lambda: stop() or window.closed

    def close(self) -> None:
        if self.view is not None:
            self.view.close()
        if self.window is not None:
            self.window.close()

    def __enter__(self) -> Watchers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _url_to_open(view: Any) -> str:
    if view.host in _EVERY_INTERFACE:
        return f"http://localhost:{view.port}/ (served on every interface, port {view.port})"
    return view.url
