"""The receiver's sound: Opus decoding, jitter buffer, concealment, playback and lip sync.

AudioFrame packets (docs/protocol.md) go into a jitter buffer keyed by their 20 ms step
(``seq``; a 40 or 60 ms packet covers the steps from it on). A thread plays one step every
20 ms: the packet if it came, else Opus's own packet-loss concealment for up to
CONCEAL_FRAMES steps (a lost packet, or the start of the silence the sender left out, DTX),
then silence. Steps are played on the capture clock:
step s is due at ``capture_us(s) + latency``, where ``latency`` is the face's (how long after
capture the receive loop put its pictures on screen, :attr:`RenderedFrame.latency_ms`), or
more when the sound needs it to arrive in time (its packets wait for the video frame that
follows them, and then cross the network). So voice and lips leave the receiver together;
the latency is chosen again whenever the sound has paused, never in the middle of a word.

Where there is no sound device (or sounddevice is not installed) the sound goes to a null
sink, paced the same way; either way what was played is kept for the recording and muxed
into the MP4 at the end (:func:`mux_audio`, PyAV: the video copied, the sound as AAC).
"""

from __future__ import annotations

import logging
import os
import tempfile
import threading
import time
import wave
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from facewire.protocol.clock import now_us
from facewire.protocol.constants import AUDIO_FRAME_MS, AUDIO_FRAME_SAMPLES, AUDIO_RATE
from facewire.protocol.packets import AudioFrame, KeyFrame

logger = logging.getLogger(__name__)

_Device = TypeVar("_Device")

FRAME_US = AUDIO_FRAME_MS * 1000
#: Missing steps concealed by the codec in a row; beyond them the gap is silence.
CONCEAL_FRAMES = 5
#: A pause this long (steps without a packet, nothing buffered) lets the latency be chosen again.
RESYNC_FRAMES = 10
#: Steps kept ahead of the one playing (5 s); packets beyond are dropped.
MAX_AHEAD_FRAMES = 250
#: A packet this far behind the one playing is a new sender (its steps start again from 0).
RESTART_FRAMES = 250
#: Margin the sound's own latency keeps over the slowest recent packet, µs.
MARGIN_US = 10_000
#: The least latency the sound starts with, µs: a packet is sent when the video frame after
#: its 20 ms is read (up to 33 ms at 30 fps, and that frame's encoding) and then waits for its
#: datagram (one every two frames by default, protocol/media_path.py: up to 33 ms more), so
#: before the first packets have shown what the link does, this keeps them from being late.
#: Once OWN_TRANSITS packets have come, theirs set it: held for good, it put the sound 119 ms
#: behind a face drawn 21 ms after capture on loopback (one frame a datagram there).
MIN_LATENCY_US = 140_000
#: A step due this much later after its capture than the latency needs now (the first
#: packets of a call are often slow, or stamped off the later ones' pace: the run's start
#: then sets too long a latency for all of it) makes the run catch up, µs ...
CATCH_UP_US = 2_000
#: ... by leaving out as much of a step this quiet (RMS, int16; about -40 dBFS), in whole ms,
#: up to all of it: a pause between words is shorter on the device, and the recording keeps
#: it. (Whole steps only, the run stayed up to 20 ms later than needed: +100 ms behind the
#: demo's face where +87 would do.)
QUIET_RMS = 330.0
#: A packet that comes later than its step (capture to arrival under this, µs) makes the
#: playing run wait 20 ms more (a step of the codec's concealment on the device).
MAX_STRETCHED_US = 1_000_000
#: Until this many sound packets have come, the latency also follows the video frames'
#: median transit plus SOUND_AFTER_PICTURE_US (a sound packet leaves with the video frame after
#: its 20 ms: up to a frame later at 30 fps, and its own 20 ms to fill) and REPEAT_US (on a
#: lossy link a lost datagram's packets come again in the next one, a frame later).
OWN_TRANSITS = 25
SOUND_AFTER_PICTURE_US = FRAME_US + 33_000
REPEAT_US = 33_000
#: Recent packets (capture to arrival) and pictures (capture to screen) that set the latency.
WINDOW = 100
#: Audio latency samples kept for the figures (about 3 minutes of sound).
MAX_SAMPLES = 10_000
#: Video frames kept to place the sound in the recording: two hours at 30 fps.
MAX_ANCHORS = 216_000
#: A packet's capture-to-arrival time this far from the recent packets' median is no network's
#: jitter but a capture time that lies: it does not set the latency, µs ...
MAX_SKEW_US = 2_000_000
#: ... once there are this many recent packets to outvote it.
TRUSTED_AFTER = 3
#: No step is due further ahead than the latency (seconds at most): a run whose first step is
#: due later than this, or was due this long ago, starts from its next packet instead, µs.
MAX_WAIT_US = 5_000_000
#: A stopping receiver waits this long for the sound's thread, s.
CLOSE_WAIT_S = 1.0
#: A sender that said bye has its buffered sound played out for at most this long, s (no
#: step is due further ahead than MAX_WAIT_US).
PLAY_OUT_S = MAX_WAIT_US / 1e6
#: Silence for a pause is written this many samples at a time (bounded memory), one second.
SILENCE_CHUNK = AUDIO_RATE


