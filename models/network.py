"""MediaPipe's TFLite networks, run by LiteRT (TensorFlow Lite's own runtime, ``ai-edge-litert``).

The sender runs three every frame or on a loss (face detection, the 468 landmarks, the eye
model) and both ends run one on each snapshot (the person's segmentation). LiteRT's XNNPACK
kernels run them about twice as fast as OpenCV's DNN module, which ran them before: on one core
the eye model takes 1.5 ms an eye against 3.4, the landmarks 1.6 ms against 2.9
(benchmarks/bench_tracker.py, docs/what-we-tried.md).

Each network runs on one thread: both ends of a call share the machine's cores, and a second
thread of ours would only take time from the other end.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

THREADS = 1

# LiteRT writes one "INFO: Created TensorFlow Lite XNNPACK delegate" line on stderr when the
# process's first network is readied, and has no setting to turn it off.
_quiet_lock = threading.Lock()
_readied_once = False


def _allocate_quietly(interpreter: object) -> None:
    global _readied_once
    with _quiet_lock:
        if _readied_once:
            interpreter.allocate_tensors()  # type: ignore[attr-defined]
            return
        saved = os.dup(2)
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 2)
                interpreter.allocate_tensors()  # type: ignore[attr-defined]
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        _readied_once = True


class Network:
    """One TFLite network with one NHWC float input and named outputs.

    ``run`` is safe to call from several threads (the scene's start runs beside the call's
    loop); it takes them one at a time.
    """

    def __init__(self, path: str | Path) -> None:
        from ai_edge_litert.interpreter import Interpreter

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"network file {self.path} does not exist")
        self._interpreter = Interpreter(model_path=str(self.path), num_threads=THREADS)
        _allocate_quietly(self._interpreter)
        (source,) = self._interpreter.get_input_details()
        self._input = source["index"]
        self.input_shape = tuple(int(n) for n in source["shape"])
        self._outputs = {d["name"]: d["index"] for d in self._interpreter.get_output_details()}
        self._lock = threading.Lock()

    @property
    def input_size(self) -> tuple[int, int]:
        """(width, height) of the image the network takes."""
        return self.input_shape[2], self.input_shape[1]

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(self._outputs)

    def run(self, image: np.ndarray) -> dict[str, np.ndarray]:
        """Outputs by name for ``image``: (height, width, 3) float32 RGB, scaled as the
        network expects."""
        if image.shape != self.input_shape[1:]:
            raise ValueError(f"expected a {self.input_shape[1:]} image, got {image.shape}")
        with self._lock:
            self._interpreter.set_tensor(
                self._input, np.ascontiguousarray(image, dtype=np.float32)[None]
            )
            self._interpreter.invoke()
            # get_tensor copies: what is returned stays as it is through the next invoke.
            return {name: self._interpreter.get_tensor(i) for name, i in self._outputs.items()}


def rgb_input(image_bgr: np.ndarray, scale: float, offset: float = 0.0) -> np.ndarray:
    """A uint8 BGR image as a network's float32 RGB input: ``value * scale + offset``."""
    rgb = image_bgr[..., ::-1].astype(np.float32)
    rgb *= np.float32(scale)
    if offset:
        rgb += np.float32(offset)
    return rgb
