"""``facewire track --tracker markers`` and ``facewire demo --tracker markers`` end to end:
the command line, the JSON, a real loopback call (two processes, ZeroMQ, EGL), and a face
without markers said in one line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
from marker_clip import clip_frames, truth

from facewire.cli import main
from facewire.sender.capture import demo_clip_path
from facewire.sender.markers import MarkerTracker

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"
T = truth()


def _facewire(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYOPENGL_PLATFORM="egl")
    return subprocess.run(
        [sys.executable, "-m", "facewire", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _video_of_the_photo(path: Path, frames: int = 8) -> Path:
    """A short video of the astronaut photo (a face without markers)."""
    photo = cv2.imread(str(FIXTURE))
    frame = cv2.copyMakeBorder(photo, 30, 30, 110, 110, cv2.BORDER_REPLICATE)
    h, w = frame.shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 30, (w, h))
    for _ in range(frames):
        writer.write(frame)
    writer.release()
    return path


def test_track_markers_writes_every_marker(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "markers.json"
    draw = tmp_path / "markers.mp4"
    rc = main(
        [
            "track", "--tracker", "markers", "--input", str(demo_clip_path()),
            "--json", str(out), "--draw", str(draw), "--frames", "40",
        ]
    )  # fmt: skip
    assert rc == 0
    assert capsys.readouterr().out.strip() == (
        f"track: 40 frames, 40 with markers (1 acquired, 39 tracked); wrote {out}"
    )
    doc = json.loads(out.read_text())
    assert doc["tracker"] == "markers" and doc["smoothed"] is False
    assert [f["state"] for f in doc["frames"]] == ["acquired"] + ["tracked"] * 39
    names = [str(n) for n in T["marker_names"]]
    # The file says what the tracker says, frame by frame.
    tracker = MarkerTracker()
    for (index, image), record in zip(clip_frames(40), doc["frames"], strict=True):
        found = tracker.track(image)
        assert found is not None and record["index"] == index
        conf = [m["confidence"] for m in record["markers"]]
        np.testing.assert_allclose(conf, found.confidence, atol=1e-3)
        assert [m["status"] for m in record["markers"]] == list(found.status)
        assert [m["role"] for m in record["markers"]] == list(found.roles)
        np.testing.assert_allclose(record["pose"]["rotation"], found.pose.rotation, atol=1e-5)
    for record in doc["frames"]:
        markers = record["markers"]
        assert [m["name"] for m in markers] == names
        xy = np.array([[m["x"], m["y"]] for m in markers])
        visible = T["marker_visible"][record["index"]]
        err = np.linalg.norm(xy - T["marker_xy"][record["index"]], axis=1)[visible]
        assert err.max() < 1.5
        assert all(m["status"] == "seen" and m["confidence"] > 0.5 for m in markers)
        assert record["pose"]["scale"] > 10  # px per cm: a face ~200 px wide
    cap = cv2.VideoCapture(str(draw))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 40
    cap.release()


def test_track_markers_on_a_face_without_them(tmp_path: Path) -> None:
    video = _video_of_the_photo(tmp_path / "photo.mp4", frames=3)
    out = tmp_path / "none.json"
    r = _facewire(
        "track", "--tracker", "markers", "--input", str(video), "--json", str(out), cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"track: 3 frames, 0 with markers (3 no_markers); wrote {out}"
    doc = json.loads(out.read_text())
    assert all(f["markers"] == [] and f["pose"] is None for f in doc["frames"])


def test_demo_with_markers(tmp_path: Path) -> None:
    """A loopback call driven by the markers: every frame tracked and rebuilt."""
    stats = tmp_path / "stats.json"
    r = _facewire(
        "demo", "--tracker", "markers", "--frames", "30", "--every-frame",
        "--output", str(tmp_path / "out.mp4"), "--compare", str(tmp_path / "cmp.mp4"),
        "--stats", str(stats),
        cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    got = json.loads(stats.read_text())
    assert got["frames_in"] + got["frames_dropped"] == got["frames_out"] == 30
    assert got["frames_untracked"] == 0
    assert got["kbps"]["geometry"] > 0
    cap = cv2.VideoCapture(str(tmp_path / "out.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 30
    cap.release()


def test_demo_with_markers_on_a_face_without_them(tmp_path: Path) -> None:
    video = _video_of_the_photo(tmp_path / "photo.mp4")
    # Every frame: the search's count is the clip's, however busy the machine.
    r = _facewire(
        "demo", "--tracker", "markers", "--every-frame", "--input", str(video), cwd=tmp_path
    )
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"facewire: error: a face but no markers on it in the first 8 frames of {video} "
        "(--tracker markers: see the README for where they go)"
    )