class AudioDecodeError(ValueError):
    """An Opus packet the decoder refused."""


#: Opus packet lengths a sender may use, in 20 ms steps.
MAX_PACKET_STEPS = 3


class OpusDecoder:
    """PyAV's libopus decoder: 20, 40 or 60 ms packets in, 960 int16 samples a 20 ms step
    out; codec concealment 20 ms at a time."""

    def __init__(self) -> None:
        import av

        self._av = av
        ctx: Any = av.CodecContext.create("libopus", "r")
        ctx.sample_rate = AUDIO_RATE
        ctx.layout = "mono"
        ctx.open()
        self._ctx = ctx
        self._toc: int | None = None

    def decode(self, data: bytes) -> np.ndarray:
        """The 20, 40 or 60 ms an Opus packet holds; AudioDecodeError when it is not one."""
        try:
            frames = self._ctx.decode(self._av.Packet(data))
        except self._av.FFmpegError as exc:
            raise AudioDecodeError(f"Opus packet of {len(data)} bytes refused: {exc}") from None
        pcm = _pcm(frames)
        steps, rest = divmod(len(pcm), AUDIO_FRAME_SAMPLES)
        if rest or not 1 <= steps <= MAX_PACKET_STEPS:
            raise AudioDecodeError(
                f"Opus packet of {len(data)} bytes holds {len(pcm)} samples, "
                f"expected {AUDIO_FRAME_SAMPLES} (20 ms), or twice or three times that"
            )
        self._toc = data[0]
        return pcm

    def conceal(self) -> np.ndarray:
        """20 ms of the codec's concealment: a packet whose only frame is empty tells libopus
        the frame was lost (RFC 6716, 3.2.1), which it then extrapolates; its TOC byte is the
        last packet's with the frame length made 20 ms."""
        if self._toc is None:
            return np.zeros(AUDIO_FRAME_SAMPLES, np.int16)
        try:
            toc = bytes([_toc_of_20_ms(self._toc)])
            pcm = _pcm(self._ctx.decode(self._av.Packet(toc)))
        except self._av.FFmpegError:
            pcm = np.zeros(0, np.int16)
        if len(pcm) != AUDIO_FRAME_SAMPLES:
            return np.zeros(AUDIO_FRAME_SAMPLES, np.int16)
        return pcm


def _toc_of_20_ms(toc: int) -> int:
    """A TOC byte (RFC 6716, 3.1) of the same mode and bandwidth, one frame of 20 ms: the
    configuration's low bits pick the length (SILK 10/20/40/60 ms, hybrid 10/20, CELT
    2.5/5/10/20), the two lowest bits of the byte the frame count code (0: one frame)."""
    config, stereo = toc >> 3, toc & 0x04
    if config < 12:  # SILK: 4 lengths a bandwidth
        config = (config & ~3) | 1
    elif config < 16:  # hybrid: 2
        config = (config & ~1) | 1
    else:  # CELT: 4
        config |= 3
    return (config << 3) | stereo


