"""``facewire room``: join a call of many people through a NATS relay (docs/rooms.md).

A participant sends its own stream once, as a two-party sender would (the same encoder, the
same bundles), and receives everyone else's, one decoder per peer. Three threads: the sender's
loop (capture, track, encode, publish), the NATS link's event loop, and this one, which opens
and decodes what comes (and records it, one file per peer); each peer's sound plays on a
thread of its own, mixed into the one sound device (facewire/room_sound.py).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import threading
from pathlib import Path
from typing import Any

from facewire.protocol import subjects
from facewire.protocol.media_path import DEFAULT_BUDGET_BPS
from facewire.protocol.sender_keys import SenderKeys, load_peers
from facewire.protocol.sframe import RoomKey, Sealer, new_kid

logger = logging.getLogger(__name__)

#: How long the receiving loop waits for a message before it looks at who went silent.
TICK_S = 0.1


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    from facewire.call import _add_source_arguments, _max_kbps, add_sound_arguments

    p = subparsers.add_parser(
        "room",
        help="join a room: a call of many people through a NATS relay",
        description="Joins a room: sends this end's face once (a camera, a file or the "
        "bundled clip) and rebuilds everyone else's, one recording per person, through a NATS "
        "relay (without --server, one started on loopback). Everything is sealed end to end "
        "with the room's secret (facewire keys --room NAME): the relay cannot see faces.",
    )
    p.add_argument("--room", required=True, help="the room's name")
    p.add_argument("--name", required=True, help="this participant's name in the room")
    p.add_argument(
        "--key", metavar="FILE", required=True,
        help="the room's secret (facewire keys --room NAME makes it), or, with --peer, this "
        "participant's CURVE secret key (facewire keys: NAME.key_secret)",
    )  # fmt: skip
    p.add_argument(
        "--peer", metavar="FILE", action="append", default=[],
        help="with a CURVE --key: a peer's public key, NAME.key (NAME is that peer's name in "
        "the room), or a folder of them; again for each. Only they hear this participant, and "
        "only they are heard",
    )  # fmt: skip
    p.add_argument(
        "--server", metavar="URL", action="append", default=[],
        help="a relay, nats://TOKEN@HOST:PORT or tls://TOKEN@HOST:PORT (again for each node "
        "of a cluster); none: an embedded relay on loopback",
    )  # fmt: skip
    p.add_argument(
        "--tls-ca", metavar="FILE",
        help="trust relays whose TLS certificate this CA (PEM) signed, e.g. the relay's own "
        "self-signed HOST.crt; the connection is then TLS",
    )  # fmt: skip
    _add_source_arguments(p)
    add_sound_arguments(p)
    p.add_argument(
        "--max-kbps", type=_max_kbps, metavar="N",
        help=f"this participant's stream budget (default {DEFAULT_BUDGET_BPS / 1000:g})",
    )  # fmt: skip
    p.add_argument("--record-dir", metavar="DIR", help="record each peer to DIR/NAME.mp4")
    p.add_argument(
        "--view", metavar="HOST:PORT",
        help="serve the gallery (every peer with its name) as a web page, e.g. 127.0.0.1:8080",
    )  # fmt: skip
    p.add_argument("--stats", metavar="FILE.json", help="write the room's figures as JSON")
    p.add_argument(
        "--receive-only", action="store_true",
        help="send nothing: watch the room (leaves once those who came have left)",
    )  # fmt: skip
    p.set_defaults(func=run)


class _SendingSide:
    """The sender's loop in a thread; what ended it is kept for the main thread."""

    def __init__(self, args: argparse.Namespace, link: Any, key: RoomKey | SenderKeys,
                 sealer: Sealer, stop: Any, tell: Any) -> None:  # fmt: skip
        self.args, self.link, self.key, self.sealer = args, link, key, sealer
        self.stop, self.tell = stop, tell
        self.endpoint: Any = None
        self.report: Any = None
        self.dropped = 0  # input frames left out: this end was behind
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, name="room-sender", daemon=True)

    def _run(self) -> None:
        try:
            self._send()
        except BaseException as exc:  # said by the main thread, in one line
            logger.debug("sender failed", exc_info=True)
            self.error = exc
        finally:
            self.done.set()

    def _send(self) -> None:
        from facewire.call import _Source, sound_as_asked
        from facewire.room_sender import RoomSender
        from facewire.sender.audio import with_sound
        from facewire.sender.encoder import FaceEncoder
        from facewire.sender.session import restamped, run_sender, start_session

        args = self.args
        source = _Source(args)
        try:
            # A new scene is a new session, as in a two-party call: its snapshot goes to the
            # room's bucket, and the peers read it when its heartbeat names it (room_peer.py).
            encoder = FaceEncoder(*source.size, source.video.fps)
            frames = source.frames()
            snapshot, buffered = start_session(encoder, frames, source.video.fps, source.name)
            max_bps = DEFAULT_BUDGET_BPS if args.max_kbps is None else args.max_kbps * 1000
            endpoint = RoomSender(
                self.link, self.key, args.name, self.sealer, source.video.fps, max_bps
            )
            endpoint.set_snapshot(snapshot)
            self.endpoint = endpoint
            width, height = source.size
            self.tell(
                f"sending {source.name} ({width}x{height} at {source.video.fps:g} fps) to room "
                f"{args.room} as {args.name}"
            )
            source.video.resync(buffered[-1].index + 1)
            where = source.path if source.path is not None else args.camera
            sound = sound_as_asked(
                args, where, source.video.is_camera, True, endpoint.publish, self.tell, max_bps
            )
            sent = with_sound(itertools.chain(restamped(buffered), frames), sound, source.video.fps)
            # RoomSender has the part of SenderEndpoint's interface that run_sender uses.
            self.report = run_sender(
                endpoint,  # type: ignore[arg-type]
                encoder,
                sent,
                stop=self.stop,
                read_to=lambda: source.read_to,
            )
            self.link.delete_snapshot()  # a joiner from now on finds no stale face
        finally:
            self.dropped = source.dropped
            source.close()


