"""The room's gallery: a grid of the peers' newest pictures with their names."""

from __future__ import annotations

import numpy as np

from facewire.room_gallery import TILE, Gallery, grid


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
    gallery.show("alice", np.zeros((480, 640, 3), np.uint8), 80.0, 0)
    gallery.left("bob")
    assert shown[1][0] == (TILE[1], 2 * TILE[0], 3)  # two tiles side by side
    assert shown[-1][0] == (TILE[1], TILE[0], 3)  # bob's gone
    assert [n for _, n in shown] == sorted(n for _, n in shown)