def _pcm(frames: Sequence[Any]) -> np.ndarray:
    chunks = [f.to_ndarray().reshape(-1) for f in frames]
    if not chunks:
        return np.zeros(0, np.int16)
    pcm = np.concatenate(chunks)
    if pcm.dtype != np.int16:  # float planar from some builds
        pcm = np.clip(np.round(pcm * 32767), -32768, 32767).astype(np.int16)
    return pcm


class AudioSink(Protocol):
    """Where played sound goes. ``latency_us``: from write to the speaker."""

    name: str
    latency_us: int

    def write(self, pcm: np.ndarray) -> None: ...

    def close(self) -> None: ...


class NullSink:
    """No sound device: the sound is only timed, recorded and measured."""

    name = "no sound device"
    latency_us = 0

    def write(self, pcm: np.ndarray) -> None:
        pass

    def close(self) -> None:
        pass


class DeviceSink:
    """The default output device through sounddevice (PortAudio)."""

    def __init__(self) -> None:
        import sounddevice as sd

        self._stream = sd.OutputStream(
            samplerate=AUDIO_RATE, channels=1, dtype="int16", blocksize=AUDIO_FRAME_SAMPLES
        )
        self._stream.start()
        self.name = str(sd.query_devices(kind="output")["name"])
        self.latency_us = round(float(self._stream.latency) * 1e6)

    def write(self, pcm: np.ndarray) -> None:
        self._stream.write(pcm.reshape(-1, 1))

    def close(self) -> None:
        self._stream.close()


def open_device(make: Callable[[], _Device]) -> tuple[_Device | None, str | None]:
    """What ``make`` opens on the sound device, or None and one line saying why it cannot."""
    try:
        return make(), None
    except ImportError:
        reason = "no sound device (sounddevice is not installed): the sound is only recorded"
    except Exception as exc:  # PortAudio: no device, busy, no library
        reason = f"no sound device ({str(exc).splitlines()[0]}): the sound is only recorded"
    return None, reason


def open_sink(device: bool = True) -> tuple[AudioSink, str | None]:
    """The sound device, or a null sink and one line saying why there is none."""
    if not device:
        return NullSink(), None
    sink, reason = open_device(DeviceSink)
    return (NullSink() if sink is None else sink), reason


