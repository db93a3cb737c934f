"""Protocol constants: version, packet kinds, limits, timings, channel names.

Everything a compatible peer must agree on lives here (and in docs/protocol.md), so that the
codec (:mod:`protocol.packets`), the quantiser (:mod:`protocol.quant`) and the transport
(:mod:`protocol.transport`) never disagree.
"""

from __future__ import annotations

import logging
from enum import IntEnum
from typing import Final

logger = logging.getLogger(__name__)

#: The first element of every packet. Bumped on any incompatible change of the wire format.
PROTOCOL_VERSION: Final = 1


class Kind(IntEnum):
    """Packet kind codes, the second element of every packet."""

    SNAPSHOT = 1
    FRAME = 2
    REM_PATCH = 3
    KEYFRAME_REQUEST = 4
    HEARTBEAT = 5
    RECEIVER_STATS = 6
    BYE = 7
    SNAPSHOT_REQUEST = 8


# --- limits (decoding rejects anything beyond them) -----------------------------------------

#: Largest packet accepted, in bytes (the snapshot carries a texture and a background image).
MAX_PACKET_BYTES: Final = 16 * 1024 * 1024
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
#: Largest frame size in pixels along either axis.
MAX_IMAGE_SIDE: Final = 16384
#: Largest control-point count of one wire curve.
MAX_CTRL: Final = 1024

# --- integer ranges ----------------------------------------------------------------------------

UINT32_MAX: Final = 2**32 - 1
INT64_MIN: Final = -(2**63)
INT64_MAX: Final = 2**63 - 1
#: Quantised values are clipped to +-INT16_LIMIT (-32768 is never produced, so negation is safe).
INT16_LIMIT: Final = 32767

# --- payload formats -----------------------------------------------------------------------------

#: Image codecs accepted for REM patches.
REM_CODECS: Final = ("jpeg", "png")
JPEG_MAGIC: Final = b"\xff\xd8\xff"
PNG_MAGIC: Final = b"\x89PNG\r\n\x1a\n"

# --- quantisation table keys (Snapshot.quant) and defaults -------------------------------------

#: Step of the pose scale, in natural-log units (the wire carries round(ln(scale) / step)).
QUANT_POSE_SCALE: Final = "pose.scale"
#: Step of the pose translation, in the units of the pose's target frame (facewire: image pixels).
QUANT_POSE_TRANSLATION: Final = "pose.translation"
#: Step of the wire radial scales s_j (sent as s_j - 1, dimensionless).
QUANT_WIRE_S: Final = "wire.s"
#: Step of the wire control-point displacements q_jl, in cm (model space).
QUANT_WIRE_Q: Final = "wire.q"
DEFAULT_SCALE_STEP: Final = 1e-4
DEFAULT_TRANSLATION_STEP_CM: Final = 0.01

# --- bandwidth accounting channels ---------------------------------------------------------------

CHANNEL_SNAPSHOT: Final = "snapshot"
CHANNEL_GEOMETRY: Final = "geometry"
CHANNEL_REM: Final = "rem"
CHANNEL_CONTROL: Final = "control"
CHANNELS: Final = (CHANNEL_SNAPSHOT, CHANNEL_GEOMETRY, CHANNEL_REM, CHANNEL_CONTROL)

# --- transport timings and queue sizes -----------------------------------------------------------

#: The sender publishes a Heartbeat when it has published nothing for this long.
HEARTBEAT_INTERVAL_S: Final = 1.0
#: A receiver declares the peer lost after this long without a well-formed packet.
PEER_TIMEOUT_S: Final = 3.0
#: During the handshake the receiver re-sends its probe this often until its SUB socket
#: receives a published packet.
PROBE_INTERVAL_MS: Final = 100
#: Send and receive high-water marks, in messages, for every socket (about 5 min at 30 fps).
HWM: Final = 10_000
