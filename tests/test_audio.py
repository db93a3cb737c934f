"""Sound: AudioFrame packets, Opus through PyAV, the jitter buffer's concealment, odd inputs.

Real parts: the bundled clip's speech track coded by libopus, decoded by the receiver's
AudioPlayout on its own thread against the real clock (into a null sink: no sound device is
needed), files made with PyAV.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from facewire.protocol.constants import AUDIO_FRAME_SAMPLES, AUDIO_RATE
from facewire.protocol.packets import AudioFrame, KeyFrame, PacketError, decode
from facewire.receiver.audio import (
    FRAME_US,
    MARGIN_US,
    MIN_LATENCY_US,
    AudioPlayout,
    NullSink,
    OpusDecoder,
    _Timeline,
    _toc_of_20_ms,
    mux_audio,
    read_audio,
)
from facewire.sender.audio import (
    AudioSender,
    AudioSettings,
    demo_speech_path,
    frame_ms_for,
    open_track,
    sound_for,
)
from facewire.sender.capture import demo_clip_path
from tests.voices import talking_clip, talking_voice, voice_match

FIXTURES = Path(__file__).parent / "fixtures" / "packets"


def coded_speech(**settings: object) -> list[AudioFrame]:
    """The bundled clip's speech as the sender sends it (capture clock: 0 at frame 0)."""
    out: list[AudioFrame] = []
    track = open_track(demo_speech_path())
    assert track is not None
    sender = AudioSender(track, out.append, AudioSettings(**settings))  # type: ignore[arg-type]
    for i in range(301):
        sender.send_until(i / 30, i / 30, round(i * 1e6 / 30))
    return out


@pytest.fixture(scope="module")
def speech() -> list[AudioFrame]:
    return coded_speech()


# --- packets ---------------------------------------------------------------------------------


def test_fixture_is_a_real_opus_frame() -> None:
    data = (FIXTURES / "audio_frame.bin").read_bytes()
    packet = decode(data)
    assert isinstance(packet, AudioFrame)
    assert (packet.seq, packet.capture_us, len(packet.data)) == (305, 1_700_006_093_500, 22)
    assert bytes(packet) == data and data[0] == 0x2A
    assert len(OpusDecoder().decode(packet.data)) == AUDIO_FRAME_SAMPLES


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"\x2a" + bytes(12), "truncated AudioFrame: 13 bytes, needs at least 14"),
        (b"\x2a\x01", "truncated AudioFrame: 2 bytes, needs at least 14"),
        (b"\x2a" + bytes(12) + bytes(1276), "AudioFrame.data: 1276 bytes outside [1, 1275]"),
    ],
)
def test_bad_audio_frames_are_refused_with_one_line(data: bytes, message: str) -> None:
    with pytest.raises(PacketError) as exc:
        decode(data)
    assert str(exc.value) == message


# --- coding ----------------------------------------------------------------------------------


def test_speech_is_coded_near_the_bit_rate_asked_and_silence_is_left_out(speech) -> None:
    talking = [p for p in speech if 300 <= p.seq <= 420]  # 6.0-8.4 s: the clip talks
    kbps = sum(len(p.data) for p in talking) * 8 / (len(talking) * 0.02) / 1000
    assert 8 < kbps < 16
    # DTX: of 500 steps of which ~130 carry sound, the silent ones are not sent.
    assert 100 < len(speech) < 200
    louder = coded_speech(bitrate=24_000)
    loud = [p for p in louder if 300 <= p.seq <= 420]
    assert sum(len(p.data) for p in loud) > 1.6 * sum(len(p.data) for p in talking)
    assert len(coded_speech(dtx=False)) == 500


def test_capture_times_follow_the_video_clock(speech) -> None:
    # Step s decodes to the input from s * 20 ms less the coder's look-ahead (6.5 ms).
    for p in speech:
        assert p.capture_us == pytest.approx(p.seq * 20_000 - 6_500, abs=50)


