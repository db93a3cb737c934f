"""What the receiver shows of the camera's picture where the model fails (Refresh packets).

Each refresh is an image of an area of the frame (a hand raised to the chin, an object, the
scene a person uncovered), shown over the warped surroundings from its frame on and under
the drawn face, which stays the geometry's (and not at the face's edge, where the face fades
into what is under it); or, for something in front of the face (a hand), over the drawn face
too (:meth:`RefreshLayer.on_top`). Its border fades over :data:`FEATHER` of its shorter
side, so the area's edge does not show as a seam. A new refresh takes the place of every
earlier one it overlaps; an empty one gives its area back to the model. Both ends keep one
(the sender, to compare its frame with what the receiver shows: sender/refresh.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: The border fades over this share of the refresh's shorter side.
FEATHER = 0.2
#: A refresh does not show on the face's outline grown by this share about its centre.
FACE_MARGIN = 0.15
#: Most refreshes shown at once: the oldest goes first.
MAX_SHOWN = 8


@dataclass(frozen=True)
class _Area:
    seq: int
    x: int
    y: int
    image: np.ndarray  # (h, w, 3) uint8, scaled to the area
    weight: np.ndarray  # (h, w, 1) float32
    on_top: bool  # shown over the drawn face too (a hand in front of it)

    @property
    def box(self) -> tuple[int, int, int, int]:
        h, w = self.image.shape[:2]
        return self.x, self.y, self.x + w, self.y + h


class RefreshLayer:
    """The refreshes of one session over a ``width`` x ``height`` picture."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self._waiting: list[tuple[int, int, int, int, int, np.ndarray | None, bool]] = []
        self._shown: list[_Area] = []

    def fits(self, x: int, y: int, width: int, height: int) -> bool:
        """Whether an area lies inside the picture."""
        return x >= 0 and y >= 0 and x + width <= self.width and y + height <= self.height

    def add(
        self,
        seq: int,
        x: int,
        y: int,
        width: int,
        height: int,
        image: np.ndarray | None,
        on_top: bool = False,
    ) -> None:
        """Keep a refresh of frame ``seq`` (shown from :meth:`due` of that frame on): ``image``
        (any size, BGR) over the area, or None to give it back to the model; ``on_top``: over
        the drawn face too (:meth:`on_top`)."""
        if not self.fits(x, y, width, height):
            raise ValueError(f"refresh area {width}x{height} at ({x}, {y}) outside the picture")
        self._waiting.append((seq, x, y, width, height, image, on_top))

    def due(self, seq: int) -> None:
        """Show the refreshes of frames up to ``seq``, in the order they came."""
        later = []
        for item in self._waiting:
            if item[0] > seq:
                later.append(item)
                continue
            _, x, y, w, h, image, on_top = item
            box = (x, y, x + w, y + h)
            self._shown = [a for a in self._shown if not _overlap(a.box, box)]
            if image is not None:
                scaled = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
                self._shown.append(_Area(item[0], x, y, scaled, _feather(w, h), on_top))
        self._waiting = later
        del self._shown[:-MAX_SHOWN]

    def __len__(self) -> int:
        return len(self._shown)

    def over(self, picture: np.ndarray, face: np.ndarray | None = None) -> np.ndarray:
        """``picture`` (height, width, 3) uint8 with the refreshes shown over it (in place),
        except on ``face`` (k, 2), the face's outline in it, grown by FACE_MARGIN about its
        centre: the face drawn over it fades into the picture at its edge, and a refresh
        cut a moment ago must not show through there as the face moves on."""
        grown = None
        if face is not None and len(self._shown):
            centre = face.mean(0)
            grown = centre + (1.0 + FACE_MARGIN) * (face - centre)
        for area in self._shown:
            if area.on_top:
                continue
            weight = area.weight
            if grown is not None:
                x0, y0, x1, y1 = area.box
                inside = np.zeros((y1 - y0, x1 - x0), np.uint8)
                cv2.fillPoly(inside, [np.round(grown - (x0, y0)).astype(np.int32)], 1)
                weight = weight * (1 - inside)[..., None]
            _blend(picture, area, weight)
        return picture

    def on_top(self, picture: np.ndarray) -> np.ndarray:
        """``picture`` (height, width, 3) uint8, the face drawn, with the refreshes shown over
        the face too blended in (in place): what is in front of the face."""
        for area in self._shown:
            if area.on_top:
                _blend(picture, area, area.weight)
        return picture


def _blend(picture: np.ndarray, area: _Area, weight: np.ndarray) -> None:
    x0, y0, x1, y1 = area.box
    under = picture[y0:y1, x0:x1].astype(np.float32)
    mixed = under + weight * (area.image.astype(np.float32) - under)
    picture[y0:y1, x0:x1] = np.clip(mixed + 0.5, 0, 255).astype(np.uint8)


def _feather(width: int, height: int) -> np.ndarray:
    """(height, width, 1) float32: 1 inside, easing to 0 at the border."""
    reach = max(1.0, FEATHER * min(width, height))
    xs = np.minimum(np.arange(width) + 0.5, width - np.arange(width) - 0.5) / reach
    ys = np.minimum(np.arange(height) + 0.5, height - np.arange(height) - 0.5) / reach
    ramp = np.minimum(np.clip(ys, 0, 1)[:, None], np.clip(xs, 0, 1)[None, :])
    return (ramp * ramp * (3.0 - 2.0 * ramp)).astype(np.float32)[..., None]


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