def run(args: argparse.Namespace) -> int:
    from facewire.call import StopSignal, say
    from facewire.relay import Relay, RelayConfig, free_port
    from facewire.room_link import MAX_RECONNECT_ATTEMPTS, RECONNECT_WAIT_S, RoomLink, _hidden
    from facewire.room_peer import RoomReceiver
    from facewire.room_sound import RoomSound

    subjects.check_name(args.room, "room")
    subjects.check_name(args.name, "participant")
    key: RoomKey | SenderKeys
    if args.peer:
        key = SenderKeys(args.room, args.name, args.key, load_peers(args.peer))
        sealer = Sealer(key.own_key, key.kid)
    else:
        if "secret-key" in _head(args.key):
            raise ValueError(f"{args.key} is a CURVE secret key: name the peers with --peer")
        key = RoomKey.load(args.key)
        if key.room != args.room:
            raise ValueError(f"{args.key} is room {key.room}'s key, not room {args.room}'s")
        sealer = Sealer(key.base_key(args.name), new_kid(args.name))
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    tls = None
    if args.tls_ca:
        from facewire.tls import client_context

        tls = client_context(args.tls_ca)
    record_dir = Path(args.record_dir) if args.record_dir else None
    if record_dir is not None:
        record_dir.mkdir(parents=True, exist_ok=True)
    relay: Relay | None = None
    link: RoomLink | None = None
    receiver: RoomReceiver | None = None
    sending: _SendingSide | None = None
    view: Any = None
    sound: RoomSound | None = None
    tell = say
    with StopSignal() as stop:
        try:
            gallery = None
            if args.view:
                from facewire.receiver.live_view import LiveView, parse_view_address
                from facewire.room_gallery import Gallery

                view = LiveView(*parse_view_address(args.view))
                gallery = Gallery(view)

                def tell(line: str) -> None:
                    say(line)
                    view.event(line)

                tell(f"gallery on {view.url}")
            servers = list(args.server)
            if not servers:
                relay = Relay(RelayConfig(port=free_port())).start()
                servers = [relay.config.client_url()]
                tell(f"no --server: a relay on loopback; others join with --server {servers[0]}")
            sound = RoomSound(tell)
            receiver = RoomReceiver(
                key, args.name,
                get_snapshot=lambda name: link.get_snapshot(name) if link else None,
                publish=lambda subject, data: link.publish(subject, data) if link else None,
                sealer=sealer, notify=tell, record_dir=record_dir, gallery=gallery, sound=sound,
                on_keyframe_request=lambda request: (
                    sending.endpoint.request_keyframe(request)
                    if sending is not None and sending.endpoint is not None else None
                ),
            )  # fmt: skip
            link = RoomLink(
                servers, args.room, args.name, receiver.deliver, tell, tls,
                on_reconnected=lambda: (
                    sending.endpoint.reconnected()
                    if sending is not None and sending.endpoint is not None else None
                ),
            )  # fmt: skip
            link.start()
            if isinstance(key, SenderKeys):  # the boxes are in the bucket before any media
                key.fetch = link.get_entry
                for box, sealed in key.boxes().items():
                    link.put_entry(box, sealed)
            tell(f"joined room {args.room} as {args.name} through {link.connected_url}")
            if args.receive_only:
                tell("receiving only; leaving once those who came have all left")
            else:
                sending = _SendingSide(args, link, key, sealer, stop, tell)
                sending.thread.start()
            # Receive until this one's stream has ended and no one else is left (or a stop);
            # one only receiving waits for someone first.
            while not stop():
                sent = sending is None or sending.done.is_set()
                came = any(f.sessions for f in receiver.figures.values())
                alone = not receiver.peers and not receiver.joining
                if sent and alone and (sending is not None or came):
                    break
                receiver.run_once(TICK_S)
                if link.lost:
                    raise RuntimeError(
                        f"lost the relay: no node of {', '.join(_hidden(s) for s in servers)} "
                        f"answered for {MAX_RECONNECT_ATTEMPTS * RECONNECT_WAIT_S:g} s"
                    )
            if sending is not None and sending.error is not None:
                raise sending.error
        finally:
            if sending is not None:
                sending.done.wait(5.0)
            if receiver is not None:
                receiver.close()
            if sound is not None:
                sound.close()
            if link is not None:
                link.close()
            if relay is not None:
                relay.close()
            if view is not None:
                view.close()
    if receiver is not None and receiver.finish_errors:
        raise receiver.finish_errors[0]  # a recording that could not be finished
    stats = _stats(args, servers, link, receiver, sending, _hidden)
    seen = ", ".join(f"{n} {p['frames']} frames" for n, p in stats["peers"].items())
    say(f"left room {args.room}: {seen or 'no one came'}")
    if args.stats:
        Path(args.stats).write_text(json.dumps(stats, indent=1))
    return 0


def _head(path: str) -> str:
    """The start of a key file, to tell a CURVE key from a room's secret ("" if unreadable:
    the room key's own error says why)."""
    try:
        with open(path, errors="replace") as f:
            return f.read(4096)
    except OSError:
        return ""


def _stats(args: argparse.Namespace, servers: list[str], link: Any, receiver: Any,
           sending: Any, hidden: Any) -> dict[str, Any]:  # fmt: skip
    sent: dict[str, Any] = {}
    if sending is not None and sending.report is not None:
        report = sending.report
        sent = {
            "frames_in": report.frames_in,
            "frames_dropped": sending.dropped,
            "packets": report.packets,
            "keyframe_requests": report.keyframe_requests,
            "sender_fps": round(report.fps, 1),
            **sending.endpoint.figures(),
        }
    return {
        "room": args.room,
        "name": args.name,
        "servers": [hidden(s) for s in servers],
        "reconnects": link.reconnects if link is not None else 0,
        "sent": sent,
        "peers": receiver.stats() if receiver is not None else {},
        "rejected": dict(receiver.rejected) if receiver is not None else {},
    }
