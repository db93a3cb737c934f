"""The receive loop's seams: a frame sink sees every rendered picture, a stop request ends the
call cleanly and tells the sender. A real call on loopback (tests/call_helpers.py), the
receiver in its own process.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from call_helpers import CTX, HOST, JOIN_TIMEOUT_S, Keys, read_video, start_sender

from facewire.protocol.transport import SenderEndpoint
from facewire.sender.session import run_sender, wait_until_ready

STOP_AFTER = 45  # rendered pictures


def _receiver(ports: tuple[int, int], output: str, keys: dict[str, Any], results: Any) -> None:
    from facewire.receiver.session import ReceiverReport, RenderedFrame, run_receiver

    seen: list[tuple[int, int, tuple[int, ...], float, float, int, int]] = []

    def sink(frame: RenderedFrame, report: ReceiverReport) -> None:
        seen.append(
            (
                frame.session_id,
                frame.seq,
                frame.image.shape,
                float(frame.image.mean()),
                frame.latency_ms,
                report.bytes_received.get("geometry", 0),
                frame.capture_us,
            )
        )

    lines: list[str] = []
    report = run_receiver(
        HOST,
        *ports,
        output,
        join_timeout_s=JOIN_TIMEOUT_S,
        sink=sink,
        stop=lambda: len(seen) >= STOP_AFTER,
        notify=lines.append,
        **keys,
    )
    results.put((report.as_dict(), seen, lines))


def test_sink_sees_each_rendered_picture_and_stop_ends_the_call(tmp_path: Path) -> None:
    keys = Keys(tmp_path)
    encoder, snapshot, frames = start_sender(300)
    output = tmp_path / "out.mp4"
    results = CTX.Queue()
    said: list[dict[str, float]] = []
    with SenderEndpoint(HOST, **keys.sender()) as endpoint:
        endpoint.set_snapshot(snapshot)
        process = CTX.Process(
            target=_receiver, args=(endpoint.ports, str(output), keys.receiver(), results)
        )
        process.start()
        try:
            assert wait_until_ready(endpoint, JOIN_TIMEOUT_S, process.is_alive)
            # The sender stops once the receiver says it left.
            sent = run_sender(
                endpoint,
                encoder,
                frames,
                stop=lambda: any(values.get("left") for values in said),
                on_stats=said.append,
            )
            report, seen, lines = results.get(timeout=60)
        finally:
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
    assert sent.stopped and sent.frames_in < 300
    assert report["ended_by"] == "stopped"
    # Every frame recorded as its own picture was shown; the screen may also show pictures
    # between two frames (receiver/playout.py), which the recording leaves out.
    assert len(seen) == STOP_AFTER >= report["frames_out"] - report["frames_held"] > 30
    sessions, seqs, shapes, means, latencies, geometry, instants = zip(*seen, strict=True)
    assert set(sessions) == {snapshot.session_id}
    assert list(seqs) == sorted(seqs) and len(set(seqs)) > 30  # in order
    # Each instant once, in order.
    assert all(a < b for a, b in zip(instants, instants[1:], strict=False))
    assert set(shapes) == {(snapshot.height, snapshot.width, 3)}
    assert min(means) > 20  # a picture, not a black frame
    assert all(0 < ms < 5000 for ms in latencies)
    assert list(geometry) == sorted(geometry) and geometry[-1] > 0  # live figures
    # The recording ends where the call stopped, with its index: every frame plays.
    assert len(read_video(output)) == report["frames_out"]
    assert lines[0].startswith("waiting for a sender at tcp://127.0.0.1:")
    assert lines[1] == f"session {snapshot.session_id}: 640x480 at 30 fps"
    assert np.isfinite(report["latency_ms"]["p90"])


def test_the_stats_say_in_which_second_pictures_were_late() -> None:
    from facewire.receiver.session import ReceiverReport

    report = ReceiverReport()
    start = 5_000_000
    for i in range(90):  # three seconds at 30 fps, the second one with a 400 ms stall in it
        ready = start + i * 33_333
        late = 400.0 if i == 40 else 30.0 + i % 3
        report.latency_ms.append(late)
        report.shown.append((ready, ready - round(late * 1000)))
    assert report.as_dict()["latency_ms_each_second"] == [32.0, 400.0, 32.0]
    assert ReceiverReport().as_dict()["latency_ms_each_second"] == []