@dataclass
class AudioReport:
    """What the receiver's sound did over the call."""

    packets: int = 0
    bytes: int = 0
    played: int = 0  # 20 ms steps played from a packet
    concealed: int = 0  # steps the codec made up (loss, or the start of DTX silence)
    silent: int = 0  # steps of silence after CONCEAL_FRAMES
    shortened: int = 0  # quiet steps cut short or left out on the device (latency down)
    stretched: int = 0  # steps of concealment put in on the device after a late packet
    late: int = 0  # packets that came after their step was played
    dropped: int = 0  # too far ahead, duplicates
    malformed: int = 0  # packets the Opus decoder refused (concealed instead)
    refused: int = 0  # a run's first packet due too far ahead or behind (MAX_WAIT_US)
    restarts: int = 0
    sink: str = ""
    # (audio latency, face latency) µs per played step: capture to sink, capture to screen.
    latency_us: list[tuple[int, int]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        lat = np.asarray(self.latency_us, dtype=np.float64).reshape(-1, 2)
        offset = (lat[:, 0] - lat[:, 1]) / 1000 if len(lat) else np.zeros(0)

        def pct(q: float) -> float:
            return float(np.percentile(offset, q)) if len(offset) else 0.0

        return {
            "packets": self.packets,
            "bytes": self.bytes,
            "played": self.played,
            "concealed": self.concealed,
            "silent": self.silent,
            "shortened": self.shortened,
            "stretched": self.stretched,
            "late": self.late,
            "dropped": self.dropped,
            "malformed": self.malformed,
            "refused": self.refused,
            "restarts": self.restarts,
            "sink": self.sink,
            "latency_ms_p50": float(np.median(lat[:, 0])) / 1000 if len(lat) else 0.0,
            # Sound minus face, ms: > 0 the sound comes after the lips (BT.1359: at most
            # 125 ms), < 0 before them (at most 45 ms).
            "av_offset_ms": {"p5": pct(5), "p50": pct(50), "p95": pct(95)},
        }


class _Timeline:
    """What was played, as 48 kHz mono int16 on the capture clock, kept in a WAV file (an
    anonymous one: it goes with the process however the process ends; named, a receiver
    killed mid-call left one behind in the temporary folder).

    A pause between runs is written as silence, but never longer than the time that passed
    on ``clock`` (µs) and a second: capture times that lie cannot make the file outgrow the
    call.
    """

    def __init__(self, clock: Callable[[], int] = now_us) -> None:
        self._clock = clock
        self._written_at: int | None = None
        self._file = tempfile.TemporaryFile(prefix="facewire-audio-", suffix=".wav")
        self._wav = wave.open(self._file, "wb")  # closing it leaves the file open
        self._wav.setnchannels(1)
        self._wav.setsampwidth(2)
        self._wav.setframerate(AUDIO_RATE)
        self.start_us: int | None = None  # capture time of the first sample
        self.samples = 0
        #: (capture µs, sample) where the written sound starts anew (a gap or an overlap
        #: before it): each such stretch is placed in the recording on its own.
        self.stretches: list[tuple[int, int]] = []
        #: (the packet's own capture stamp µs, sample) of each step written from a packet.
        self.stamps: list[tuple[int, int]] = []

    def put(self, capture_us: int, pcm: np.ndarray, stamp_us: int | None = None) -> None:
        """Write ``pcm`` at ``capture_us`` on the run's clock; ``stamp_us``: the capture
        time its packet carried (None: concealed or silence)."""
        if self.start_us is None:
            self.start_us = capture_us
        at = round((capture_us - self.start_us) * AUDIO_RATE / 1e6)
        now = self._clock()
        if self._written_at is not None:
            longest = self.samples + round((now - self._written_at + 1e6) * AUDIO_RATE / 1e6)
            if at > longest:
                self.start_us += round((at - longest) * 1e6 / AUDIO_RATE)
                at = longest
        self._written_at = now
        if stamp_us is not None and len(self.stamps) < MAX_ANCHORS:
            self.stamps.append((stamp_us, at))
        if at != self.samples or not self.stretches:
            overlap = max(self.samples - at, 0)  # kept as written, the new part after it
            begins = capture_us + round(overlap * 1e6 / AUDIO_RATE)
            self.stretches.append((begins, max(at, self.samples)))
        while at > self.samples:  # a pause: silence up to it
            chunk = min(at - self.samples, SILENCE_CHUNK)
            self._wav.writeframes(np.zeros(chunk, "<i2").tobytes())
            self.samples += chunk
        skip = self.samples - at  # overlap after a re-sync: keep what was written
        if skip < len(pcm):
            self._wav.writeframes(pcm[skip:].astype("<i2").tobytes())
            self.samples += len(pcm) - skip

    def close(self) -> None:
        self._wav.close()

    def read(self) -> np.ndarray:
        self._file.seek(0)
        with wave.open(self._file, "rb") as w:
            return np.frombuffer(w.readframes(w.getnframes()), "<i2")

    def discard(self) -> None:
        self._file.close()


class AudioPlayout:
    """The jitter buffer and the thread that plays it (see the module's docstring).

    ``face_latency`` gives the recent capture-to-screen times of the face, µs (the receive
    loop's shown pictures); the sound follows them. :meth:`push` takes AudioFrame packets
    (and KeyFrames, whose capture time places the sound in the recording).
    """

    def __init__(
        self,
        sink: AudioSink,
        face_latency: Callable[[], int | None],
        clock: Callable[[], int] = now_us,
    ) -> None:
        self.sink = sink
        self.report = AudioReport(sink=sink.name)
        self._face_latency = face_latency
        self._clock = clock
        self._decoder = OpusDecoder()
        self._timeline = _Timeline(clock)
        self._lock = threading.Condition()
        self._buffer: dict[int, AudioFrame] = {}
        # The later 20 ms steps of a 40 or 60 ms packet played: (pcm, capture µs) by step.
        self._decoded: dict[int, tuple[np.ndarray, int]] = {}
        self._transit: list[int] = []  # capture to arrival, µs, recent packets
        self._video_transit: list[int] = []  # the same of recent video frames
        self._next: int | None = None  # the step to play next (None: idle)
        self._base: tuple[int, int, int] = (0, 0, 0)  # (step, its capture µs, its local due µs)
        self._missing = 0  # steps in a row without a packet
        self._stretch = 0  # late packets not yet answered by a step of concealment
        self._stop = False
        #: (frame seq, capture µs) of video frames: where the recording's frames were captured.
        self.video_anchors: list[tuple[int, int]] = []
        self._thread = threading.Thread(target=self._run, name="audio-playout", daemon=True)
        self._thread.start()

    # --- receive side (the receive loop's thread) ------------------------------------------

    def frame(self, seq: int, capture_us: int, arrival_us: int | None = None) -> None:
        """A video frame the receiver decoded: where the recording's frame ``seq`` was taken;
        ``arrival_us``: when it came, which tells the sound what the link does before its own
        packets have (a lossy link's repeats bring some a datagram late)."""
        if len(self.video_anchors) < MAX_ANCHORS:
            self.video_anchors.append((seq, capture_us))
        if arrival_us is not None:
            with self._lock:
                self._video_transit.append(arrival_us - capture_us)
                del self._video_transit[:-WINDOW]

    def push(self, packet: AudioFrame | KeyFrame, arrival_us: int | None = None) -> None:
        if isinstance(packet, KeyFrame):
            self.frame(packet.seq, packet.capture_us)
            return
        arrival = self._clock() if arrival_us is None else arrival_us
        with self._lock:
            report = self.report
            report.packets += 1
            report.bytes += len(packet.data)
            nxt = self._next
            if nxt is not None and packet.seq < nxt - RESTART_FRAMES:
                logger.info("sound starts again at step %d (was at %d)", packet.seq, nxt)
                report.restarts += 1
                self._buffer.clear()
                self._decoded.clear()
                self._next = None
                nxt = None
            if nxt is not None and packet.seq < nxt:
                # Later than the run's latency allows: the run waits a step longer from now
                # on, and the next run's latency counts this packet's transit.
                report.late += 1
                self._transit.append(arrival - packet.capture_us)
                del self._transit[:-WINDOW]
                if arrival - packet.capture_us < MAX_STRETCHED_US:
                    self._stretch += 1
                return
            if (
                packet.seq in self._buffer
                or packet.seq in self._decoded
                or (nxt is not None and packet.seq > nxt + MAX_AHEAD_FRAMES)
            ):
                report.dropped += 1
                return
            self._buffer[packet.seq] = packet
            self._transit.append(arrival - packet.capture_us)
            del self._transit[:-WINDOW]
            self._lock.notify()

    def delay_us(self) -> int | None:
        """How long after capture the sound is heard now, µs: the playing run's latency, or
        between runs the one a run starting now would take; None before any packet came (a
        sender without sound). A picture shown this long after its capture is seen with the
        voice it was sent with."""
        with self._lock:
            if self._next is not None:
                _, base_capture, base_due = self._base
                return base_due - base_capture
            if not self._transit:
                return None
            return self._latency()

    # --- play side (its own thread) --------------------------------------------------------

    def _usual_transit(self) -> int | None:
        """The recent packets' median capture-to-arrival time, µs (None: too few yet)."""
        if len(self._transit) < TRUSTED_AFTER:
            return None
        return int(np.median(self._transit))

    def _latency(self) -> int:
        """How long after capture the next run of sound is played, µs: the slowest recent
        packet sets it, of those near the median (a lying one the median outvotes)."""
        usual = self._usual_transit()
        near = [t for t in self._transit if usual is None or abs(t - usual) <= MAX_SKEW_US]
        slowest = max(near, default=0)
        known = len(self._transit) >= OWN_TRANSITS
        if not known and self._video_transit:
            # The pictures' typical transit (their median: a stalled frame says nothing of
            # the link), what a sound packet waits for on top of it, and a repeat's datagram.
            pictures = int(np.median(self._video_transit)) + SOUND_AFTER_PICTURE_US + REPEAT_US
            slowest = max(slowest, pictures)
        own = max(0 if known else MIN_LATENCY_US, slowest + FRAME_US + MARGIN_US)
        face = self._face_latency()
        return max(own, face if face is not None else own)

    def _run(self) -> None:
        while True:
            with self._lock:
                while not self._stop and self._next is None and not self._buffer:
                    self._lock.wait(0.1)
                if self._stop:
                    return
                if self._next is None:  # start a run: choose the latency now
                    first = min(self._buffer)
                    capture = self._buffer[first].capture_us
                    self._next = first
                    self._base = (first, capture, capture + self._latency())
                    self._stretch = 0  # the latency just chosen counts the late ones
                step = self._next
                base_step, base_capture, base_due = self._base
                due = base_due + (step - base_step) * FRAME_US
                stretch = self._stretch > 0
                if stretch:  # this step's place gets 20 ms of concealment; the run moves on
                    self._stretch -= 1
                    self._base = (base_step, base_capture, base_due + FRAME_US)
            wait = due - self.sink.latency_us - self._clock()
            if step == base_step and abs(wait) > MAX_WAIT_US:
                # The run's first packet lied about its capture time (before enough packets
                # came to outvote it): it is dropped, the run starts from the next one.
                with self._lock:
                    self.report.refused += self._buffer.pop(step, None) is not None
                    self._next = None
                continue
            if wait > 0:
                with self._lock:  # close() wakes it
                    if self._lock.wait_for(lambda: self._stop, wait / 1e6):
                        return
            if stretch:
                self.sink.write(self._decoder.conceal())
                self.report.stretched += 1
                continue
            left_out_us = self._play(step, base_capture + (step - base_step) * FRAME_US, due)
            if left_out_us:
                with self._lock:  # the rest of the run plays that much earlier
                    self._base = (base_step, base_capture, base_due - left_out_us)

    def _play(self, step: int, run_us: int, due_us: int) -> int:
        """Play ``step``, due on the device at ``due_us``; ``run_us`` is its capture time
        counted from the run's start (the recording places it there, so a run is written
        without seams). Of a quiet step due CATCH_UP_US or more later than needed, as much as
        it is late is left out on the device (its end); returns how much, µs."""
        with self._lock:
            packet = self._buffer.pop(step, None)
            decoded = self._decoded.pop(step, None)
            self._next = step + 1
        report = self.report
        pcm: np.ndarray | None = None
        stamp: int | None = None  # the capture time the step's packet gives it
        if decoded is not None:
            pcm, stamp = decoded
        elif packet is not None:
            try:
                whole = self._decoder.decode(packet.data)
                pcm, stamp = whole[:AUDIO_FRAME_SAMPLES], packet.capture_us
                with self._lock:
                    for i in range(1, len(whole) // AUDIO_FRAME_SAMPLES):
                        part = whole[i * AUDIO_FRAME_SAMPLES : (i + 1) * AUDIO_FRAME_SAMPLES]
                        self._decoded[step + i] = (part, stamp + i * FRAME_US)
            except AudioDecodeError as exc:
                logger.debug("%s", exc)
                report.malformed += 1
        if pcm is not None:
            report.played += 1
            self._missing = 0
        else:
            self._missing += 1
            if self._missing <= CONCEAL_FRAMES:
                pcm = self._decoder.conceal()
                report.concealed += 1
            else:
                pcm = np.zeros(AUDIO_FRAME_SAMPLES, np.int16)
                report.silent += 1
        late_ms = 0 if stamp is None else (due_us - stamp - self._latency()) // 1000
        if late_ms * 1000 < CATCH_UP_US or (
            float(np.sqrt(np.mean(pcm.astype(np.float64) ** 2))) >= QUIET_RMS
        ):
            late_ms = 0
        left_out = min(AUDIO_FRAME_SAMPLES, late_ms * AUDIO_RATE // 1000)
        self._timeline.put(run_us, pcm, stamp)
        if left_out:
            report.shortened += 1
        if left_out == AUDIO_FRAME_SAMPLES:
            return FRAME_US
        self.sink.write(pcm[: AUDIO_FRAME_SAMPLES - left_out])
        played = self._clock() + self.sink.latency_us
        face = self._face_latency()
        if stamp is not None and face is not None and len(report.latency_us) < MAX_SAMPLES:
            report.latency_us.append((played - stamp, face))
        with self._lock:
            if self._missing >= RESYNC_FRAMES and not self._buffer and not self._decoded:
                self._next = None  # a pause: the next run chooses its latency again
        return left_out * 1_000_000 // AUDIO_RATE

    # --- the end ---------------------------------------------------------------------------

    def play_out(self, timeout_s: float = PLAY_OUT_S) -> None:
        """Wait until what is buffered has been played (or ``timeout_s``): looked at once a
        step (the play thread's notifications are for itself)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if self._stop or not (self._buffer or self._decoded):
                    return
            time.sleep(FRAME_US / 1e6)

    def close(self) -> None:
        """Stop playing (what is still buffered is dropped) and close the sink."""
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        self._thread.join(CLOSE_WAIT_S)
        if self._thread.is_alive():  # a sound device that does not return: leave it
            logger.warning("the sound's thread did not stop within %g s", CLOSE_WAIT_S)
        self.sink.close()
        self._timeline.close()

    def recorded(self, first_seq: int, fps: float) -> np.ndarray:
        """What was played, placed against a recording whose frame 0 is the sender's frame
        ``first_seq``: sample 0 of the result is that frame's instant.

        The recording shows frame n at (n - first_seq) / fps, but the sender captured it at
        its own pace: a sender that falls behind (most of all over its first frames) stamps
        its frames, and the sound sent with them, later. A packet's place is its stamp less
        how late the frames captured then were; each stretch of sound is placed where its
        packets put it (their median), so the voice stays with the lips it was sent with.
        """
        pcm = self._timeline.read()
        stretches = self._timeline.stretches
        if not stretches or not self.video_anchors:
            return pcm[:0]
        anchors = np.array(sorted(self.video_anchors, key=lambda a: a[1]), dtype=np.float64)
        seqs, captures = anchors[:, 0], anchors[:, 1]
        late = captures - (seqs - first_seq) * 1e6 / fps  # each frame's capture - its place
        stamps = np.array(self._timeline.stamps, dtype=np.float64).reshape(-1, 2)
        # Where each packet's first sample belongs in the recording, less its sample: the
        # recording's time of the timeline's sample 0, as that packet tells it.
        told = (
            stamps[:, 0] - np.interp(stamps[:, 0], captures, late) - stamps[:, 1] * 1e6 / AUDIO_RATE
        )
        # Nothing far beyond the recording's last frame and the sound played (the MP4 cuts
        # it to the picture): a stamp that lies cannot make the sound outgrow the call.
        length = max(round((seqs.max() - first_seq + 1) / fps * AUDIO_RATE), len(pcm))
        length += AUDIO_RATE
        out = np.zeros(0, np.int16)
        ends = [k for _, k in stretches[1:]] + [len(pcm)]
        for (capture_us, start), end in zip(stretches, ends, strict=True):
            inside = (stamps[:, 1] >= start) & (stamps[:, 1] < end)
            if inside.any():
                place_us = float(np.median(told[inside])) + start * 1e6 / AUDIO_RATE
            else:  # concealment alone: placed by its own start
                place_us = capture_us - float(np.interp(capture_us, captures, late))
            at = round(place_us * AUDIO_RATE / 1e6)
            part = pcm[start:end]
            if at < 0:
                part, at = part[-at:], 0
            part = part[: max(0, length - at)]
            if not len(part):
                continue
            if at + len(part) > len(out):
                out = np.concatenate([out, np.zeros(at + len(part) - len(out), np.int16)])
            out[at : at + len(part)] = part
        return out

    def discard(self) -> None:
        self._timeline.discard()


def face_latency_from(shown: list[tuple[int, int]]) -> Callable[[], int | None]:
    """The face's recent capture-to-screen time (median of the last pictures), from the
    receive loop's ``(ready µs, depicted instant µs)`` list, which it keeps appending to."""

    def latency() -> int | None:
        recent = shown[-30:]
        if not recent:
            return None
        return int(np.median([ready - media for ready, media in recent]))

    return latency


def mux_audio(video_path: str | Path, pcm: np.ndarray, bitrate: int = 64_000) -> None:
    """Put ``pcm`` (48 kHz mono int16, sample 0 at the first frame) into the MP4 at
    ``video_path`` beside its video: the video packets are copied, the sound coded as AAC
    and cut or padded to the video's length. The file is replaced when all went well."""
    import av

    video_path = Path(video_path)
    tmp = video_path.with_name(f".{video_path.stem}.mux{video_path.suffix}")
    with av.open(str(video_path)) as src:
        vin = src.streams.video[0]
        duration_s = float(vin.frames / vin.average_rate) if vin.frames and vin.average_rate else 0
        with av.open(str(tmp), "w", format="mp4") as dst:
            vout = dst.add_stream_from_template(vin)
            aout: Any = dst.add_stream("aac", rate=AUDIO_RATE, layout="mono")
            aout.bit_rate = bitrate
            for packet in src.demux(vin):
                if packet.dts is None:
                    continue
                packet.stream = vout
                dst.mux(packet)
            want = round(duration_s * AUDIO_RATE) if duration_s else len(pcm)
            pcm = np.pad(pcm[:want], (0, max(0, want - len(pcm))))
            frame_size = aout.codec_context.frame_size or 1024
            for at in range(0, len(pcm), frame_size):
                chunk = pcm[at : at + frame_size]
                frame = av.AudioFrame.from_ndarray(
                    chunk.reshape(1, -1).astype(np.int16), format="s16", layout="mono"
                )
                frame.sample_rate = AUDIO_RATE
                frame.pts = at
                dst.mux(aout.encode(frame))
            dst.mux(aout.encode(None))
    os.replace(tmp, video_path)


def read_audio(path: str | Path, rate: int = AUDIO_RATE) -> np.ndarray:
    """A file's first audio track as mono int16 at ``rate`` (tests, benchmarks)."""
    import av

    with av.open(str(path)) as src:
        if not src.streams.audio:
            return np.zeros(0, np.int16)
        resampler = av.AudioResampler(format="s16", layout="mono", rate=rate)
        chunks = []
        for frame in src.decode(src.streams.audio[0]):
            chunks += [f.to_ndarray().reshape(-1) for f in resampler.resample(frame)]
        chunks += [f.to_ndarray().reshape(-1) for f in resampler.resample(None)]
    return np.concatenate(chunks) if chunks else np.zeros(0, np.int16)


class CallSound:
    """The receive loop's sound: :meth:`push` it the AudioFrame packets and tell it each
    decoded :meth:`frame`; :meth:`finish` it after the recording is closed."""

    def __init__(
        self,
        shown: list[tuple[int, int]],
        first_seq: int,
        fps: float,
        notify: Callable[[str], None],
        device: bool = True,
        sink: AudioSink | None = None,
    ) -> None:
        self._no_device: str | None = None
        if sink is None:  # a sink given (a room's mixer) is the caller's to speak of
            sink, self._no_device = open_sink(device)
        self._notify = notify  # says there is no device when sound first comes, not before
        self.playout = AudioPlayout(sink, face_latency_from(shown))
        self.first_seq = first_seq
        self.fps = fps

    def frame(self, seq: int, capture_us: int, arrival_us: int | None = None) -> None:
        self.playout.frame(seq, capture_us, arrival_us)

    def push(self, packet: AudioFrame, arrival_us: int) -> None:
        if self._no_device is not None:
            self._notify(self._no_device)
            self._no_device = None
        self.playout.push(packet, arrival_us)

    def delay_us(self) -> int | None:
        """:meth:`AudioPlayout.delay_us`: when, after capture, a picture meets its voice."""
        return self.playout.delay_us()

    def play_out(self) -> None:
        """Play what is buffered (the sender said bye) before :meth:`finish`."""
        self.playout.play_out()

    def finish(self, output: str | Path | None) -> dict[str, Any]:
        """Stop playing; put what was played into the MP4 at ``output`` (if any, and if
        there was sound); the figures (:meth:`AudioReport.as_dict`)."""
        self.playout.close()
        try:
            if output is not None and self.playout.report.packets:
                pcm = self.playout.recorded(self.first_seq, self.fps)
                try:
                    mux_audio(output, pcm)
                except Exception as exc:  # the video alone is still a good recording
                    logger.warning("could not add the sound to %s: %s", output, exc)
        finally:
            self.playout.discard()
        return self.playout.report.as_dict()
