"""A room participant that sends a recorded stream instead of running the face encoder, for
benchmarks/bench_room.py: the relay and the receivers are measured, not the encoders.

:func:`record` runs a clip once through the real encoder (``run_sender`` into a
:class:`~facewire.room_sender.RoomSender` whose link drops what it is given) and keeps the
encoder's packets frame by frame. :func:`replay` joins a room as a participant (it decodes
everyone else, as ``facewire room`` does) and publishes the recording through a real
RoomSender: the same bundles, sealed with the real SFrame code at publish time, paced at the
clip's frame rate. A keyframe's capture time is restamped to when its frame is due (a delta's
is coded relative to the frame before), so the latency the receivers measure is still
capture to decoded.

A recording cannot answer a keyframe request, so a replaying participant heartbeats until
each expected peer has asked it for one (they have its snapshot), and starts its first
keyframe at the time the benchmark gives; requests after that are counted, not answered.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import threading
import time
from pathlib import Path
from typing import Any

from facewire.protocol.clock import now_us
from facewire.protocol.media_path import DEFAULT_BUDGET_BPS
from facewire.protocol.packets import Bye, Heartbeat, KeyFrame, Packet, Snapshot, decode
from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_sender import RoomSender

#: How often a replaying participant heartbeats while it waits for the others to join.
WARMUP_BEAT_S = 1.0


class _NoLink:
    """A RoomLink that drops what it is given (the recording run)."""

    def publish(self, subject: str, data: bytes) -> None:
        pass

    def put_snapshot(self, data: bytes) -> None:
        pass


class _Recorder(RoomSender):
    """A RoomSender that also keeps each frame's packets (heartbeats and the Bye are left
    out: the replay makes its own)."""

    def __init__(self, fps: float, frame_us: list[int]) -> None:
        key = RoomKey.generate("record")
        sealer = Sealer(key.base_key("rec"), new_kid("rec"))
        super().__init__(_NoLink(), key, "rec", sealer, fps, DEFAULT_BUDGET_BPS)  # type: ignore[arg-type]
        self.frame_us = frame_us  # the capture time of the frame being encoded
        self.entries: list[tuple[Any, ...]] = []
        self._packets: list[tuple[bytes, int | None]] = []

    def set_snapshot(self, snapshot: Snapshot, draft: Snapshot | None = None) -> None:
        super().set_snapshot(snapshot)
        self.entries.append(("snapshot", bytes(snapshot)))

    def publish(self, packet: Packet, seq: int | None = None) -> None:
        super().publish(packet, seq)
        if not isinstance(packet, (Bye, Heartbeat)):
            self._packets.append((bytes(packet), seq))

    def end_frame(self) -> None:
        super().end_frame()
        self.entries.append(("frame", self.frame_us[0], self._packets))
        self._packets = []


def record(clip: Path | None, size: tuple[int, int], frames: int, out: Path) -> dict[str, Any]:
    """Encode ``frames`` frames of ``clip`` (None: the bundled clip) scaled to ``size`` once,
    into ``out`` (a pickle: fps and the entries); capture times are the clip's own."""
    from facewire.sender.capture import VideoSource, demo_clip_path
    from facewire.sender.encoder import FaceEncoder
    from facewire.sender.session import capped_size, run_sender, scaled, start_session

    video = VideoSource(clip or demo_clip_path(), realtime=False)
    fps = video.fps
    size = capped_size(video.width, video.height, *size)
    current = [0]

    def stamped() -> Any:
        for frame in video.frames(frames):
            capture_us = int(frame.index * 1e6 / fps)
            current[0] = capture_us
            yield dataclasses.replace(frame, capture_us=capture_us)

    try:
        source = scaled(stamped(), size)
        # One session: the replay serves one snapshot and makes its own heartbeats, so a new
        # scene's (which facewire/room.py's sender would start) could not be replayed.
        encoder = FaceEncoder(*size, fps, scenes=False)
        snapshot, buffered = start_session(encoder, source, fps, str(clip))
        recorder = _Recorder(fps, current)
        recorder.set_snapshot(snapshot)

        def sent() -> Any:
            for frame in buffered:
                current[0] = frame.capture_us
                yield frame
            yield from source

        run_sender(recorder, encoder, sent())  # type: ignore[arg-type]
    finally:
        video.close()
    recording = {"fps": fps, "size": size, "entries": recorder.entries}
    out.write_bytes(pickle.dumps(recording))
    return recording


