"""Both ends of a call in one process, for measuring what the coding does.

The sender's packets go to the receiver's decoder as bytes, through the real codecs, with no
sockets, no pacing and no loss: what the benchmarks and tests need to compare frame i of the
output with frame i of the input. A call between people runs each end in its own process
(``facewire demo``, ``send``, ``receive``); nothing in the product uses this module.

    with Loopback(FaceEncoder(w, h, fps), frames[0]) as call:
        for frame in frames:
            call.step(frame)
            picture = call.picture()
"""

from __future__ import annotations

from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np

from facewire.protocol.channels import FrameValues
from facewire.protocol.packets import DeltaFrame, KeyFrame, Refresh, RemPatch, Snapshot, decode
from facewire.receiver.decoder import FaceDecoder

if TYPE_CHECKING:
    from facewire.models.pose import Pose
    from facewire.sender.capture import CapturedFrame
    from facewire.sender.encoder import FaceEncoder


class Loopback:
    """One session: ``encoder`` started on ``first`` (frame number ``seq``), and a receiver
    built from its snapshot's bytes. Raises ValueError when ``first`` shows no face."""

    def __init__(self, encoder: FaceEncoder, first: CapturedFrame, seq: int | None = 0) -> None:
        snapshot = encoder.start(first, seq=seq)
        if snapshot is None:
            raise ValueError(f"no face in frame {first.index}")
        self.encoder = encoder
        #: The snapshot as the receiver decoded it from its bytes.
        self.snapshot: Snapshot = decode(bytes(snapshot))  # type: ignore[assignment]
        self.decoder = FaceDecoder(self.snapshot)
        #: What the receiver shows: the values of the last frame packet (None before one).
        self.shown: FrameValues | None = None
        #: Patches and refreshes the receiver could not use (FaceDecoder.add_patch, add_refresh).
        self.refused = 0
        #: New scenes (sessions started at a cut).
        self.scenes = 0

    def send(self, frame: CapturedFrame) -> list[bytes]:
        """The sender's side of ``frame``: its REM patches, then its frame packet (if any),
        as bytes. A frame of another scene starts a new session first (the receiver is built
        again from its snapshot: :attr:`scenes` counts them)."""
        if self.encoder.scene_changed(frame):
            scene = self.encoder.start_scene(frame)
            if scene is not None:
                self._join(scene)
                self.scenes += 1
        return self.send_analysed(frame, self.encoder.analyse(frame.image))

    def _join(self, snapshot: Snapshot) -> None:
        self.decoder.close()
        self.snapshot = decode(bytes(snapshot))  # type: ignore[assignment]
        self.decoder = FaceDecoder(self.snapshot)
        self.shown = None

    def send_analysed(
        self, frame: CapturedFrame, analysed: tuple[Pose, np.ndarray] | None
    ) -> list[bytes]:
        """:meth:`send` for a frame the caller has analysed (``FaceEncoder.analyse``)."""
        packet = self.encoder.encode_analysed(frame, analysed)
        sent = [bytes(p) for p in self.encoder.take_patches()]
        return sent if packet is None else [*sent, bytes(packet)]

    def receive(self, sent: list[bytes]) -> list[RemPatch | Refresh | KeyFrame | DeltaFrame]:
        """The receiver's side: each packet decoded and taken, as the receive loop does."""
        packets = []
        for data in sent:
            packet = decode(data)
            if isinstance(packet, RemPatch):
                self.refused += not self.decoder.add_patch(packet)
            elif isinstance(packet, Refresh):
                self.refused += not self.decoder.add_refresh(packet)
            elif isinstance(packet, (KeyFrame, DeltaFrame)):
                self.shown = self.decoder.decode(packet)
            else:
                raise TypeError(f"a sender does not send {type(packet).__name__} per frame")
            packets.append(packet)
        return packets

    def step(self, frame: CapturedFrame) -> list[bytes]:
        """Both sides of ``frame``; the bytes that went (none: the receiver keeps the last
        picture)."""
        sent = self.send(frame)
        self.receive(sent)
        return sent

    def picture(self) -> np.ndarray:
        """(h, w, 3) uint8 BGR: what the receiver draws now."""
        if self.shown is None:
            raise RuntimeError("no frame packet has arrived yet")
        return self.decoder.reconstruct(self.shown)

    def close(self) -> None:
        self.decoder.close()

    def __enter__(self) -> Loopback:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