@pytest.mark.parametrize("frame_ms", [40, 60])
def test_longer_packets_cover_their_steps(speech, frame_ms: int) -> None:
    """A thin budget's 40 or 60 ms packets: each one's seq is its first 20 ms step, the
    capture times stay on the clock, and the same speech takes 2 or 3 times fewer packets."""
    longer = coded_speech(frame_ms=frame_ms)
    steps = frame_ms // 20
    assert all(p.seq % steps == 0 for p in longer)
    for p in longer:
        assert p.capture_us == pytest.approx(p.seq * 20_000 - 6_500, abs=50)
    assert len(longer) <= len(speech) / steps + 10
    # What a datagram carries besides Opus (the AudioFrame's 13 bytes a packet) shrinks.
    assert 13 * len(longer) < 13 * len(speech) * 0.6


def test_the_budget_sets_the_packet_length() -> None:
    assert [frame_ms_for(b) for b in (64_000, 32_000, 24_000, 20_000, 16_000, 8_000)] == [
        20,
        20,
        40,
        40,
        60,
        60,
    ]


# --- playout ---------------------------------------------------------------------------------


def play(packets: list[AudioFrame], latency_us: int = 60_000) -> AudioPlayout:
    """Play ``packets`` now, as if captured just now; wait until they are done."""
    playout = AudioPlayout(NullSink(), lambda: latency_us)
    shift = time.monotonic_ns() // 1000 - packets[0].capture_us
    # Video frame 0 captured with the first packet: the recording starts with it.
    playout.push(KeyFrame(0, 1, 0, packets[0].capture_us + shift, b""))
    for p in packets:
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data), p.capture_us + shift)
    span_s = (packets[-1].seq - packets[0].seq + 1) * 0.02
    time.sleep(span_s + latency_us / 1e6 + 0.3)
    playout.close()
    return playout


def talk(speech: list[AudioFrame]) -> list[AudioFrame]:
    return [p for p in speech if 330 <= p.seq < 380]  # one second of continuous speech


def test_a_lost_packet_is_concealed_by_the_codec(speech) -> None:
    packets = talk(speech)
    assert [p.seq for p in packets] == list(range(330, 380))
    whole = play(packets)
    lost = play([p for p in packets if p.seq != 355])
    # The end of the sound is concealed the same way in both (the codec fades it out).
    assert whole.report.played == 50 and lost.report.played == 49
    assert lost.report.concealed == whole.report.concealed + 1
    a, b = whole.recorded(0, 30.0), lost.recorded(0, 30.0)
    at = 25 * AUDIO_FRAME_SAMPLES
    gap = slice(at, at + AUDIO_FRAME_SAMPLES)
    ref = a[gap].astype(float)
    made_up = b[gap].astype(float)
    # Not silence: the concealment continues the voice, closer to it than silence is.
    assert np.sqrt(np.mean(made_up**2)) > 0.2 * np.sqrt(np.mean(ref**2))
    assert np.mean((made_up - ref) ** 2) < np.mean(ref**2)
    # Everything else is the same sound.
    assert np.array_equal(a[:at], b[:at])
    whole.discard()
    lost.discard()


def test_a_60_ms_packet_plays_its_three_steps_and_its_loss_is_concealed() -> None:
    packets = [p for p in coded_speech(frame_ms=60) if 330 <= p.seq < 380]
    assert len(packets) == 17  # steps 330 to 380
    whole = play(packets)
    lost = play([p for p in packets if p.seq != 354])
    assert whole.report.played == 51 and whole.report.malformed == 0
    assert lost.report.played == 48 and lost.report.concealed == whole.report.concealed + 3
    a, b = whole.recorded(0, 30.0), lost.recorded(0, 30.0)
    talking = a[: 45 * AUDIO_FRAME_SAMPLES].astype(float)
    assert np.sqrt(np.mean(talking**2)) > 300  # the voice, not silence
    at = 24 * AUDIO_FRAME_SAMPLES  # the lost packet's 60 ms
    gap = b[at : at + 3 * AUDIO_FRAME_SAMPLES].astype(float)
    assert np.sqrt(np.mean(gap[:AUDIO_FRAME_SAMPLES] ** 2)) > 0.1 * np.sqrt(np.mean(talking**2))
    assert np.array_equal(a[:at], b[:at])
    whole.discard()
    lost.discard()


