"""REM patches, receiver side: live eyes and mouth pasted into the face's texture (seed 003).

A patch is decoded (its header first: it must be exactly its region's box on the session's
patch grid, so a patch far larger than its region is refused before a pixel is decoded),
then kept until the frame it belongs to is drawn. Drawing that frame (:meth:`RemMerger.due`)
applies it, in frame order:

1. when it brings another reference colour, the whole snapshot texture is moved to it with
   Eq. 2 (seed 003 section 2.3: hue shifted to the video's peak, saturation and value scaled
   by the ratio of the means), from the snapshot's own reference colour. Moving only the
   regions and a band around them was tried: through the call it scored face SSIM 0.004
   lower on carphone and 0.001 higher on akiyo and mother-daughter (BENCHMARKS.md "REM
   patches");
2. every region's latest patch, scaled up to the texture, is blended over that with its box's
   feathered weight, so no seam shows at the region's edge.

A region keeps its last patch until another comes (an unchanged region is not sent again);
one never sent shows the snapshot's texture. The last REM_CACHE images of each region are
kept, so a patch may name one of them (or the snapshot's texture) instead of carrying an
image: an eye open again after a blink costs a reference. Whatever is wrong with a patch (no
such region, older than the snapshot, corrupt image, wrong size, a reference to an image
this end does not hold, no REM in the session) is counted in :attr:`RemMerger.dropped` by
reason and dropped; nothing raises.
"""

from __future__ import annotations

import logging
from collections import Counter

import cv2
import numpy as np

from facewire.models.colour import ColourStats, adapt, reference_colour, to_hsv
from facewire.models.rem import EYES, RemLayout
from facewire.protocol.constants import REM_CACHE
from facewire.protocol.images import ImageError, decode_image
from facewire.protocol.packets import RemPatch

logger = logging.getLogger(__name__)

#: Patches waiting for their frame, at most (a hostile sender's far-future patches must not
#: pile up). Over it, the oldest that a newer one of its region would replace anyway goes
#: first (a receiver that drew nothing for a second, its mouth's inside coming as references
#: every few frames, lost nothing then), else the oldest.
MAX_PENDING = 16


#: A texel of a patch replaces the texture's where their luma differs by more than
#: GATE_LOW (fully from GATE_HIGH): where they agree, the snapshot's clean texel stays (a
#: patch coded in 100 bytes is blocky on smooth skin, which SSIM sees).
GATE_LOW, GATE_HIGH = 6.0, 18.0


def _gate(patch: np.ndarray, under: np.ndarray) -> np.ndarray:
    """(h, w) float32 in [0, 1]: where ``patch`` brings something the texture lacks."""
    weights = np.array([0.114, 0.587, 0.299], np.float32)
    d = np.abs((patch.astype(np.float32) - under) @ weights)
    d = cv2.GaussianBlur(d, (5, 5), 0)
    gate = np.clip((d - GATE_LOW) / (GATE_HIGH - GATE_LOW), 0.0, 1.0)
    return np.asarray(cv2.GaussianBlur(gate, (5, 5), 0), np.float32)


