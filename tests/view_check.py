"""What a person sees on the live view's page, checked from Chromium's screenshots
(tests/browser.py) of a call sending the bundled clip.

The picture must be the rebuilt face: the landmark tracker finds a face in the picture area
of the screenshot, where the clip frame it looks most like has it, and the face region looks
like that frame. Two screenshots apart must show two different pictures and a frame count
that went up (a live picture and live figures, not a frozen one), and the figures must be
filled in and written on the page.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache
from typing import Any

import cv2
import numpy as np

from facewire.quality import frame_scores, read_frames, region_masks, track_all
from facewire.sender.capture import demo_clip_path

#: Face-region SSIM of the page's picture against the clip frame it looks most like.
#: Measured on Chromium's screenshots of a loopback call: 0.71 and 0.73; a flat grey picture
#: scores 0.48-0.51, black 0.00, the clip five seconds away 0.30-0.35.
MIN_FACE_SSIM = 0.6
#: Median distance (px) between the landmarks found in the page's picture and in that frame.
MAX_LANDMARK_PX = 12.0
#: Mean absolute difference (grey levels) between two screenshots' pictures 1.5 s apart: a
#: frozen picture gives 0 (JPEG is deterministic), the talking face 2 or more.
MIN_CHANGE = 0.5
#: Light pixels (text on the page's dark background) in each figure's cell: 45-300 with a
#: figure written in it ("8" is 47), about 10 for the dash the page starts with.
MIN_TEXT_PIXELS = 25

SIZE = (640, 480)


@dataclass
class Seen:
    """One screenshot's picture and what the page's figures said."""

    picture: np.ndarray  # (480, 640, 3) BGR, cut from the screenshot
    page: dict[str, Any]
    clip_frame: int  # the bundled clip's frame it looks most like
    face_ssim: float
    landmark_px: float


@cache
def _clip() -> tuple[list[np.ndarray], np.ndarray]:
    frames = list(read_frames(demo_clip_path()))
    return frames, np.stack([_small(f) for f in frames])


def _small(image: np.ndarray) -> np.ndarray:
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return cv2.resize(grey, (160, 120), interpolation=cv2.INTER_AREA).astype(np.float32)


def _box(shot: np.ndarray, rect: dict[str, float]) -> np.ndarray:
    x, y = round(rect["x"]), round(rect["y"])
    return shot[y : y + round(rect["height"]), x : x + round(rect["width"])]


def number(text: str) -> float:
    """The first number in a figure's text ("27.4 ms" -> 27.4); NaN when there is none."""
    found = re.search(r"-?\d+(?:\.\d+)?", text)
    return float(found[0]) if found else float("nan")


def see_picture(picture: np.ndarray, page: dict[str, Any] | None = None) -> Seen:
    """A (480, 640, 3) BGR picture a person sees, matched against the bundled clip."""
    assert picture.shape[1::-1] == SIZE, f"the picture is drawn at {picture.shape}: {page}"
    frames, small = _clip()
    index = int(np.abs(small - _small(picture)).mean(axis=(1, 2)).argmin())
    found, expected = track_all([picture, frames[index]])
    assert expected is not None, f"no face in the clip's frame {index}"
    assert found is not None, "no face in the picture"
    landmark_px = float(np.median(np.linalg.norm(found[:, :2] - expected[:, :2], axis=1)))
    masks = region_masks(expected, picture.shape)
    face_ssim = frame_scores(frames[index], picture, {"face": masks["face"]})["face"][0]
    return Seen(picture, page or {}, index, face_ssim, landmark_px)


def see(shot_path: str, page: dict[str, Any]) -> Seen:
    """The picture in one screenshot of the page."""
    shot = cv2.imread(shot_path)
    assert shot is not None, f"cannot read the screenshot {shot_path}"
    assert page["natural"] == list(SIZE), page  # the stream's pictures are the call's size
    return see_picture(_box(shot, page["picture"]), page)


def check_page(looks: list[dict[str, Any]], shared_clock: bool = True) -> list[Seen]:
    """Asserts what the module docstring says over ``looks`` (tests/browser.py's JSON:
    ``{"shot": PNG path, "page": figures}``, at least two, in order)."""
    assert len(looks) >= 2, looks
    seen = [see(look["shot"], look["page"]) for look in looks]
    for look, s in zip(looks, seen, strict=True):
        page = s.page
        assert s.face_ssim > MIN_FACE_SSIM, (s.face_ssim, s.clip_frame)
        assert s.landmark_px < MAX_LANDMARK_PX, (s.landmark_px, s.clip_frame)
        assert page["size"] == "640\u00d7480", page
        assert page["status"].startswith("session "), page
        assert number(page["fps"]) > 0, page
        kbps = {name: number(v) for name, v in page["kbps"].items()}
        assert kbps["geometry"] > 0 and kbps["total"] >= kbps["geometry"], page
        latency = number(page["latency"])
        if shared_clock:
            assert 0 < latency < 5000, page
        shot = cv2.imread(look["shot"])
        assert len(page["cells"]) == 6, page["cells"]  # each figure's element is there
        for cell, rect in page["cells"].items():
            ink = int((_box(shot, rect).max(axis=2) > 120).sum())
            assert ink > MIN_TEXT_PIXELS, f"figure {cell} is not written on the page ({ink})"
    for before, after in zip(seen, seen[1:], strict=False):
        change = np.abs(before.picture.astype(np.int16) - after.picture).mean()
        assert change > MIN_CHANGE, f"the picture did not change between screenshots ({change})"
        assert number(after.page["frames"]) > number(before.page["frames"]), (
            before.page,
            after.page,
        )
    return seen