def test_concealment_asks_for_20_ms_whatever_the_packets_length() -> None:
    """The lost-frame packet's TOC keeps the mode and the bandwidth (RFC 6716, 3.1)."""
    assert _toc_of_20_ms(0x58) == 0x48  # SILK wideband 60 ms -> 20 ms
    assert _toc_of_20_ms(0x53) == 0x48  # SILK wideband 40 ms, code 3 -> one frame
    assert _toc_of_20_ms(0x60) == 0x68  # hybrid super-wideband 10 ms -> 20 ms
    assert _toc_of_20_ms(0xF8 | 0x04) == 0xFC  # CELT fullband 20 ms, stereo stays


def test_a_run_started_too_late_catches_up_in_the_pauses(speech) -> None:
    """The first packet stamped 80 ms after the pace of the rest (a sender's first frames,
    stamped when the call began) sets the whole run 80 ms late; quiet steps between words are
    left out on the device until the sound is no later than it needs to be."""
    packets = [p for p in speech if 300 <= p.seq < 420]  # the words, with pauses between
    first = packets[0]
    packets[0] = AudioFrame(first.seq, first.capture_us + 80_000, first.data)
    played = play(packets)
    report = played.report
    latencies = [audio for audio, _ in report.latency_us]
    print(f"shortened {report.shortened}, latency first {latencies[0] / 1e3:.0f} ms, "
          f"last {latencies[-1] / 1e3:.0f} ms")  # fmt: skip
    # Here every packet has come before the run starts: their transits (and the face's 60 ms
    # behind its capture) set what it needs, not MIN_LATENCY_US, the guess before them.
    needed = 60_000
    assert latencies[1] > needed + 70_000  # the run began 80 ms later than needed
    assert 4 <= report.shortened <= 6
    assert needed - 5_000 < latencies[-1] <= needed + 5_000
    assert latencies[1] - latencies[-1] >= 80_000 - 5_000
    assert report.late == 0
    # The recording keeps every step: nothing left out there.
    assert len(played.recorded(0, 30.0)) >= (420 - 300 - 10) * AUDIO_FRAME_SAMPLES
    played.discard()


