"""The room's gallery: a grid of the peers' pictures with their names, each held until its
voice is heard."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.room_gallery import GALLERY_FPS, TILE, Gallery, grid


def test_grid_is_the_squarest_that_holds_everyone() -> None:
    w, h = TILE
    assert grid({}).shape == (h, w, 3)
    three = {n: np.full((144, 176, 3), 200, np.uint8) for n in ("carol", "alice", "bob")}
    out = grid(three)
    assert out.shape == (2 * h, 2 * w, 3)
    # Alice's tile first (sorted by name), her picture in it; the fourth place stays empty.
    assert out[h // 2, w // 2].tolist() == [200, 200, 200]
    assert out[h + h // 2, w + w // 2].tolist() == [0, 0, 0]
    # Each tile carries its name: white text on the strip at its foot.
    assert (out[h - 26 : h, :w] == 255).any()


def test_a_tile_without_a_picture_yet_and_who_left() -> None:
    shown = []
    gallery = Gallery(lambda frame, report: shown.append((frame.image.shape, report.frames_out)))
    gallery.joined("alice")
    gallery.joined("bob")
    gallery.show("alice", np.zeros((480, 640, 3), np.uint8), capture_us=0)
    gallery.left("bob")
    assert shown[1][0] == (TILE[1], 2 * TILE[0], 3)  # two tiles side by side
    assert shown[-1][0] == (TILE[1], TILE[0], 3)  # bob's gone
    assert [n for _, n in shown] == sorted(n for _, n in shown)


def test_a_picture_waits_for_its_voice() -> None:
    """Each picture goes on screen when its voice is heard (its capture plus its sound's delay),
    not when it came; of a peer's pictures due by then, the newest."""
    now = [1_000_000]
    drawn: list[tuple[int, dict[str, int]]] = []
    gallery = Gallery(lambda frame, report: None, clock=lambda: now[0])
    gallery.sink = lambda frame, report: drawn.append((now[0], dict(gallery.captured)))
    picture = np.full((144, 176, 3), 90, np.uint8)
    gallery.joined("alice", lambda: 200_000)
    gallery.joined("bob")  # no sound: shown at once
    gallery.show("alice", picture, capture_us=900_000)
    gallery.show("alice", picture, capture_us=933_000)
    gallery.show("bob", picture, capture_us=950_000)
    assert gallery.captured == {"bob": 950_000}
    now[0] = 1_034_000  # drawn a frame after the joins' grid
    gallery.tick()
    assert drawn[-1] == (1_034_000, {"bob": 950_000})
    assert gallery.wait_s() == pytest.approx(0.066)
    now[0] = 1_099_000
    gallery.tick()
    assert "alice" not in gallery.captured  # not yet
    now[0] = 1_140_000  # the loop was late: the newest picture due goes up
    gallery.tick()
    assert drawn[-1] == (1_140_000, {"alice": 933_000, "bob": 950_000})
    assert gallery.wait_s() == float("inf")


def test_the_grid_is_drawn_at_most_at_the_frame_rate() -> None:
    now = [0]
    drawn: list[int] = []
    gallery = Gallery(lambda frame, report: drawn.append(now[0]), clock=lambda: now[0])
    picture = np.zeros((144, 176, 3), np.uint8)
    for i in range(10):  # a picture every 10 ms
        now[0] = i * 10_000
        gallery.show("alice", picture, capture_us=now[0])
    now[0] = 100_000
    gallery.tick()
    assert drawn == [0, 40_000, 80_000]  # 30 a second: 33 ms apart at least
    assert gallery.wait_s() == pytest.approx((80_000 + 1e6 / GALLERY_FPS - 100_000) / 1e6, abs=1e-6)
    now[0] = 114_000
    gallery.tick()
    assert drawn[-1] == 114_000 and gallery.captured["alice"] == 90_000


def test_the_pictures_follow_the_sound_as_it_catches_up() -> None:
    # The sound's delay went down while pictures waited (it left out quiet steps to catch
    # up, or a new run of it chose a shorter one): they go up at the delay of then.
    now = [0]
    delay = [900_000]
    gallery = Gallery(lambda frame, report: None, clock=lambda: now[0])
    gallery.joined("alice", lambda: delay[0])
    picture = np.zeros((144, 176, 3), np.uint8)
    gallery.show("alice", picture, capture_us=0)
    gallery.show("alice", picture, capture_us=33_000)
    assert gallery.wait_s() == pytest.approx(0.9)
    delay[0] = 200_000
    assert gallery.wait_s() == pytest.approx(0.2)
    now[0] = 233_000
    gallery.tick()
    assert gallery.captured == {"alice": 33_000}
