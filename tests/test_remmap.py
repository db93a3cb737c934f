"""``facewire rem-map``: the REM analysis as a command, on the bundled clip."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.cli import main
from facewire.models.rem import REGION_NAMES
from facewire.remmap import GRID, MAP_SCALE
from facewire.sender.capture import demo_clip_path


def test_rem_map_writes_the_map_and_the_figures(tmp_path: Path, capsys) -> None:
    out, figures = tmp_path / "map.png", tmp_path / "map.json"
    args = ["rem-map", "--input", str(demo_clip_path()), "--output", str(out)]
    assert main([*args, "--json", str(figures), "--frames", "40"]) == 0
    image = cv2.imread(str(out))
    assert image.shape == (GRID * MAP_SCALE, 3 * GRID * MAP_SCALE, 3)
    result = json.loads(figures.read_text())
    assert result["frames"] == 40
    assert set(result["regions"]) == set(REGION_NAMES)
    for name, fig in result["regions"].items():
        assert fig["texels"] > 0, name
        for key in ("flow_px", "shape_change_px", "texture_change_px", "texture_over_shape"):
            assert np.isfinite(fig[key]) and fig[key] >= 0, (name, key)
        assert isinstance(fig["rem"], bool)
    printed = capsys.readouterr().out
    assert "eye_right: texture change" in printed and f"wrote {out}" in printed
    # The clip's first 40 frames: still, then turning, one smile coming. The face moves its
    # mouth (the wires' shape change) more than it moves around the eyes.
    regions = result["regions"]
    assert regions["mouth"]["shape_change_px"] > regions["eye_right"]["shape_change_px"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--input", "/nonexistent.mp4"], "facewire: error: "),
        (["--input", str(demo_clip_path()), "--frames", "1"], "--frames must be at least 2"),
    ],
)
def test_bad_input_ends_in_one_line(tmp_path: Path, capsys, args: list[str], message: str) -> None:
    code = main(["rem-map", *args, "--output", str(tmp_path / "m.png")])
    err = capsys.readouterr().err
    assert code == 1
    assert message in err and len(err.strip().splitlines()) == 1
