"""Protocol constants: version, packet kinds, limits, timings, channel names.

Everything a compatible peer must agree on lives here (and in docs/protocol.md), so that the
codec (:mod:`facewire.protocol.packets`), the quantiser (:mod:`facewire.protocol.quant`) and the
transport (:mod:`facewire.protocol.transport`) never disagree.
"""

from __future__ import annotations

import logging
from enum import IntEnum
from typing import Final

logger = logging.getLogger(__name__)

#: The first element of every packet. Bumped on any incompatible change of the wire format.
PROTOCOL_VERSION: Final = 2


class Kind(IntEnum):
    """Packet kind codes, the low nibble of every packet's header byte."""

    SNAPSHOT = 1
    KEY_FRAME = 2
    REM_PATCH = 3
    KEYFRAME_REQUEST = 4
    HEARTBEAT = 5
    RECEIVER_STATS = 6
    BYE = 7
    SNAPSHOT_REQUEST = 8
    DELTA_FRAME = 9
    AUDIO_FRAME = 10
    MEDIA_KEY = 11
    REFRESH = 12


# --- limits (decoding rejects anything beyond them) -----------------------------------------

#: Largest packet accepted, in bytes (the snapshot carries a texture and a background image).
MAX_PACKET_BYTES: Final = 16 * 1024 * 1024
#: Largest message a receiver's SUB socket takes (libzmq disconnects a peer that sends more):
#: every update is far smaller (a frame body is at most 16 KiB, an Opus packet 1275 bytes, a
#: REM patch a few hundred), and a queue of UPDATE_HWM of them then holds at most 16 MiB.
MAX_UPDATE_BYTES: Final = 256 * 1024
#: Longest msgpack str (names, meta values), in UTF-8 bytes.
MAX_STR_LEN: Final = 1024
#: Longest msgpack array (wire_layout entries are the longest arrays).
MAX_ARRAY_LEN: Final = 4096
#: Largest msgpack map (quant table, meta, stats, channels).
MAX_MAP_LEN: Final = 256
#: Most vertices in a snapshot mesh.
MAX_VERTICES: Final = 200_000
#: Most int16 values in one parameter vector (params or one channel).
MAX_PARAMS: Final = 8192
#: Largest frame size in pixels along either axis (a real call needs no more; a bigger image
#: costs gigabytes to decode and render).
MAX_IMAGE_SIDE: Final = 4096
#: Frame rates a snapshot may state, frames per second: 1e6 / fps, the frame interval in
#: microseconds, must be a sane integer (1e6 / 5e-324 is infinite).
MIN_FPS: Final = 0.01
MAX_FPS: Final = 1000.0
#: Most channels in a session's channel table.
MAX_CHANNELS: Final = 32
#: Largest range-coded body of one frame packet, in bytes.
MAX_FRAME_BODY: Final = 16384
#: Largest |value| of a quantised channel value (keeps every residual inside 32 bits).
MAX_CHANNEL_VALUE: Final = 2**24
#: Most frames one delta frame may advance (the sender sends at least this often).
MAX_SEQ_STEP: Final = 30
#: Largest |capture time - prediction| a delta frame can carry, milliseconds.
MAX_TIME_RESIDUAL_MS: Final = 60_000
#: Largest Opus packet of one audio frame, in bytes (RFC 6716, section 3.4, R2).
MAX_AUDIO_BYTES: Final = 1275

# --- integer ranges ----------------------------------------------------------------------------

UINT32_MAX: Final = 2**32 - 1
INT64_MIN: Final = -(2**63)
INT64_MAX: Final = 2**63 - 1

# --- payload formats -----------------------------------------------------------------------------

#: Image codecs accepted for REM patches (the sender codes them as WebP: a patch of 30 to 200
#: bytes would be mostly header as a JPEG).
REM_CODECS: Final = ("jpeg", "png", "webp")
#: A REM patch's "codec" when it shows an earlier patch of its region again (data: that
#: patch's frame number).
REM_REFERENCE: Final = "ref"
#: A RemPatch's codec byte: the index in this table.
REM_CODES: Final = (REM_REFERENCE, *REM_CODECS)
#: The REM regions (models/rem.py lays them out); a RemPatch's region byte is the index here.
REM_REGIONS: Final = ("eye_right", "eye_left", "mouth", "mouth_interior")
#: The colour figures a RemPatch carries travel as u16: hue in hundredths of a degree,
#: saturation and value in 65535ths.
REM_HUE_STEP: Final = 0.01
REM_UNIT_STEPS: Final = 65535
#: Images of each REM region both ends hold besides the snapshot's texture (a reference may
#: name one): the newest ones, in the order their patches were sent.
REM_CACHE: Final = 6
#: A refresh (a part of the camera's picture the model does not show) is the area of its
#: frame it covers, at most this many pixels on a side.
MAX_REFRESH_SIDE: Final = 4096

# --- bandwidth accounting channels ---------------------------------------------------------------

CHANNEL_SNAPSHOT: Final = "snapshot"
CHANNEL_GEOMETRY: Final = "geometry"
CHANNEL_REM: Final = "rem"
CHANNEL_CONTROL: Final = "control"
CHANNEL_AUDIO: Final = "audio"
#: Second copies of frame packets, sent over the back channel's connection (3.6).
CHANNEL_SPARE: Final = "spare"
CHANNELS: Final = (
    CHANNEL_SNAPSHOT,
    CHANNEL_GEOMETRY,
    CHANNEL_REM,
    CHANNEL_CONTROL,
    CHANNEL_AUDIO,
    CHANNEL_SPARE,
)

