"""MediaPipe's networks as LiteRT runs them (models/network.py)."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest

from facewire.models.network import Network, rgb_input
from facewire.sender.detector import model_path
from facewire.sender.eyes import OUTPUT_LAYER


def test_the_eye_model_takes_its_own_size_and_names_its_outputs() -> None:
    net = Network(model_path("iris_landmark.tflite"))
    assert net.input_size == (64, 64)
    assert OUTPUT_LAYER in net.output_names
    with pytest.raises(ValueError, match=r"expected a \(64, 64, 3\) image, got \(32, 64, 3\)"):
        net.run(np.zeros((32, 64, 3), np.float32))


def test_a_missing_file_is_named() -> None:
    with pytest.raises(FileNotFoundError, match="no_such.tflite does not exist"):
        Network("no_such.tflite")


def test_rgb_input_swaps_the_channels_and_scales() -> None:
    bgr = np.array([[[0, 128, 255]]], np.uint8)
    np.testing.assert_allclose(rgb_input(bgr, 1 / 255.0), [[[1.0, 128 / 255.0, 0.0]]], rtol=1e-6)
    assert rgb_input(bgr, 1 / 127.5, -1.0)[0, 0, 0] == pytest.approx(1.0)


def test_threads_sharing_a_network_get_what_each_would_alone() -> None:
    net = Network(model_path("iris_landmark.tflite"))
    rng = np.random.default_rng(3)
    images = [rng.random((64, 64, 3), dtype=np.float32) for _ in range(2)]
    alone = [net.run(image)[OUTPUT_LAYER] for image in images]
    got: dict[int, list[np.ndarray]] = {0: [], 1: []}

    def work(which: int) -> None:
        for _ in range(30):
            got[which].append(net.run(images[which])[OUTPUT_LAYER])

    threads = [threading.Thread(target=work, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for which in (0, 1):
        assert len(got[which]) == 30
        assert all(np.array_equal(out, alone[which]) for out in got[which])


def test_readying_the_networks_writes_nothing_on_stderr() -> None:
    # LiteRT announces its XNNPACK delegate on stderr; a user's terminal should not see it.
    code = (
        "from facewire.sender.landmarks import LandmarkTracker\n"
        "from facewire.models.person import person_mask\n"
        "import numpy as np\n"
        "LandmarkTracker(); person_mask(np.zeros((144, 176, 3), np.uint8))\n"
        "import sys; print('still writes', file=sys.stderr)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr == "still writes\n"
