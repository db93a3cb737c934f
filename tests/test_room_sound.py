"""The room's mixer: every peer's steps summed into the one stream a sound device plays.

The device itself is not here (this machine has none): :meth:`Mixer.fill` is what its
callback calls. That the room says once that there is no device, and records each voice, is
tests/test_room.py's.
"""

from __future__ import annotations

import numpy as np

from facewire.protocol.constants import AUDIO_FRAME_SAMPLES, AUDIO_RATE
from facewire.room_sound import MAX_QUEUED, Mixer, RoomSound


def _tone(hz: float, amplitude: int, samples: int = AUDIO_FRAME_SAMPLES) -> np.ndarray:
    t = np.arange(samples) / AUDIO_RATE
    return np.round(amplitude * np.sin(2 * np.pi * hz * t)).astype(np.int16)


def test_the_peers_steps_are_added_and_clipped() -> None:
    mixer = Mixer()
    alice, bob = mixer.input("alice"), mixer.input("bob")
    a, b = _tone(440, 20_000), _tone(660, 20_000)
    alice.write(a)
    bob.write(b)
    mixed = mixer.fill(AUDIO_FRAME_SAMPLES)
    want = np.clip(a.astype(np.int32) + b, -32768, 32767)
    assert np.array_equal(mixed, want)
    assert mixed.max() == 32767 and mixed.min() == -32768  # clipped, not wrapped round


def test_a_peer_with_nothing_queued_adds_silence_and_one_gone_adds_nothing() -> None:
    mixer = Mixer()
    alice, bob = mixer.input("alice"), mixer.input("bob")
    a = _tone(440, 8_000, 3 * AUDIO_FRAME_SAMPLES // 2)
    alice.write(a)
    first = mixer.fill(AUDIO_FRAME_SAMPLES)
    assert np.array_equal(first, a[:AUDIO_FRAME_SAMPLES])
    second = mixer.fill(AUDIO_FRAME_SAMPLES)  # half a step left, then silence
    assert np.array_equal(second[: len(a) - AUDIO_FRAME_SAMPLES], a[AUDIO_FRAME_SAMPLES:])
    assert not second[len(a) - AUDIO_FRAME_SAMPLES :].any()
    bob.write(_tone(660, 8_000))
    bob.close()  # bob left: what he had queued is not played
    alice.write(a[:AUDIO_FRAME_SAMPLES])
    assert np.array_equal(mixer.fill(AUDIO_FRAME_SAMPLES), a[:AUDIO_FRAME_SAMPLES])


def test_a_slow_device_drops_the_oldest_sound_not_the_newest() -> None:
    mixer = Mixer()
    alice = mixer.input("alice")
    steps = [np.full(AUDIO_FRAME_SAMPLES, i, np.int16) for i in range(20)]
    for step in steps:
        alice.write(step)
    kept = MAX_QUEUED // AUDIO_FRAME_SAMPLES
    assert alice.dropped == (20 - kept) * AUDIO_FRAME_SAMPLES
    out = mixer.fill(kept * AUDIO_FRAME_SAMPLES)
    assert np.array_equal(out, np.concatenate(steps[20 - kept :]))


def test_without_a_device_each_peer_plays_into_a_null_sink_of_its_own() -> None:
    said: list[str] = []
    room = RoomSound(said.append, device=False)
    alice = room.for_peer("alice", [], 30.0)
    bob = room.for_peer("bob", [], 30.0)
    assert alice.playout.sink is not bob.playout.sink
    room.heard()
    assert said == []  # no device was asked for: nothing to say
    for sound in (alice, bob):
        assert sound.finish(None)["sink"] == "no sound device"
    room.close()