# --- audio (docs/protocol.md, AudioFrame) -------------------------------------------------------

#: Opus at 48 kHz, mono, one 20 ms frame per AudioFrame packet.
AUDIO_RATE: Final = 48_000
AUDIO_FRAME_MS: Final = 20
AUDIO_FRAME_SAMPLES: Final = AUDIO_RATE * AUDIO_FRAME_MS // 1000

# --- transport timings and queue sizes -----------------------------------------------------------

#: The sender publishes a Heartbeat when it has published nothing for this long.
HEARTBEAT_INTERVAL_S: Final = 1.0
#: A receiver declares the peer lost after this long without a well-formed packet: two
#: heartbeats missed and half an interval of slack, so a lost sender is noticed within 3 s.
PEER_TIMEOUT_S: Final = 2.5
#: During the handshake the receiver re-sends its probe this often until its SUB socket
#: receives a published packet.
PROBE_INTERVAL_MS: Final = 100

# --- transport v2: bounded queues, rate limits, CURVE (protocol/transport.py) -------------------

#: PUB send and SUB receive high-water marks, in messages (about 2 s at 30 fps). Past it libzmq
#: drops what the sender publishes to that receiver; the receiver sees a seq gap.
UPDATE_HWM: Final = 64
#: Back channel (DEALER send, ROUTER receive) high-water marks: a flooding peer is slowed down.
BACK_CHANNEL_HWM: Final = 64
#: Snapshot replies queued per peer on the ROUTER (up to MAX_PACKET_BYTES each); more are dropped.
SNAPSHOT_HWM: Final = 2
#: A peer (one ROUTER identity) is sent at most one snapshot per this many seconds.
SNAPSHOT_MIN_INTERVAL_S: Final = 0.5
#: Most peers the snapshot rate limit remembers, and most requests waiting for a first snapshot.
MAX_SNAPSHOT_PEERS: Final = 256
#: The same snapshot is sent to the same peer again only after this many times its bare
#: transfer time at the sender's budget (a request repeated while a reply crosses a thin link).
SNAPSHOT_TRANSFER_ROOM: Final = 3.0
#: A joining receiver repeats its SnapshotRequest this often until the snapshot arrives.
SNAPSHOT_RETRY_MS: Final = 1000
#: A frame that reaches the receiver this much later than the fastest of the last
#: LATE_WINDOW_S (capture to arrival) waited behind a lost TCP segment: it is late.
LATE_FRAME_MS: Final = 50
LATE_WINDOW_S: Final = 10.0
#: ReceiverStats name: frames that came late since the last report (they ask for the second
#: path), sent at most every LATE_REPORT_S.
LATE_FRAMES: Final = "late_frames"
LATE_REPORT_S: Final = 1.0
#: ReceiverStats name: the full snapshot after its draft was taken (docs/protocol.md 8.7).
REFINED: Final = "refined"
#: Snapshot meta key: set on a draft, a smaller version of the session's snapshot (8.7).
DRAFT: Final = "draft"
#: The sender serves a draft of its snapshot first when the full one would take longer than
#: this at its budget, and sends the full one paced behind the media; again every
#: REFINE_RETRY_S until the receiver says REFINED, at most REFINE_ATTEMPTS times.
DRAFT_ABOVE_S: Final = 1.0
REFINE_RETRY_S: Final = 6.0
REFINE_ATTEMPTS: Final = 3
#: ReceiverStats name: how long the snapshot took to come, ms (with "ready"). A draft that came
#: at FAST_JOIN_BPS or more crossed a fast link: the full snapshot follows at once on the
#: ROUTER connection instead of paced in the datagrams. The time includes a round trip and
#: the sender's answer, which a 2 KB draft does not outweigh: a loaded loopback brought it
#: at 150-250 kbit/s, while a 48 kbit/s link cannot bring it faster than 48.
SNAPSHOT_MS: Final = "snapshot_ms"
FAST_JOIN_BPS: Final = 96_000
#: A draft goes in the datagrams once the receiver's path is open (its key opens it); where
#: the path has not opened this long after the key, on the snapshot connection instead.
DRAFT_PATH_WAIT_S: Final = 1.0
#: Snapshot meta of a new scene's session (the camera cut to another shot: the sender starts a
#: session from it): the id of the session that began the call it goes on. A receiver of that
#: call rejoins it in the same call; any other session is a restarted sender's (docs/protocol.md
#: 8.9).
CALL: Final = "call"
#: Snapshot meta of a scene that shows no face (docs/protocol.md 8.9): 0. Its texture is empty
#: and its reference puts the face outside the frame, so every receiver draws the scene alone.
FACE: Final = "face"
#: ReceiverStats name, sent instead of "ready" when a receiver has joined a new scene's
#: session of its call (with SNAPSHOT_MS).
SCENE: Final = "scene"
#: After a receiver's last report of late frames, the sender keeps sending it a second copy of
#: every frame packet, over the ROUTER/DEALER connection, for this long.
SPARE_PATH_HOLD_S: Final = 30.0
#: A frame packet whose counter was taken less than this long ago is a second copy. Counters wrap
#: after 256 packets (8.5 s at 30 fps): the window must be shorter than that.
COPY_WINDOW_S: Final = 4.0
#: ZAP domain of the sender's CURVE sockets (each endpoint appends its own suffix).
ZAP_DOMAIN: Final = "facewire"