def test_once_its_packets_have_come_the_sound_waits_what_they_need(speech) -> None:
    """MIN_LATENCY_US is a guess made before the link is known. Packets that take 40 ms (on
    loopback a datagram carries each frame) with pictures shown 20 ms after capture: the sound
    starts at the guess, then catches up in the pauses to what its packets need (their slowest,
    a step and a margin), not 140 ms behind a picture shown at 20 (held for good, it put the
    demo's voice 119 ms behind the face), and to within a few ms of it: whole steps left out
    stopped up to a step short (81 ms here)."""
    packets = [p for p in speech if 300 <= p.seq < 420]  # words, with pauses to catch up in
    playout = AudioPlayout(NullSink(), lambda: 20_000)
    shift = time.monotonic_ns() // 1000 + 20_000 - packets[0].capture_us
    for p in packets:
        arrive = p.capture_us + shift + 40_000
        time.sleep(max(0.0, (arrive - time.monotonic_ns() // 1000) / 1e6))
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data))
    time.sleep(0.6)
    playout.close()
    report = playout.report
    latencies = [audio for audio, _ in report.latency_us]
    print(f"latency first {latencies[0] / 1e3:.0f} ms, last {latencies[-1] / 1e3:.0f} ms, "
          f"shortened {report.shortened}, late {report.late}")  # fmt: skip
    assert latencies[0] >= MIN_LATENCY_US - 5_000  # the guess, before the packets showed more
    assert latencies[-1] <= 40_000 + FRAME_US + MARGIN_US + 5_000
    assert report.shortened >= 3 and report.late == 0
    playout.discard()


def test_packets_that_come_late_make_the_run_wait_longer(speech) -> None:
    """Half-way through a second of speech the packets start taking 30 ms more than the run's
    latency allows (a path that got slower): each late one makes the run wait a step longer
    (concealment on the device), so after two the rest are in time again; before, all were
    late until the sound had been missing 200 ms and a new run began."""
    packets = talk(speech)
    playout = AudioPlayout(NullSink(), lambda: None)
    start = time.monotonic_ns() // 1000 + 20_000
    shift = start - packets[0].capture_us
    for p in packets:
        transit = 20_000 if p.seq < 355 else MIN_LATENCY_US + 30_000
        arrive = p.capture_us + shift + transit
        time.sleep(max(0.0, (arrive - time.monotonic_ns() // 1000) / 1e6))
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data))
    time.sleep(0.6)
    playout.close()
    report = playout.report
    print(f"late {report.late}, stretched {report.stretched}, played {report.played}")
    assert 1 <= report.late <= 4  # 30 ms more: a few steps of concealment catch up with it
    assert report.stretched == report.late
    assert report.played == len(packets) - report.late
    playout.discard()


def test_the_first_words_follow_the_pictures_transit(speech) -> None:
    """Before its own packets have come, the sound takes its latency from the video frames'
    capture-to-arrival (100 ms; a stalled one of 1.5 s changes nothing) and what sound waits
    for on top of it: its first words are in time though the first packet came in 100 ms and
    some later ones take 190 (a lossy link's repeats), where the first packet's transit and the
    least latency (140 ms) made those late."""
    packets = talk(speech)[:20]
    playout = AudioPlayout(NullSink(), lambda: 50_000)
    start = time.monotonic_ns() // 1000 + 20_000
    shift = start - packets[0].capture_us
    for i in range(30):  # a second of pictures before the voice
        capture = start - 1_000_000 + i * 33_333
        playout.frame(i, capture, capture + (1_500_000 if i == 20 else 100_000))
    for p in packets:
        arrive = p.capture_us + shift + (190_000 if p.seq % 4 == 3 else 100_000)
        time.sleep(max(0.0, (arrive - time.monotonic_ns() // 1000) / 1e6))
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data))
    time.sleep(0.5)
    playout.close()
    assert playout.report.late == 0 and playout.report.played == 20
    latencies = [audio for audio, _ in playout.report.latency_us]
    assert max(latencies) < 300_000  # not the stalled frame's 1.5 s
    playout.discard()


def test_a_malformed_opus_packet_is_counted_and_concealed(speech) -> None:
    packets = talk(speech)[:20]
    bad = AudioFrame(packets[5].seq, packets[5].capture_us, bytes([0x4B]) + b"\xff" * 3)
    played = play(packets[:5] + [bad] + packets[6:])
    report = played.report
    assert report.malformed == 1 and report.played == 19
    assert report.concealed == 1 + 5  # the bad one, then the end's fade (CONCEAL_FRAMES)
    assert len(played.recorded(0, 30.0)) >= 20 * AUDIO_FRAME_SAMPLES
    played.discard()


# --- inputs ----------------------------------------------------------------------------------


def write_tone(path: Path, rate: int, layout: str, codec: str = "pcm_s16le") -> None:
    import av

    channels = {"mono": 1, "stereo": 2, "5.1": 6}[layout]
    t = np.arange(rate // 2) / rate
    tone = (0.3 * np.sin(2 * np.pi * 440 * t) * 32767).astype(np.int16)
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=rate, layout=layout)
        pcm = np.tile(tone, (channels, 1)) if channels > 1 else tone.reshape(1, -1)
        frame = av.AudioFrame.from_ndarray(
            np.ascontiguousarray(pcm.T.reshape(1, -1)), format="s16", layout=layout
        )
        frame.sample_rate = rate
        for packet in stream.encode(frame):
            out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)


@pytest.mark.parametrize(("rate", "layout"), [(8000, "mono"), (44100, "stereo"), (96000, "5.1")])
def test_any_rate_and_layout_becomes_48_khz_mono(tmp_path: Path, rate: int, layout: str) -> None:
    path = tmp_path / "tone.wav"
    write_tone(path, rate, layout)
    track = open_track(path)
    assert track is not None
    chunks = []
    while (chunk := track.read(4800)) is not None:
        chunks.append(chunk)
    pcm = np.concatenate(chunks)
    assert abs(len(pcm) - AUDIO_RATE // 2) < 100
    spectrum = np.abs(np.fft.rfft(pcm.astype(float)))
    assert abs(np.argmax(spectrum) * AUDIO_RATE / len(pcm) - 440) < 5


def test_a_file_without_sound_is_said_in_one_line() -> None:
    lines: list[str] = []
    sender = sound_for(demo_clip_path().with_name("x.mp4"), False, True, print, notify=lines.append)
    assert sender is None
    assert len(lines) == 1 and "no audio track" in lines[0] or "cannot read sound" in lines[0]
    # The bundled clip has no audio track either: its speech lies beside it.
    assert open_track(demo_clip_path()) is None
    assert sound_for(demo_clip_path(), False, True, print) is not None
    lines.clear()
    assert sound_for(demo_clip_path(), False, False, print, notify=lines.append) is None
    assert lines == ["no sound: the file is read faster than its frame rate"]


def test_mux_puts_the_sound_beside_the_video(tmp_path: Path) -> None:
    import cv2

    video = tmp_path / "v.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*"mp4v"), 30.0, (64, 48))
    for i in range(30):
        writer.write(np.full((48, 64, 3), i * 8, np.uint8))
    writer.release()
    t = np.arange(AUDIO_RATE) / AUDIO_RATE
    pcm = (0.3 * np.sin(2 * np.pi * 300 * t) * 32767).astype(np.int16)
    mux_audio(video, pcm)
    back = read_audio(video)
    assert abs(len(back) - AUDIO_RATE) < 2048
    n = min(len(back), len(pcm))
    assert np.corrcoef(back[2048 : n - 2048], pcm[2048 : n - 2048])[0, 1] > 0.95
    cap = cv2.VideoCapture(str(video))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 30


@pytest.mark.parametrize(
    "case", ["voice-at-6-s", "voice-from-the-start", "sender-behind", "no-sound"]
)
def test_send_and_receive_record_the_voice_with_the_face(tmp_path: Path, case: str) -> None:
    """``facewire send`` and ``facewire receive --record`` as a user runs them: the recording
    carries the voice where the input had it beside the same frames. The bundled clip speaks
    from 6 s on; a clip that speaks from its first frame meets the sender's slow first frames
    (the recording once put its voice 50 ms late). A sender that shares its core with a busy
    process keeps up by leaving frames out: the voice stays whole (it once sent its sound at
    the pace of its frames, and 50 of 110 packets came after their turn)."""
    from cli_call import Facewire, all_end_well, free_ports

    behind = case == "sender-behind"
    if behind and len(os.sched_getaffinity(0)) < 2:
        pytest.skip("needs two cores: the sender's, shared, and the receiver's")
    port = free_ports(2)
    record = tmp_path / "call.mp4"
    talking = case == "voice-from-the-start"
    clip = tmp_path / "talking.mp4"
    source = (
        ("--input", str(talking_clip(clip, talking_voice()))) if talking else ("--frames", "240")
    )
    cores = sorted(os.sched_getaffinity(0))[:2]
    busy = [sys.executable, "-c", "while True: pass"]
    hog = subprocess.Popen(["taskset", "-c", str(cores[0]), *busy]) if behind else None
    try:
        receiver = Facewire(
            "receive", "--bind", f"tcp://127.0.0.1:{port}", "--plain", "--once",
            "--record", str(record),
            prefix=("taskset", "-c", str(cores[1])) if behind else (),
        )  # fmt: skip
        sender = Facewire(
            "send", "--connect", f"tcp://127.0.0.1:{port}", "--plain", *source,
            *(("--no-sound",) if case == "no-sound" else ()),
            prefix=("taskset", "-c", str(cores[0])) if behind else (),
        )  # fmt: skip
        all_end_well(sender, receiver)
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    print(sender.lines[-1])
    recorded = read_audio(record)
    if case == "no-sound":
        assert len(recorded) == 0, "--no-sound recorded sound"
        return
    frames = 120 if talking else 240
    assert abs(len(recorded) - frames / 30 * AUDIO_RATE) < AUDIO_RATE // 10
    if talking:
        said = read_audio(source[1])
    else:
        track = open_track(demo_speech_path())
        assert track is not None
        said = track.read(len(recorded))
    assert said is not None
    spoken = slice(0 if talking else 6 * AUDIO_RATE, min(len(recorded), len(said)))
    correlation, lag_ms = voice_match(recorded[spoken], said[spoken])
    print(f"voice correlation {correlation:.2f} at {lag_ms:+.0f} ms")
    assert correlation > 0.9 and abs(lag_ms) <= 20


def test_a_looped_file_plays_its_sound_again() -> None:
    """``send --loop`` sends the file's sound again with its pictures, not once."""
    from facewire.sender.audio import LoopedTrack

    once = open_track(demo_speech_path())
    assert once is not None
    first = once.read(10 * AUDIO_RATE)
    assert first is not None and once.read(AUDIO_FRAME_SAMPLES) is None
    looped = LoopedTrack(demo_speech_path())
    read = [looped.read(AUDIO_RATE) for _ in range(25)]
    assert all(pcm is not None and len(pcm) > 0 for pcm in read)
    again = np.concatenate([pcm for pcm in read if pcm is not None])
    assert len(again) >= 2 * len(first)
    assert np.array_equal(again[len(first) : 2 * len(first)], first)


# --- capture times that lie (a hostile or broken sender) --------------------------------------

HOUR_US = 3600 * 1_000_000


def play_after(
    first: AudioFrame, packets: list[AudioFrame], face_us: int | None
) -> tuple[AudioPlayout, bool]:
    """Push ``first`` (its capture time as given, relative to the others'), then ``packets``
    as if captured just now; wait until they are played; close. Whether close() ended the
    sound's thread (it once slept for as long as the first packet said)."""
    playout = AudioPlayout(NullSink(), lambda: face_us)
    shift = time.monotonic_ns() // 1000 - packets[0].capture_us
    now = packets[0].capture_us + shift
    playout.push(AudioFrame(first.seq, first.capture_us + shift, first.data), now)
    for p in packets:
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data), p.capture_us + shift)
    time.sleep(len(packets) * 0.02 + MIN_LATENCY_US / 1e6 + 0.3)
    playout.close()
    stopped = not playout._thread.is_alive()
    playout.discard()
    return playout, stopped


@pytest.mark.parametrize(
    ("ahead_us", "face_us"),
    [(HOUR_US, 60_000), (HOUR_US, None), (2**62, None), (-HOUR_US, 60_000)],
    ids=["hour-ahead", "hour-ahead-before-any-picture", "near-2^62", "hour-behind"],
)
def test_a_packet_whose_capture_time_lies_does_not_hold_the_sound(
    speech: list[AudioFrame], ahead_us: int, face_us: int | None
) -> None:
    """One AudioFrame an hour ahead made the sound's thread sleep an hour (close() waited
    for it: the receiver ignored SIGTERM); one near 2^62 killed it (OverflowError). The run
    it begins is due too far ahead or behind: it is dropped, and the run starts from the next
    packet; the packets after it outvote its time, so the latency does not take it."""
    packets = talk(speech)
    liar = AudioFrame(packets[0].seq - 1, packets[0].capture_us + ahead_us, packets[0].data)
    playout, stopped = play_after(liar, packets, face_us)
    assert stopped
    assert playout.report.played == len(packets) and playout.report.refused >= 1


def test_close_ends_a_long_wait_at_once(speech: list[AudioFrame]) -> None:
    """A face 4 s behind (within the limits) makes the sound wait 4 s: close() ends it."""
    playout = AudioPlayout(NullSink(), lambda: 4_000_000)
    packets = talk(speech)[:5]
    shift = time.monotonic_ns() // 1000 - packets[0].capture_us
    for p in packets:
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data), p.capture_us + shift)
    time.sleep(0.1)
    assert playout._next == packets[0].seq  # waiting for its first step
    playout.close()
    assert not playout._thread.is_alive()
    playout.discard()


def test_the_sound_file_grows_no_faster_than_the_call() -> None:
    """A run stamped an hour after the last one is written a second after it, not an hour
    of silence (345 MB) later."""
    clock = [0]
    timeline = _Timeline(lambda: clock[0])
    pcm = np.ones(AUDIO_FRAME_SAMPLES, np.int16)
    timeline.put(0, pcm)
    clock[0] += 20_000
    timeline.put(HOUR_US, pcm)
    timeline.close()
    assert timeline.samples <= 2 * AUDIO_RATE
    assert len(timeline.read()) == timeline.samples
    timeline.discard()
