"""Parts of the camera's picture the model cannot show, sent as they are (Refresh packets).

The receiver's picture is the snapshot frame warped (models/surround.py) with the face drawn
over it. What that frame never showed (a hand raised to the chin, an object held up, the scene
a person uncovers, a light switched on) it cannot show. The sender rebuilds the receiver's
surroundings as it does for the face's edge (no drawing, on the frame reduced to about 120
pixels wide, every fourth frame: 0.13 s is soon enough, and the sender has 16 ms a frame in
all) and compares them with its frame in blocks, leaving out the drawn face. Where the warp
carries the surroundings with the head (hair, ears: above the mouth, within the head's reach)
something new is cut only while the head holds still, and given back as soon as the head
moves on: an area fixed in the frame there goes stale when the head moves (a lock of hair
shows where the head was). A hand held up there (sender/palms.py finds it) stays where it is
while the head moves: it is cut whatever the head does, first, and kept. Each pixel's
difference is the least over shifts of up to :data:`SLACK` pixels, so hair or a shoulder a
pixel or two off (which the warp leaves, and the edge's corrections mend) does not count; a
block whose mean difference stays above :data:`DIFF_LEVEL` for :data:`PERSIST_S` is the model's
failure, not a moment's. The largest group of such blocks, grown by a block (on no side where
that would take another refresh's place), is cut from the frame and sent as a WebP image of
that area; the receiver shows it over its surroundings (under the face) from then on, and the
sender compares against the picture with it. Where the model matches the frame again under a
refresh (the hand went down), the area is given back to the model with an empty one,
whatever the bucket holds; so is a refresh that no longer matches while the bucket cannot pay
for a new one (the head moved on: frozen, it showed a piece of the head where it was). The
images are paid from a token bucket of their own (:data:`REFRESH_KBPS`, with two seconds of
credit: the first one goes at once, the ones after wait for its debt).

What stands in front of the face (a hand: sender/occlusion.py finds it in the face's texture)
is cut with the blocks beside the face that fail next to it (its arm) and shown over the face
(``over``), kept while the area stays much the same and given back once the face is itself
again. Without such blocks nothing is sent there: a face changing more than its snapshot can
show (foreman's laugh) is no hand.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from facewire.models.refresh import RefreshLayer
from facewire.models.surround import SurroundWarp, carried_by_head
from facewire.protocol.images import decode_image
from facewire.protocol.packets import Refresh
from facewire.sender.occlusion import FaceOcclusion
from facewire.sender.palms import Hand, HeldPalms
from facewire.sender.rate_cap import RateCap

logger = logging.getLogger(__name__)

#: Payload budget of the refreshes, kbit/s: with the geometry's 1.5, the edge's 0.75, the body's
#: 0.25 and the REM patches' 3.7 at most, 7.7: a call within 8 kbit/s whatever happens.
REFRESH_KBPS = 1.5
#: Seconds of budget the bucket holds (and starts with).
BUCKET_S = 2.0
#: The comparison's frame is reduced by a whole factor to about this width, pixels.
WORK_WIDTH = 120
#: The comparison is made every this many frames.
EVERY = 4
#: Blocks of the comparison, work pixels on a side.
BLOCK = 8
#: Work pixels of misplacement forgiven: the difference is the least over these shifts.
SLACK = 2
#: A block is the model's failure where its mean luma difference is above this (0-255) ...
DIFF_LEVEL = 28.0
#: ... for this long, seconds ...
PERSIST_S = 0.25
#: ... in a group of at least this many blocks: a block or two failing is most often hair or
#: an ear a few pixels off as the head turns, and a refresh of it goes stale as it moves on.
MIN_BLOCKS = 4
#: Where the warp carries the surroundings with the head, a refresh is cut only while the
#: head has stayed within STILL of its width of where it is for STILL_S seconds.
STILL = 0.08
STILL_S = 0.25
#: A refresh whose failing blocks lie at least this share where the warp carries the
#: surroundings with the head goes when the head moves on.
HEAD_SHARE = 0.5
#: A hand held in place (sender/palms.py) within this many face widths of the face's centre
#: is one held up by it: its blocks may be cut whatever the head does.
HAND_REACH = 1.5
#: The palm detector looks at a square this many face widths wide around the face, where
#: smaller than the frame: a hand there is larger in its 192-pixel input (beside a 72-px face
#: in a 1280x720 frame, a 76-px hand was found only so).
HAND_LOOK = 4.0
#: What stands in front of the face is cut again when its area has moved so that it shares
#: less than this (intersection over union) with the one shown.
SAME_AREA = 0.6
_CHANNEL_MEAN = np.full((1, 3), 1.0 / 3.0, np.float32)
#: A refresh's image is at most this many pixels (scaled down if larger) ...
MAX_PIXELS = 64 * 64
#: ... at this WebP quality.
QUALITY = 60


#: A face's place in the work image: centre x, centre y and width, pixels.
Face = tuple[float, float, float]


@dataclass
class _Shown:
    """A refresh the receiver shows, and its area in work blocks."""

    packet: Refresh
    blocks: tuple[int, int, int, int]  # column, row, end column, end row
    #: Where the face was when it was cut, if it was cut mostly for what fails where the
    #: warp carries the surroundings with the head (it goes when the head moves on).
    head: Face | None


class RefreshMeter:
    """Finds what the receiver's picture misses, frame by frame, for one session.

    background : (h, w, 3) uint8, the snapshot frame as the receiver decoded it
    outline : (k, 3) the face's outline in it, as the receiver rebuilds the snapshot's values
    person : (h, w) float, the person mask the receiver makes of it (models.person)
    """

    def __init__(
        self,
        background: np.ndarray,
        outline: np.ndarray,
        person: np.ndarray,
        fps: float,
        kbps: float = REFRESH_KBPS,
        occlusion: FaceOcclusion | None = None,
        palms: HeldPalms | None = None,
    ) -> None:
        self.height, self.width = background.shape[:2]
        #: Finds what stands in front of the face, sent over it (None: not looked for).
        self.occlusion = occlusion
        #: Finds hands held up near the face (None: not looked for), and those it last found.
        self.palms = palms
        self._hands: list[Hand] = []
        self.reduce = k = max(1, self.width // WORK_WIDTH)
        shift = 0.5 / k - 0.5
        self._to_work = np.array([[1 / k, 0.0, shift], [0.0, 1 / k, shift], [0.0, 0.0, 1.0]])
        self._from_work = np.linalg.inv(self._to_work)
        work = self._reduced(background)
        self.size = (work.shape[1], work.shape[0])
        self.surround = SurroundWarp(
            work, self._work(outline), self._reduced(person.astype(np.float32))
        )
        self.cols, self.rows = self.size[0] // BLOCK, self.size[1] // BLOCK
        self._failing = np.zeros((self.rows, self.cols), np.int32)
        ys, xs = np.mgrid[: self.rows, : self.cols]
        self._block_centres = (np.c_[xs.ravel(), ys.ravel()] + 0.5) * BLOCK - 0.5  # work pixels
        self._persist = max(1, round(PERSIST_S * fps / EVERY))
        self._still = max(1, round(STILL_S * fps / EVERY))
        # Where the face was at the last measurements.
        self._faces: list[Face] = []
        self._frames = 0
        self.bucket = RateCap(kbps, fps, BUCKET_S)
        self.bucket.tokens = self.bucket.capacity
        #: What the receiver shows over its surroundings, as it shows it.
        self.layer = RefreshLayer(*self.size)
        self._shown: list[_Shown] = []
        #: Bytes of the refreshes sent.
        self.bytes = 0

    def set_budget(self, kbps: float) -> None:
        """Fill the bucket at ``kbps`` from now on (what the link leaves the pictures)."""
        self.bucket.set_rate(kbps)

    def _reduced(self, image: np.ndarray) -> np.ndarray:
        k = self.reduce
        if k == 1:
            return image
        h, w = image.shape[:2]
        whole = image[: h - h % k, : w - w % k]
        return cv2.resize(whole, (w // k, h // k), interpolation=cv2.INTER_AREA)

    def _work(self, points: np.ndarray) -> np.ndarray:
        out = np.array(points, dtype=np.float64)
        out[:, :2] = out[:, :2] @ self._to_work[:2, :2].T + self._to_work[:2, 2]
        if out.shape[1] > 2:
            out[:, 2] /= self.reduce
        return out

    def _in_work(self, homography: np.ndarray | None) -> np.ndarray | None:
        if homography is None or self.reduce == 1:
            return homography
        return self._to_work @ homography @ self._from_work

    def measure(
        self,
        seq: int,
        image: np.ndarray,
        outline: np.ndarray,
        camera: np.ndarray | None,
        body: np.ndarray | None,
        vertices: np.ndarray | None = None,
    ) -> list[Refresh]:
        """The refreshes of frame ``seq`` (``image``, (h, w, 3) BGR), where the receiver draws
        the face's outline at ``outline`` (k, 3) with the camera's and the body's homographies
        (models/surround.py); none while the bucket is in debt or nothing fails. ``vertices``:
        the face's (n, 3) as drawn, to look for what is in front of it."""
        can_send = self.bucket.next_frame()
        self._frames += 1
        if self.palms is not None and (self._frames - 1) % EVERY == EVERY // 2:
            # Half-way between two comparisons: no frame pays for both (4 ms and 6).
            self._hands = self.palms.update(image, self._hand_look())
        if (self._frames - 1) % EVERY:
            return []
        poly = self._work(outline)
        model = self.surround.warp(poly, self._in_work(camera), body=self._in_work(body))
        shown = self.layer.on_top(self.layer.over(model.copy(), poly[:, :2]))
        seen = self._reduced(image)
        failing = self._blocks(seen, shown) > DIFF_LEVEL
        face = self._face_blocks(poly)
        failing &= ~face
        self._failing = np.where(failing, self._failing + 1, 0)
        due = self._failing >= self._persist
        self._note_face(poly)
        if self.occlusion is not None and vertices is not None:
            held = len(self._faces) > 1 and not _moved(self._faces[-2], self._faces[-1])
            area = self.occlusion.update(image, vertices, held)
            packets = self._in_front(seq, image, area, failing, can_send)
            if packets:
                return self._spent(packets)
        carried, still = self._head_blocks(poly), self._held_still()
        hand = self._hand_blocks(poly)
        # A refresh cut where the head carries the surroundings (while it held still) goes
        # once the head has moved on from where it was: a lock of hair, fixed in the frame,
        # showed where the head had been for 20 frames (Claire), as hair over hair differs
        # too little to fail. A hand still held there fails again, and is cut again.
        stale = [s for s in self._shown if s.head is not None and _moved(s.head, self._faces[-1])]
        if stale:
            return self._spent([self._clear(seq, s) for s in stale])
        # Nothing new is cut where the warp carries the surroundings with a moving head, but
        # a refresh reaching in there that no longer matches is still given back or replaced.
        # What is shown over the face is the occlusion's to keep or give back.
        # A hand held up there stays where it is while the head moves: it may be cut.
        due &= (~carried | self._under_shown() | still | hand) & ~self._under_shown(over=True)
        if not due.any():
            return []
        tight, size = self._largest(due, hand)
        c0, r0, c1, r1 = self._grown(tight)
        group = due[r0:r1, c0:c1]
        head: Face | None = None
        if (
            carried[r0:r1, c0:c1][group].mean() >= HEAD_SHARE
            and not hand[r0:r1, c0:c1][group].any()
        ):
            head = self._faces[-1]  # it goes when the head moves on
        # Where the model alone matches the frame, a refresh there is only in the way; and one
        # that no longer matches and cannot be replaced now is older than the model's picture
        # (a head that moved on): either goes (a few bytes, whatever the bucket holds).
        model_fails = (self._blocks(seen, model) > DIFF_LEVEL) & ~face
        under = [
            s for s in self._shown if not s.packet.over and _overlap(s.blocks, (c0, r0, c1, r1))
        ]
        replace = can_send and size >= MIN_BLOCKS
        if under and not (replace and model_fails[r0:r1, c0:c1].any()):
            packets = [self._clear(seq, s) for s in under]
        elif replace and not (
            (head is not None and any(s.head is None for s in under))
            or any(s.packet.over and _overlap(s.blocks, (c0, r0, c1, r1)) for s in self._shown)
        ):
            # (One that goes with the head's stillness takes no other's place: on Claire
            # one of her jaw's, kept to the clip's end before, went with a lock of her hair.
            # Nor does one take the place of what is shown over the face.)
            packets = [self._cut(seq, image, (c0, r0, c1, r1), head)]
        else:
            return []
        self._failing[r0:r1, c0:c1] = 0
        return self._spent(packets)

    def _spent(self, packets: list[Refresh]) -> list[Refresh]:
        """``packets``, paid for."""
        for packet in packets:
            self.bucket.spend(len(bytes(packet)))
            self.bytes += len(bytes(packet))
        return packets

    def again(self, seq: int) -> list[Refresh]:
        """What the receiver should show from frame ``seq`` on, whatever it lost: the whole
        frame given back to the model, then every refresh shown now (sent when it asks for a
        keyframe; a lost refresh, or a lost empty one, is put right)."""
        everything = Refresh(seq, 0, 0, self.width, self.height, "", b"")
        # All of frame ``seq``: shown in this order whatever frame the receiver draws next.
        shown = [dataclasses.replace(s.packet, seq=seq) for s in self._shown]
        return [everything, *shown]

    def _blocks(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(rows, cols) mean absolute difference of two work images (BGR, its channels'
        mean), per block: at each pixel the larger of the least difference of ``a`` to ``b``
        shifted by up to SLACK pixels and of ``b`` to ``a`` shifted (one way only, a texture
        in the one shifted would find a near match for a flat colour in the other)."""
        fa, fb = cv2.blur(a, (3, 3)), cv2.blur(b, (3, 3))
        diff = cv2.max(_least(fa, fb), _least(fb, fa))
        diff = diff[: self.rows * BLOCK, : self.cols * BLOCK]
        return cv2.resize(diff, (self.cols, self.rows), interpolation=cv2.INTER_AREA)

    def _face_blocks(self, poly: np.ndarray) -> np.ndarray:
        """(rows, cols) bool: blocks whose centre the drawn face covers."""
        mask = np.zeros((self.rows, self.cols), np.uint8)
        scaled = (poly[:, :2] / BLOCK - 0.5).round().astype(np.int32)
        cv2.fillPoly(mask, [scaled], 1)
        return mask.astype(bool)

    def _hand_look(self) -> tuple[float, float, float] | None:
        """Where to look for hands (centre x, centre y, side, image pixels): HAND_LOOK face
        widths around the face at the last comparison (None before the first)."""
        if not self._faces:
            return None
        x, y, width = self._faces[-1]
        cx, cy = (self._from_work @ [x, y, 1.0])[:2]
        return float(cx), float(cy), HAND_LOOK * width * self.reduce

    def _hand_blocks(self, poly: np.ndarray) -> np.ndarray:
        """(rows, cols) bool: blocks of the hands held in place (sender/palms.py) within
        HAND_REACH face widths of the face (``poly``, its outline in work pixels), but not
        those whose palm is on the face (the detector takes some faces for palms; a hand in
        front of the face is sender/occlusion.py's)."""
        hand = np.zeros((self.rows, self.cols), bool)
        xy = poly[:, :2]
        centre, width = xy.mean(0), float(np.ptp(xy[:, 0]))
        outline = xy.astype(np.float32).reshape(-1, 1, 2)
        for found in self._hands:
            palm = self._work(found.centre[None])[0]
            if cv2.pointPolygonTest(outline, (float(palm[0]), float(palm[1])), False) >= 0:
                continue
            corners = self._work(found.box.reshape(2, 2))
            if np.hypot(*(corners.mean(0) - centre)) > HAND_REACH * width:
                continue
            c0, r0 = np.floor(corners[0] / BLOCK).astype(int).clip(0)
            c1, r1 = np.ceil(corners[1] / BLOCK).astype(int).clip(0)
            hand[r0:r1, c0:c1] = True
        return hand

    def _head_blocks(self, poly: np.ndarray) -> np.ndarray:
        """(rows, cols) bool: blocks whose centre the warp carries with the head (hair, ears:
        models/surround.py). A refresh there, fixed in the frame, is stale as soon as the head
        moves on: a turn showed a lock of hair the snapshot lacked, and each refresh of it
        showed that lock where the head had been within a second, then went; resent at every
        turn, it took a clip's whole budget."""
        return carried_by_head(self._block_centres, poly).reshape(self.rows, self.cols)

    def _note_face(self, poly: np.ndarray) -> None:
        """Keep where the face is at this measurement (``poly``, its outline in work pixels),
        and at the ones STILL_S before."""
        xy = poly[:, :2]
        centre = xy.mean(0)
        self._faces.append((float(centre[0]), float(centre[1]), float(np.ptp(xy[:, 0]))))
        del self._faces[: -(self._still + 1)]

    def _held_still(self) -> bool:
        """Whether the head has stayed within STILL of its width of where it is for STILL_S
        (a hand raised beside it, held: a refresh fixed in the frame stays right while the
        head stays where it is)."""
        if len(self._faces) <= self._still:
            return False
        return not any(_moved(self._faces[-1], face) for face in self._faces[:-1])

    def _under_shown(self, over: bool = False) -> np.ndarray:
        """(rows, cols) bool: blocks that a refresh shown now covers (``over``: one shown
        over the face, else one under it)."""
        under = np.zeros((self.rows, self.cols), bool)
        for shown in self._shown:
            if bool(shown.packet.over) == over:
                c0, r0, c1, r1 = shown.blocks
                under[r0:r1, c0:c1] = True
        return under

    def _in_front(
        self,
        seq: int,
        image: np.ndarray,
        area: tuple[int, int, int, int] | None,
        failing: np.ndarray,
        can_send: bool,
    ) -> list[Refresh]:
        """What to send of ``area`` (x, y, width, height: what stands in front of the face,
        or None): it cut and shown over the face, unless one shown there covers it much the
        same; or the one shown given back once nothing is in front of the face. The area
        takes in the ``failing`` blocks beside the face that reach it (the rest of a hand)."""
        shown = next((s for s in self._shown if s.packet.over), None)
        if area is None:
            return [] if shown is None else [self._clear(seq, shown)]
        k = BLOCK * self.reduce
        x, y, w, h = area
        c0, r0 = x // k, y // k
        c1, r1 = min(self.cols, -(-(x + w) // k)), min(self.rows, -(-(y + h) // k))
        if c1 <= c0 or r1 <= r0:
            return []
        _, labels = cv2.connectedComponents(failing.astype(np.uint8), connectivity=8)
        reaching = set(np.unique(labels[max(0, r0 - 1) : r1 + 1, max(0, c0 - 1) : c1 + 1]))
        reaching.discard(0)
        if not reaching and shown is None:
            # Nothing beside the face fails with it: no hand, whose arm would, but the face
            # changing more than the snapshot can show (foreman's laugh).
            return []
        for label in reaching:
            rows, cols = np.nonzero(labels == label)
            c0, r0 = min(c0, int(cols.min())), min(r0, int(rows.min()))
            c1, r1 = max(c1, int(cols.max()) + 1), max(r1, int(rows.max()) + 1)
        blocks = (c0, r0, c1, r1)
        if shown is not None and _iou(shown.blocks, blocks) >= SAME_AREA:
            return []
        if not can_send:
            return []
        return [self._cut(seq, image, blocks, None, over=True)]

    def _largest(self, due: np.ndarray, hand: np.ndarray) -> tuple[tuple[int, int, int, int], int]:
        """Blocks (column, row, end column, end row) around the largest group of ``due``
        blocks, of those with a held hand's blocks if any, and how many blocks it has."""
        _, labels, stats, _ = cv2.connectedComponentsWithStats(due.astype(np.uint8), connectivity=8)
        best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if (due & hand).any():
            touching = np.unique(labels[due & hand])
            best = int(touching[np.argmax(stats[touching, cv2.CC_STAT_AREA])])
        x, y, w, h, size = (int(v) for v in stats[best, :5])
        return (x, y, x + w, y + h), size

    def _grown(self, box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        """``box`` grown by a block on each side (an object's edge blocks fail less than its
        middle), but on no side where that would take another refresh's place: a flag by
        carphone's cheek never showed, its box grown into a refresh of his car's window."""
        others = [
            s.blocks for s in self._shown if not s.packet.over and not _overlap(s.blocks, box)
        ]
        for side in ((-1, 0, 0, 0), (0, -1, 0, 0), (0, 0, 1, 0), (0, 0, 0, 1)):
            c0, r0, c1, r1 = (a + b for a, b in zip(box, side, strict=True))
            wider = (max(0, c0), max(0, r0), min(self.cols, c1), min(self.rows, r1))
            if not any(_overlap(o, wider) for o in others):
                box = wider
        return box

    def _area(self, blocks: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        """Frame pixels (x, y, width, height) of work blocks."""
        c0, r0, c1, r1 = blocks
        k = BLOCK * self.reduce
        x, y = c0 * k, r0 * k
        return x, y, min(self.width, c1 * k) - x, min(self.height, r1 * k) - y

    def _cut(
        self,
        seq: int,
        image: np.ndarray,
        blocks: tuple[int, int, int, int],
        head: Face | None,
        over: bool = False,
    ) -> Refresh:
        x, y, w, h = self._area(blocks)
        part = image[y : y + h, x : x + w]
        scale = min(1.0, float(np.sqrt(MAX_PIXELS / (w * h))))
        if scale < 1.0:
            size = (max(1, round(w * scale)), max(1, round(h * scale)))
            part = cv2.resize(part, size, interpolation=cv2.INTER_AREA)
        ok, data = cv2.imencode(".webp", part, [cv2.IMWRITE_WEBP_QUALITY, QUALITY])
        if not ok:
            raise RuntimeError("WebP encoding failed")
        packet = Refresh(seq, x, y, w, h, "webp", data.tobytes(), int(over))
        self._shown = [s for s in self._shown if not _overlap(s.blocks, blocks)]
        self._shown.append(_Shown(packet, blocks, head))
        self._show(packet)
        logger.debug("refresh at frame %d: %dx%d px, %d bytes", seq, w, h, len(packet.data))
        return packet

    def _clear(self, seq: int, shown: _Shown) -> Refresh:
        old = shown.packet
        packet = Refresh(seq, old.x, old.y, old.width, old.height, "", b"")
        self._shown.remove(shown)
        self._show(packet)
        return packet

    def _show(self, packet: Refresh) -> None:
        """Keep the work-size picture of what the receiver shows up to date."""
        k = self.reduce
        x0, y0 = packet.x // k, packet.y // k
        x1 = min(self.size[0], -(-(packet.x + packet.width) // k))
        y1 = min(self.size[1], -(-(packet.y + packet.height) // k))
        if x1 <= x0 or y1 <= y0:
            return
        image = None if packet.clears else decode_image(packet.data, "refresh")  # as received
        self.layer.add(packet.seq, x0, y0, x1 - x0, y1 - y0, image, bool(packet.over))
        self.layer.due(packet.seq)


def _least(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(h, w) float32: at each pixel of ``a`` (h, w, 3) uint8 the least mean absolute
    difference over its channels to ``b`` shifted by up to SLACK pixels either way."""
    s = SLACK
    padded = cv2.copyMakeBorder(b, s, s, s, s, cv2.BORDER_REPLICATE)
    h, w = a.shape[:2]
    least = None
    for dy in (-s, 0, s):
        for dx in (-s, 0, s):
            moved = np.ascontiguousarray(padded[s + dy : s + dy + h, s + dx : s + dx + w])
            diff = cv2.transform(cv2.absdiff(a, moved), _CHANNEL_MEAN)
            least = diff if least is None else cv2.min(least, diff)
    assert least is not None
    return least


def _moved(a: Face, b: Face) -> bool:
    """Whether the face moved or changed its width by more than STILL of its width."""
    reach = STILL * max(a[2], b[2])
    return bool(np.hypot(a[0] - b[0], a[1] - b[1]) > reach or abs(a[2] - b[2]) > reach)


def _iou(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> float:
    """Intersection over union of two block boxes (column, row, end column, end row)."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    both = max(0, w) * max(0, h)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - both
    return both / union if union else 1.0


def _overlap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]
