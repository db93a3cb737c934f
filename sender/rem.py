"""REM patches, sender side: live texture for the eyes and the mouth's inside (seed 003).

Each frame, every region of the session's :class:`~facewire.models.rem.RemLayout` is cut from the
frame and warped into texture space through the mesh *as the receiver rebuilds it* (the
quantised parameters of this frame): pasted into the texture and drawn with the same mesh, a
patch puts back the pixels it came from, whatever error the geometry has there.

A region is sent when it changed against what the receiver shows for it: enough of its
texels moved by more than :data:`CHANGE_LEVEL` of luma (a blink, a glance, the mouth
opening; :meth:`RemEncoder.change`). The mouth's inside counts only while the mouth is open.
What it shows now may be an image the receiver already holds: each end keeps the last
REM_CACHE images of every region and the snapshot's (an eye open again after a blink looks
as it did before it), and then a 17-byte reference to it goes instead of an image. An image
is coded as WebP at the best quality of :data:`QUALITIES` that fits its share of the bucket
(a 30-200 byte patch is mostly header as a JPEG; docs/what-we-tried.md, "REM patches: how
to code one").

The eyes are paid from a token bucket filled at :data:`BUDGET_KBPS`, the one that has waited
longest first, and the mouth's inside from one of its own filled at
:data:`MOUTH_BUDGET_KBPS`: a talking mouth changes all the time, and behind the eyes it
waited while the mouth stayed open (a blink lasts a few frames). Every patch carries the
reference skin colour (peak hue, mean saturation and value over the eye regions: seed 003
section 2.3), which the receiver adapts the whole texture to (Eq. 2). It is measured every
frame and followed over :data:`COLOUR_TIME_S`: one frame's, over the few dozen skin texels
of two eye regions, moves by 5-10% with every blink and glance, and each patch then made the
whole face brighter or darker.

Keyframes repeat what a lost patch would have brought: a keyframe a receiver asked for (it
just joined, or lost packets) repeats every region's image, one of the snapshot's as a
reference; a periodic keyframe repeats the regions sent since the previous keyframe, as an
image while it has gone out only once, else as a reference.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.sparse as sp

from facewire.models.colour import ColourStats, reference_colour, to_hsv
from facewire.models.rem import EYES, MOUTH_INTERIOR, SENT_REGIONS, RemLayout
from facewire.protocol.constants import REM_CACHE
from facewire.protocol.packets import RemPatch
from facewire.sender.texture import UvRasteriser

logger = logging.getLogger(__name__)

#: All REM traffic, payload, on average (DESIGN.md: at most 4 kbit/s); kept under it by what a
#: blink may borrow (BLINK_DEBT_S) and the repeats keyframes owe. 3.0 since RemPatch is
#: binary (13 bytes of header, not 35-41): the same patches as 3.7 bought before, about
#: (eyes SSIM over five real clips within 0.003 of before or better, but for carphone's, which
#: moves by 0.015 from one budget to the next either way; docs/what-we-tried.md).
BUDGET_KBPS = 3.0
#: The mouth's inside has a bucket of its own, filled at this (payload, on average), beside
#: the eyes' BUDGET_KBPS: sharing theirs, it waited behind them for as long as the mouth stayed
#: open, and the open mouth showed the snapshot's shut lips stretched (a dark blob, no
#: teeth). Images it sent once come back as references (REM_CACHE of them), so a talking
#: mouth soon costs a few bytes a change.
MOUTH_BUDGET_KBPS = 1.2
#: The mouth's bucket holds this many seconds of its budget: a large face's inside (a few
#: hundred bytes) must fit.
MOUTH_BUCKET_S = 5.0
#: Most the bucket holds, in seconds of budget.
BUCKET_S = 2.5
#: Seconds of budget in the bucket when the session starts.
START_S = 0.0
#: WebP qualities tried, best first; a patch gets the best that fits its share of the bucket.
QUALITIES = (70, 50, 35, 20, 10)
#: A texel has changed when its luma moved by more than this (0-255) ...
CHANGE_LEVEL = 24.0
#: ... and a region has when this fraction of its (weighted) texels did.
CHANGE_FRACTION = 0.06
#: An image the receiver holds stands for the region when it differs on at most this
#: fraction of the texels.
SAME_FRACTION = CHANGE_FRACTION / 2
#: Seconds of budget a blink may borrow when the bucket cannot pay for both eyes ...
BLINK_DEBT_S = 0.5
#: ... as far as the call's REM traffic since it began stays under this average, kbit/s
#: (DESIGN.md's limit on all REM traffic): over a short call a loan not yet paid back
#: would show.
LIMIT_KBPS = 4.0
#: Frames an eye is taken to have waited already: ahead of a mouth that waited less longer.
EYE_HEAD_START = 15
#: An eye that changed on this fraction of its texels, with the other eye changed too (a
#: blink, a glance), may spend the bytes kept for the eyes; a smaller change, or one eye's
#: alone (the head turning the light on it), may not.
BIG_CHANGE = 0.15
#: Both eyes changed when their changes were seen at most this many frames apart: one eye's
#: may have gone out already (or matched an image held) when the other's shows, and the
#: other eye's patch is still the blink's.
PAIRED_FRAMES = 3
#: A change still growing (by more than this factor a frame: a lid closing, a glance on its
#: way) waits for where it comes to rest, at most SETTLE_FRAMES frames.
SETTLED = 1.15
SETTLE_FRAMES = 2
#: The mouth's inside is looked at only while it is open: its area on screen at least this
#: fraction of the mouth's width squared.
MOUTH_OPEN = 0.06
#: A change the bucket cannot pay an image for, that has waited this many frames (longer than
#: a blink), goes back to a held image whose difference from it is at most NEARER times that
#: of the image shown: an eye sent half shut as it began to blink stayed so for 1.5 s on
#: vtc1nw, where the open eye held before was a 17-byte reference away.
HELD_AFTER = 8
NEARER = 0.5
#: Bytes a RemPatch adds around its image (header byte, region, codec, seq and the three
#: colour figures).
PACKET_OVERHEAD = 13
#: Texels on triangles seen more obliquely than this cosine keep the receiver's content.
MIN_FACING = 0.15
#: Time constant, seconds, of the reference colour the patches carry: each frame's
#: measurement moves it by 1 / (COLOUR_TIME_S * fps) of the way. Slow enough to average the
#: eyes' own changes out, fast enough to follow the light (docs/what-we-tried.md, "A
#: steadier reference colour").
COLOUR_TIME_S = 1.5


def _luma(bgr: np.ndarray) -> np.ndarray:
    b = bgr.astype(np.float32)
    return 0.114 * b[..., 0] + 0.587 * b[..., 1] + 0.299 * b[..., 2]


def _smooth(bgr: np.ndarray) -> np.ndarray:
    """Luma, lightly smoothed (3x3 Gaussian): a sub-texel shift changes edges less."""
    return cv2.GaussianBlur(_luma(bgr), (3, 3), 0)


def encode_webp(image: np.ndarray, quality: int) -> bytes:
    ok, buf = cv2.imencode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("WebP encoding failed")
    return buf.tobytes()


@dataclass
class RemCounts:
    """What the REM sender did over a session."""

    images: dict[str, int] = field(default_factory=dict)  # patches carrying an image
    references: dict[str, int] = field(default_factory=dict)  # patches naming one held
    repeats: dict[str, int] = field(default_factory=dict)  # of both, repeats at keyframes
    bytes: dict[str, int] = field(default_factory=dict)  # patch packet bytes
    changed_frames: dict[str, int] = field(default_factory=dict)  # frames seen changed
    waited: int = 0  # region-frames a change waited for the bucket

    def add(self, packet: RemPatch, nbytes: int, repeat: bool) -> None:
        kind = self.references if packet.reference is not None else self.images
        name = packet.region
        kind[name] = kind.get(name, 0) + 1
        self.bytes[name] = self.bytes.get(name, 0) + nbytes
        if repeat:
            self.repeats[name] = self.repeats.get(name, 0) + 1

    @property
    def patches(self) -> int:
        return sum(self.images.values()) + sum(self.references.values())

    def as_dict(self) -> dict[str, object]:
        return {
            "patches": self.patches,
            "images": dict(self.images),
            "references": dict(self.references),
            "repeats": dict(self.repeats),
            "bytes": dict(self.bytes),
            "changed_frames": dict(self.changed_frames),
            "waited": self.waited,
        }


@dataclass(eq=False)
class _Image:
    """An image of a region that the receiver holds (or will, once its patch arrives)."""

    key: int  # the frame number of the patch that brought it (the snapshot's: the texture)
    content: np.ndarray  # (h, w, 3) uint8 as cut, before coding
    luma: np.ndarray  # its luma, smoothed (_smooth) and padded by one texel
    packet: RemPatch | None  # the patch that brought it (None: the snapshot's texture)
    sent: int = 1  # times its image went out


@dataclass(eq=False)
class _Region:
    """One region as the receiver has it."""

    base: _Image  # the snapshot's texture
    current: _Image  # what it shows
    held: list[_Image] = field(default_factory=list)  # images it keeps, oldest first
    waiting: int = 0  # frames it has been changed and not sent
    score: float = 0.0  # its change in the last frame (0: none)
    dirty: bool = False  # something was sent for it since the last keyframe
    changed_at: int = -(10**9)  # the last frame it was seen changed
    # The frame of its last image. A reference to an image held is no lid caught on its way:
    # after one the next change waits to settle (else a blink went out half shut).
    sent_at: int = -(10**9)

    def choices(self) -> list[_Image]:
        return [self.base, *self.held]

    def moving_on(self, seq: int) -> bool:
        """Changed again just after its last patch went out: a lid the patch caught on its
        way (a blink's half-shut frame), which is still the same blink."""
        return seq - self.sent_at <= SETTLE_FRAMES


def _image(key: int, content: np.ndarray, packet: RemPatch | None, sent: int = 1) -> _Image:
    padded = cv2.copyMakeBorder(_smooth(content), 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    return _Image(key, content, padded, packet, sent)


class RemEncoder:
    """Cuts, detects and codes one session's REM patches.

    layout : the session's REM layout (both ends build the same)
    texture : (T, T, 3) uint8 BGR, the snapshot's texture (what the receiver starts from)
    first_seq : the snapshot's frame number (how a reference names the snapshot's texture)
    fps : frames per second of the call (the bucket fills per frame)
    budget_kbps : REM payload budget; regions : names to send (default: those of
        models.rem.SENT_REGIONS in the layout)
    """

    def __init__(
        self,
        layout: RemLayout,
        texture: np.ndarray,
        first_seq: int,
        fps: float,
        budget_kbps: float = BUDGET_KBPS,
        regions: tuple[str, ...] | None = None,
    ) -> None:
        if texture.shape != (layout.size, layout.size, 3):
            raise ValueError(
                f"expected a ({layout.size}, {layout.size}, 3) texture, got {texture.shape}"
            )
        self.layout = layout
        if regions is None:
            regions = tuple(n for n in SENT_REGIONS if n in layout.boxes)
        self.regions = tuple(regions)
        self.first_seq = first_seq
        self.fps = fps
        self.set_budget(budget_kbps)
        self.tokens = budget_kbps * 1000.0 / 8.0 * START_S
        self.mouth_tokens = self.mouth_rate * self.fps * START_S
        # Bytes the call could still have spent under LIMIT_KBPS on average since it began:
        # never less than the bucket's tokens, as the bucket fills more slowly.
        self.limit = LIMIT_KBPS * 1000.0 / 8.0 / fps
        self.headroom = self.tokens
        rasteriser = UvRasteriser(layout.triangles, layout.uvs, layout.patch_size)
        self._triangles = layout.triangles
        self._samplers: dict[str, tuple[sp.csr_matrix, np.ndarray, np.ndarray]] = {}
        self._fill = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        for name in layout.names:
            box = layout.boxes[name]
            grid = np.s_[box.y : box.y + box.height, box.x : box.x + box.width]
            tri = rasteriser.triangle[grid].ravel()
            bary = rasteriser.bary[grid].reshape(-1, 3).astype(np.float64)
            covered = np.flatnonzero(tri >= 0)
            k = len(covered)
            matrix = sp.csr_matrix(
                (
                    bary[covered].ravel(),
                    (np.repeat(np.arange(k), 3), layout.triangles[tri[covered]].ravel()),
                ),
                shape=(k, len(layout.uvs)),
            )
            self._samplers[name] = (matrix, covered, tri[covered])
            if name == MOUTH_INTERIOR:
                # Texels outside the mouth's lens-shaped strip take the nearest one inside it
                # (cheap to code; bilinear sampling at the strip's edge reads them).
                outside = np.ones(box.width * box.height, np.uint8)
                outside[covered] = 0
                _, labels = cv2.distanceTransformWithLabels(
                    outside.reshape(box.height, box.width),
                    cv2.DIST_L2,
                    3,
                    labelType=cv2.DIST_LABEL_PIXEL,
                )
                nearest = np.zeros(labels.max() + 1, np.int64)
                nearest[labels.ravel()[covered]] = covered
                gaps = np.flatnonzero(outside)
                self._fill = (gaps, nearest[labels.ravel()[gaps]])
        self.states: dict[str, _Region] = {}
        for name in layout.names:
            base = _image(first_seq, self.from_texture(texture, name), None, sent=0)
            self.states[name] = _Region(base, base)
        self._colour_regions = tuple(n for n in EYES if n in layout.boxes)
        # The snapshot's own reference colour: sent while the frame shows no skin to measure
        # (the receiver's colours then stay as they are).
        self.model_colour = self._colour(
            {
                n: (s.base.content, np.ones(s.base.content.shape[:2], bool))
                for n, s in self.states.items()
            }
        )
        self._refresh_all = False
        self._smallest: dict[str, int] = {}  # region -> bytes of its last patch's lowest quality
        self.counts = RemCounts()
        #: The reference colour the patches carry, followed frame by frame (None: no skin
        #: measured yet).
        self.colour: ColourStats | None = None

    def set_budget(self, kbps: float) -> None:
        """Fill the bucket at ``kbps`` from now on (it holds BUCKET_S of it); the mouth's
        inside's at its share of that (MOUTH_BUDGET_KBPS against BUDGET_KBPS)."""
        self.rate = kbps * 1000.0 / 8.0 / self.fps  # bytes per frame
        self.capacity = kbps * 1000.0 / 8.0 * BUCKET_S
        self.mouth_rate = self.rate * MOUTH_BUDGET_KBPS / BUDGET_KBPS
        self.mouth_capacity = self.mouth_rate * self.fps * MOUTH_BUCKET_S

    def _tokens(self, name: str) -> float:
        """Bytes region ``name``'s bucket holds."""
        return self.mouth_tokens if name == MOUTH_INTERIOR else self.tokens

    def from_texture(self, texture: np.ndarray, name: str) -> np.ndarray:
        """Region ``name`` of a (T, T, 3) texture on the patch grid."""
        box = self.layout.boxes[name]
        part = texture[box.texture_slices]
        if box.scale == 1:
            return np.ascontiguousarray(part)
        return cv2.resize(part, (box.width, box.height), interpolation=cv2.INTER_AREA)

    # -- cutting --------------------------------------------------------------------------

    def cut(
        self, image: np.ndarray, vertices: np.ndarray, name: str
    ) -> tuple[np.ndarray, np.ndarray]:
        """Region ``name`` of ``image`` in texture space.

        image : (h, w, 3) uint8 BGR frame; vertices : (n, 3) the layout mesh's vertices in
        that frame's image space (:meth:`RemLayout.vertices` of the face's).
        returns the patch (box height, box width, 3) uint8 and a (box height, box width)
        bool mask of the texels seen in this frame (covered and facing the camera); the
        others hold what the receiver already shows.
        """
        box = self.layout.boxes[name]
        matrix, covered, tri = self._samplers[name]
        points = matrix @ vertices
        n = box.width * box.height
        map_x = np.full(n, -1.0, np.float32)
        map_y = np.full(n, -1.0, np.float32)
        map_x[covered] = points[:, 0]
        map_y[covered] = points[:, 1]
        patch = cv2.remap(
            image,
            map_x.reshape(box.height, box.width),
            map_y.reshape(box.height, box.width),
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        flat = np.zeros(n, bool)
        if name == MOUTH_INTERIOR:
            flat[covered] = True  # its triangles fold flat when it shuts: see _mouth_open
        else:
            v = vertices
            used = np.unique(tri)
            t = self._triangles[used]
            normal = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            length = np.linalg.norm(normal, axis=1)
            facing = np.zeros(len(self._triangles))
            facing[used] = -normal[:, 2] / np.where(length > 0, length, 1.0)
            flat[covered] = facing[tri] > MIN_FACING
        seen = flat.reshape(box.height, box.width)
        if name == MOUTH_INTERIOR:
            # Texels outside the mouth's lens-shaped strip: grown from the strip, cheap to code.
            gaps, nearest = self._fill
            flat_patch = patch.reshape(-1, 3)
            flat_patch[gaps] = flat_patch[nearest]
        else:
            patch[~seen] = self.states[name].current.content[~seen]
        return patch, seen

    def _mouth_open(self, vertices: np.ndarray) -> bool:
        strip = self._triangles[self.layout.interior_triangles]
        a, b, c = vertices[strip[:, 0], :2], vertices[strip[:, 1], :2], vertices[strip[:, 2], :2]
        u, v = b - a, c - a
        area = 0.5 * np.abs(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]).sum()
        width = float(np.ptp(vertices[np.unique(strip), 0]))
        return bool(width > 0 and area >= MOUTH_OPEN * width * width)

    # -- deciding -------------------------------------------------------------------------

    def change(
        self,
        name: str,
        patch: np.ndarray,
        seen: np.ndarray,
        against: _Image,
        shifts: tuple[int, ...] = (0, 1, 2),
    ) -> float:
        """Fraction of region ``name``'s weighted texels whose luma differs by more than
        CHANGE_LEVEL from image ``against``, once the two are aligned.

        The geometry's quantisation and the tracker's jitter move the whole cut by up to
        about a texel, which must not count as a change at every edge: both are smoothed a
        little, and ``against`` is shifted by the whole texel (of the nine, -1 to 1 in each
        direction) that matches best. A change of the eye itself (lids, iris, the white of
        the eye) stays. ``shifts`` (0 to 2: -1 to 1 texel) are the offsets tried.

        An image held that matches this way is drawn where it was cut: up to a texel off,
        the eye in it may lie a pixel or two from where the camera saw it this frame."""
        weight = self.layout.boxes[name].alpha * seen
        total = float(weight.sum())
        if total <= 0:
            return 0.0
        ref = against.luma
        luma = _smooth(patch)
        h, w = luma.shape
        best = np.inf
        for dy in shifts:
            for dx in shifts:
                d = np.abs(luma - ref[dy : dy + h, dx : dx + w])
                cost = float((weight * d).sum())
                if cost < best:
                    best, moved = cost, d > CHANGE_LEVEL
        return float((weight * moved).sum()) / total

    def both_eyes_changed(self, seq: int) -> bool:
        """Whether both eyes were seen changed within PAIRED_FRAMES of frame ``seq``."""
        eyes = self._colour_regions
        return bool(eyes) and all(seq - self.states[n].changed_at <= PAIRED_FRAMES for n in eyes)

    def request_refresh(self) -> None:
        """The next keyframe repeats every region (a receiver asked for one)."""
        self._refresh_all = True

    def changed(
        self,
        seq: int,
        image: np.ndarray,
        vertices: np.ndarray,
        tracked: np.ndarray | None = None,
    ) -> list[RemPatch]:
        """Patches of the regions that changed in frame ``seq`` and that the bucket allows.

        image : (h, w, 3) uint8 BGR; vertices : (n, 3) the face's vertices as the receiver
        rebuilds this frame, image space (n = the layout's face vertex count); tracked :
        (n, 3) the face as tracked in this frame, if known. The mouth's inside is cut
        between the tracked inner lips: the rebuilt mouth opens a little less than the real
        one (the lips channel's elements reach about 85 % of it, after smoothing and
        quantisation), and between its lips the frame shows lip, not the teeth and tongue
        the receiver's opening should show.
        """
        self.tokens = min(self.capacity, self.tokens + self.rate)
        self.mouth_tokens = min(self.mouth_capacity, self.mouth_tokens + self.mouth_rate)
        self.headroom += self.limit
        ext = self.layout.vertices(vertices)
        mouth = ext if tracked is None else self.layout.vertices(tracked)
        # The eyes are cut for their skin's colour even when they are not sent.
        wanted = self.regions + tuple(n for n in self._colour_regions if n not in self.regions)
        shut = MOUTH_INTERIOR in wanted and not self._mouth_open(mouth)
        cuts = {
            name: self.cut(image, mouth if name == MOUTH_INTERIOR else ext, name)
            for name in wanted
            if not (name == MOUTH_INTERIOR and shut)
        }
        self._follow_colour(cuts)
        candidates = []
        inside_due = False  # the mouth's inside changed, and settled
        pending = 0  # regions changed, ready or still settling: they share the bucket
        for name in self.regions:
            state = self.states[name]
            if name not in cuts:
                state.waiting = 0  # the mouth is shut: its inside shows nothing
                continue
            patch, seen = cuts[name]
            score = self.change(name, patch, seen, state.current)
            # Hysteresis: a change waiting for the bucket stays one until it is sent or
            # has mostly gone again.
            if score < (SAME_FRACTION if state.waiting else CHANGE_FRACTION):
                state.waiting, state.score = 0, 0.0
                continue
            self.counts.changed_frames[name] = self.counts.changed_frames.get(name, 0) + 1
            state.changed_at = seq
            state.waiting += 1
            pending += name != MOUTH_INTERIOR  # it has a bucket of its own
            rising, state.score = score > SETTLED * state.score, score
            if rising and state.waiting < SETTLE_FRAMES and not state.moving_on(seq):
                continue  # a lid still closing: send where it comes to rest
            if name == MOUTH_INTERIOR:
                inside_due = True  # it waits for nothing else
                continue
            head = EYE_HEAD_START if name in EYES else 0
            weight = float((self.layout.boxes[name].alpha * seen).sum())
            candidates.append((state.waiting + head, score * weight, name, score))
        candidates.sort(reverse=True)
        out: list[RemPatch] = []
        if inside_due:
            packet = self._send(seq, MOUTH_INTERIOR, *cuts[MOUTH_INTERIOR], 1, 0.0)
            if packet is None:
                self.counts.waited += 1
            else:
                out.append(packet)
        # Both eyes changed at once: a blink or a glance, which may spend the bytes kept for
        # the eyes; anything else (one eye alone: mostly the light or the fit moving) only
        # what leaves them. Each takes its share among the regions waiting (a lid still
        # closing included: the other eye's image is due a frame later).
        both = self.both_eyes_changed(seq)
        blocked = False
        for i, (_, _, name, score) in enumerate(candidates):
            moving_on = self.states[name].moving_on(seq)
            big = name in EYES and (score >= BIG_CHANGE or moving_on) and both
            if blocked and not big:
                self.counts.waited += 1
                continue
            # A blink may borrow BLINK_DEBT_S of the budget, which the frames after it pay
            # back: its moment does not come again. The loan keeps within LIMIT_KBPS.
            loan = min(BLINK_DEBT_S * self.rate * self.fps, max(0.0, self.headroom - self.tokens))
            reserve = -loan if big else self._eye_reserve(set())
            packet = self._send(seq, name, *cuts[name], pending - i, reserve)
            if packet is None:
                # The rest wait their turn behind it, but a blink: the bytes kept for the
                # eyes are its own, and a region that waited longer cannot spend them.
                self.counts.waited += 1
                blocked = True
                continue
            out.append(packet)
        return out

    def _send(
        self,
        seq: int,
        name: str,
        patch: np.ndarray,
        seen: np.ndarray,
        sharing: int,
        reserve: float,
    ) -> RemPatch | None:
        """A reference to an image the receiver holds that matches, else the image coded
        to fit its share of what the bucket holds beyond ``reserve`` (negative: into debt);
        None, nothing spent, when the bucket cannot pay."""
        state = self.states[name]
        available = self._tokens(name) - reserve
        scores = [(self.change(name, patch, seen, img), i) for i, img in enumerate(state.choices())]
        score, i = min(scores)
        if score <= SAME_FRACTION and state.choices()[i] is not state.current:
            return self._refer(seq, name, state.choices()[i], available)
        data, quality = self._coded(name, patch, available / sharing, available)
        if data is None:
            shown = self.change(name, patch, seen, state.current)
            near = max(CHANGE_FRACTION, NEARER * shown if state.waiting >= HELD_AFTER else 0.0)
            if score < near and state.choices()[i] is not state.current:
                # No image fits, but one held would not count as changed, or after a while is
                # far nearer than what the receiver shows: better than keeping that (a lid
                # caught reopening stays half shut otherwise).
                return self._refer(seq, name, state.choices()[i], available)
            return None
        packet = RemPatch(seq, name, "webp", data, *self._stats())
        if not self._pay(packet, repeat=False, available=available):
            return None
        self._hold(state, _image(seq, patch, packet))
        state.waiting, state.score, state.dirty = 0, 0.0, True
        state.sent_at = seq
        logger.debug("REM %s at frame %d: WebP q%d, %d bytes", name, seq, quality, len(data))
        return packet

    def _refer(self, seq: int, name: str, held: _Image, available: float) -> RemPatch | None:
        """A reference to image ``held`` of region ``name``, if ``available`` pays for it."""
        if len(bytes(RemPatch.referring(seq, name, held.key, 0, 0, 0))) > available:
            return None  # (the colour, float32, does not change the size)
        packet = RemPatch.referring(seq, name, held.key, *self._stats())
        self._pay(packet, repeat=False)
        state = self.states[name]
        state.current, state.waiting, state.score, state.dirty = held, 0, 0.0, True
        return packet

    def _eye_reserve(self, but: set[str]) -> float:
        """Bytes kept for the eyes' next images (their last sizes at the lowest quality),
        but for the eyes in ``but``."""
        return float(
            sum(
                self._smallest.get(n, 0) + PACKET_OVERHEAD
                for n in self.regions
                if n in EYES and n not in but
            )
        )

    def _coded(
        self, name: str, patch: np.ndarray, share: float, available: float
    ) -> tuple[bytes | None, int]:
        """WebP bytes at the best quality whose size fits ``share`` (the lowest if none
        does); None when even the lowest would not fit ``available``."""
        smallest = self._smallest.get(name)
        if smallest is not None and smallest + PACKET_OVERHEAD > available:
            return None, 0  # its last patch at the lowest quality did not fit either
        data, quality = b"", QUALITIES[-1]
        for q in reversed(QUALITIES):  # the lowest first: it tells whether any fits
            coded = encode_webp(patch, q)
            if q == QUALITIES[-1]:
                self._smallest[name] = len(coded)
                if len(coded) + PACKET_OVERHEAD > available:
                    return None, q
            elif len(coded) + PACKET_OVERHEAD > share:
                break
            data, quality = coded, q
        return data, quality

    def _pay(self, packet: RemPatch, repeat: bool, available: float = math.inf) -> bool:
        """Take the packet's bytes from the bucket, into debt if need be; nothing, and
        False, when they are more than ``available``."""
        size = len(bytes(packet))
        if size > available:
            return False
        if packet.region == MOUTH_INTERIOR:
            self.mouth_tokens -= size
        else:
            self.tokens -= size
            self.headroom -= size
        self.counts.add(packet, size, repeat)
        return True

    @staticmethod
    def _hold(state: _Region, image: _Image) -> None:
        """The receiver keeps a new image, and forgets its oldest past REM_CACHE."""
        state.current = image
        state.held.append(image)
        del state.held[:-REM_CACHE]

    def keyframe(self, seq: int, fresh: list[RemPatch]) -> list[RemPatch]:
        """Repeats that go with keyframe ``seq`` (regions in ``fresh``, this frame's own
        patches, need none).

        A receiver that asked for the keyframe gets every region again, owed: it may leave
        the bucket in debt, which later patches wait out. A periodic keyframe repeats what
        was sent since the last one as far as the bucket can pay without the eyes' bytes;
        the rest waits for the next keyframe."""
        done = {p.region for p in fresh}
        h, s, v = self._stats()
        owed = self._refresh_all
        out = []
        for name in self.regions:
            state = self.states[name]
            if name in done:
                state.dirty = False
                continue
            if not (owed or state.dirty):
                continue
            current = state.current
            if current is state.base or (current.sent > 1 and not owed):
                packet = RemPatch.referring(seq, name, current.key, h, s, v)
            else:
                old = current.packet
                assert old is not None
                packet = RemPatch(seq, name, old.codec, old.data, h, s, v)
            reserve = 0.0 if name == MOUTH_INTERIOR else self._eye_reserve(set())
            available = math.inf if owed else self._tokens(name) - reserve
            if not self._pay(packet, repeat=True, available=available):
                continue
            if packet.reference is None:
                self._hold(state, _image(seq, current.content, packet, sent=current.sent + 1))
            state.dirty = False
            out.append(packet)
        self._refresh_all = False
        return out

    def _colour(self, cuts: dict[str, tuple[np.ndarray, np.ndarray]]) -> ColourStats | None:
        """The reference skin colour over the eye regions' texels (None without any)."""
        eyes = self._colour_regions
        if not eyes:
            return None
        hsv = [to_hsv(cuts[n][0]).reshape(-1, 3) for n in eyes]
        mask = [(self.layout.boxes[n].inside & cuts[n][1]).ravel() for n in eyes]
        pixels = np.concatenate(hsv)[np.concatenate(mask)]
        return reference_colour(pixels[:, None, :])

    def _follow_colour(self, cuts: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """Move :attr:`colour` towards this frame's reference colour (``cuts``: the frame's
        cut regions), 1 / (COLOUR_TIME_S * fps) of the way; the hue the short way round."""
        frame = self._colour(cuts)
        if frame is None:
            return
        if self.colour is None:
            self.colour = frame
            return
        k = min(1.0, 1.0 / (COLOUR_TIME_S * self.fps))
        old = self.colour
        turn = (frame.h_peak - old.h_peak + 180.0) % 360.0 - 180.0
        self.colour = ColourStats(
            (old.h_peak + k * turn) % 360.0,
            old.s_mean + k * (frame.s_mean - old.s_mean),
            old.v_mean + k * (frame.v_mean - old.v_mean),
        )

    def _stats(self) -> tuple[float, float, float]:
        """The colour a patch carries: the followed one, else the snapshot's, else none (0)."""
        colour = self.colour or self.model_colour
        if colour is None:
            return (0.0, 0.0, 0.0)
        return (colour.h_peak, colour.s_mean, colour.v_mean)

    def fill_atlas(self, texture: np.ndarray, image: np.ndarray, vertices: np.ndarray) -> None:
        """Write the mouth's inside, as ``image`` shows it, into its rectangle of the
        snapshot's ``texture`` (in place) and take it as what the receiver starts from.

        vertices : (n, 3) the face's vertices in ``image`` (those the texture was unwrapped
        with). The face's unwrap leaves the rectangle to its hole filling.
        """
        if MOUTH_INTERIOR not in self.states:
            return
        patch, _ = self.cut(image, self.layout.vertices(vertices), MOUTH_INTERIOR)
        box = self.layout.boxes[MOUTH_INTERIOR]
        rows, cols = box.texture_slices
        size = (cols.stop - cols.start, rows.stop - rows.start)
        texture[rows, cols] = cv2.resize(patch, size, interpolation=cv2.INTER_LINEAR)
        base = _image(self.first_seq, patch, None, sent=0)
        self.states[MOUTH_INTERIOR] = _Region(base, base)