class _Participant:
    """The receiving side of ``facewire room`` (decoding, not drawing) and a RoomSender."""

    def __init__(self, server: str, key_file: Path, name: str, fps: float) -> None:
        from facewire.room_link import RoomLink
        from facewire.room_peer import RoomReceiver

        self.key = RoomKey.load(key_file)
        self.name = name
        self.sealer = Sealer(self.key.base_key(name), new_kid(name))
        self.asked: set[str] = set()  # who asked this one for a keyframe
        self.late_requests = 0
        self.started = False
        self.cpu_at_go = 0.0  # this process's CPU seconds when the clip started
        participant = self

        class Receiver(RoomReceiver):
            def _control(self, sender: str, data: bytes) -> None:
                participant.asked.add(sender)
                participant.late_requests += participant.started
                super()._control(sender, data)

        self.receiver = Receiver(
            self.key, name,
            get_snapshot=lambda peer: self.link.get_snapshot(peer),
            publish=lambda subject, data: self.link.publish(subject, data),
            sealer=self.sealer, notify=lambda line: None,
        )  # fmt: skip
        self.link = RoomLink([server], self.key.room, name, self.receiver.deliver, lambda _: None)
        self.link.start()
        self.sender = RoomSender(self.link, self.key, name, self.sealer, fps, DEFAULT_BUDGET_BPS)


def replay(server: str, key_file: Path, name: str, recording_file: Path, expect: list[str],
           go_file: Path, stats_file: Path) -> None:  # fmt: skip
    """Join as ``name``, wait for ``expect`` to ask for a keyframe (then write
    ``stats_file``.ready), start the recording at the monotonic time in ``go_file``, receive
    until everyone has left, write the figures to ``stats_file``."""
    recording = pickle.loads(recording_file.read_bytes())
    me = _Participant(server, key_file, name, recording["fps"])
    done = threading.Event()

    def send() -> None:
        try:
            _send(me, recording, expect, go_file, stats_file)
        finally:
            done.set()

    threading.Thread(target=send, name="replay", daemon=True).start()
    receiver = me.receiver
    while True:
        alone = not receiver.peers and not receiver.joining
        if done.is_set() and alone:
            break
        receiver.run_once(0.1)
    receiver.close()
    me.link.close()
    stats = {
        "name": name,
        "sent": me.sender.figures(),
        "late_keyframe_requests": me.late_requests,
        "cpu_s": round(time.process_time() - me.cpu_at_go, 2),
        "peers": receiver.stats(),
        "rejected": dict(receiver.rejected),
    }
    stats_file.write_text(json.dumps(stats, indent=1))


def _send(me: _Participant, recording: dict[str, Any], expect: list[str], go_file: Path,
          stats_file: Path) -> None:  # fmt: skip
    entries = recording["entries"]
    sender = me.sender
    sender.set_snapshot(decode(entries[0][1]))  # type: ignore[arg-type]
    while not go_file.exists():
        if me.asked >= set(expect):
            stats_file.with_suffix(".ready").touch()
        sender.heartbeat()
        time.sleep(WARMUP_BEAT_S)
    go_us = int(float(go_file.read_text()) * 1e6)
    first = next(e[1] for e in entries if e[0] == "frame")
    offset = go_us - first
    me.started = True
    me.cpu_at_go = time.process_time()
    last_seq = 0
    for entry in entries[1:]:
        if entry[0] == "snapshot":  # a scene cut
            sender.set_snapshot(decode(entry[1]))  # type: ignore[arg-type]
            sender.heartbeat()
            continue
        _, capture_us, packets = entry
        wait_us = capture_us + offset - now_us()
        if wait_us > 0:
            time.sleep(wait_us / 1e6)
        for data, seq in packets:
            packet = decode(data)
            if isinstance(packet, KeyFrame):
                packet = dataclasses.replace(packet, capture_us=packet.capture_us + offset)
            sender.publish(packet, seq)
            last_seq = seq if seq is not None else last_seq
        sender.heartbeat_if_idle()
        sender.end_frame()
    sender.publish(Bye(seq=last_seq + 1))
    me.link.delete_snapshot()