class RemMerger:
    """One session's REM patches merged into its texture.

    layout : the session's REM layout (the sender's, rebuilt from the snapshot)
    texture : (T, T, 3) uint8 BGR, the snapshot's texture (T = layout.size)
    first_seq : the snapshot's frame number: patches of earlier frames are stale
    adapt_colour : apply Eq. 2 (off: patches are pasted as they come, for measuring)
    """

    def __init__(
        self, layout: RemLayout, texture: np.ndarray, first_seq: int, adapt_colour: bool = True
    ) -> None:
        if texture.shape != (layout.size, layout.size, 3) or texture.dtype != np.uint8:
            raise ValueError(
                f"expected a ({layout.size}, {layout.size}, 3) uint8 texture, "
                f"got {texture.shape} {texture.dtype}"
            )
        self.layout = layout
        self.first_seq = first_seq
        self.adapt_colour = adapt_colour
        self._take_base(texture)
        #: The video's reference colour the texture is adapted to (None: not adapted).
        self.colour: ColourStats | None = None
        self._adapted = self.base
        #: The texture as drawn: adapted, with the patches in.
        self.texture = texture.copy()
        self._patches: dict[str, np.ndarray] = {}  # region -> (box at texture size) uint8
        # region -> frame number -> image (patch grid), oldest first: what a reference names
        self._held: dict[str, dict[int, np.ndarray]] = {n: {} for n in layout.names}
        self._pending: list[tuple[int, int, str, np.ndarray | None, ColourStats | None]] = []
        self._order = 0
        self.received = 0
        self.applied: Counter[str] = Counter()
        self.replaced = 0  # waiting, and left out for a newer one of their region
        self.dropped: Counter[str] = Counter()

    def _take_base(self, texture: np.ndarray) -> None:
        self.base = texture.copy()
        self._base_hsv = to_hsv(texture)
        layout = self.layout
        eyes = [n for n in layout.names if n in EYES] or list(layout.names)
        pixels = np.concatenate(
            [
                self._base_hsv[layout.boxes[n].texture_slices][layout.boxes[n].texture_inside]
                for n in eyes
            ]
        )
        #: The snapshot texture's reference colour (None: no skin in its regions to measure).
        self.model_colour = reference_colour(pixels[:, None, :])

    def rebase(self, texture: np.ndarray) -> None:
        """A sharper snapshot texture of the same size (the full snapshot after its draft):
        the patches held and shown stay, the colour adaptation is made again on it."""
        if texture.shape != self.base.shape or texture.dtype != np.uint8:
            raise ValueError(f"expected a {self.base.shape} uint8 texture, got {texture.shape}")
        self._take_base(texture)
        self._adapted = self.base
        if self.colour is not None and self.adapt_colour and self.model_colour is not None:
            self._adapted = adapt(self._base_hsv, self.model_colour, self.colour)
        self._compose()

    def add(self, packet: RemPatch) -> bool:
        """Take a patch for later (:meth:`due`); False, counted in :attr:`dropped`, if it
        cannot be used."""
        self.received += 1
        box = self.layout.boxes.get(packet.region)
        if box is None:
            return self._drop("unknown region", f"no REM region {packet.region!r}")
        if packet.seq < self.first_seq:
            return self._drop(
                "before the snapshot", f"frame {packet.seq} is older than the snapshot"
            )
        held = self._held[packet.region]
        image: np.ndarray | None
        key = packet.reference
        if key is not None:
            if key == self.first_seq:
                image = None  # the snapshot's texture
            elif key in held:
                image = held[key]
            else:
                return self._drop(
                    "unknown reference", f"{packet.region}: no image of frame {key} held"
                )
        else:
            try:
                image = decode_image(
                    packet.data,
                    f"REM patch {packet.region}",
                    expected_size=(box.width, box.height),
                )
            except ImageError as exc:
                return self._drop("bad image", str(exc))
            held[packet.seq] = image
            for old in list(held)[:-REM_CACHE]:
                del held[old]
        colour = None
        if packet.s_mean > 0 and packet.v_mean > 0:  # zeros: the sender measured none
            colour = ColourStats(packet.h_peak, packet.s_mean, packet.v_mean)
        if len(self._pending) >= MAX_PENDING:
            self._pending.sort()
            regions = [p[2] for p in self._pending]
            replaced = next((i for i, name in enumerate(regions) if name in regions[i + 1 :]), None)
            if replaced is None:
                self._pending.pop(0)
                self.dropped["overrun"] += 1
            else:
                self._pending.pop(replaced)
                self.replaced += 1
        self._order += 1
        self._pending.append((packet.seq, self._order, packet.region, image, colour))
        return True

    def _drop(self, reason: str, detail: str) -> bool:
        logger.debug("dropped REM patch: %s", detail)
        self.dropped[reason] += 1
        return False

    def due(self, seq: int) -> bool:
        """Apply the patches of frames up to ``seq`` (the frame about to be drawn); True if
        :attr:`texture` changed."""
        ready = sorted(p for p in self._pending if p[0] <= seq)
        if not ready:
            return False
        self._pending = [p for p in self._pending if p[0] > seq]
        colour = self.colour
        for _, _, name, image, patch_colour in ready:
            box = self.layout.boxes[name]
            rows, cols = box.texture_slices
            size = (cols.stop - cols.start, rows.stop - rows.start)
            if image is None:
                self._patches.pop(name, None)  # back to the snapshot's texture
            elif box.scale > 1:
                self._patches[name] = cv2.resize(image, size, interpolation=cv2.INTER_LINEAR)
            else:
                self._patches[name] = image
            if patch_colour is not None:
                colour = patch_colour
            self.applied[name] += 1
        if colour != self.colour and self.adapt_colour and self.model_colour is not None:
            assert colour is not None
            self._adapted = adapt(self._base_hsv, self.model_colour, colour)
            self.colour = colour
        self._compose()
        return True

    def _compose(self) -> None:
        texture = self._adapted.copy()
        for name, image in self._patches.items():
            box = self.layout.boxes[name]
            rows, cols = box.texture_slices
            under = texture[rows, cols].astype(np.float32)
            a = box.texture_alpha * _gate(image, under)
            a = a[:, :, None]
            texture[rows, cols] = np.clip(a * image + (1.0 - a) * under + 0.5, 0, 255).astype(
                np.uint8
            )
        self.texture = texture

    def counts(self) -> dict[str, object]:
        """Patches received, applied (by region), replaced while waiting by a newer one of
        their region, waiting for their frame to be drawn (at the call's end: arrived after
        its last picture) and dropped (by reason)."""
        return {
            "received": self.received,
            "applied": dict(self.applied),
            "replaced": self.replaced,
            "waiting": len(self._pending),
            "dropped": dict(self.dropped),
        }
