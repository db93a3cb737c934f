"""The body's own motion as a protocol channel: how the torso and shoulders moved.

The receiver carries the hair, ears and neck along with the face (models/surround.py), but
the rest of the person (shoulders, chest, arms) comes from the snapshot frame. A person
leaning back from the camera shrinks as a whole, one moving sideways shifts as a whole; with
the body held where the snapshot frame had it, the head shrank over shoulders as big as
ever, or slid away from them. The body's motion on screen is a similarity (shift, roll and
zoom of the silhouette below the head), four values a frame and most frames none at all.

On the wire it is the ``body`` channel, coded as the camera's motion is (models/camera.py):
the displacement in pixels of the frame's top-left and bottom-right corners under the
similarity. It is the body's motion relative to the scene's, applied before the camera's, so
a person sitting still in front of a shaking camera sends zeros: the person's pixels go
from the snapshot frame to ``camera @ body`` in this frame.
"""

from __future__ import annotations

from facewire.models.camera import CAMERA_SIZE, camera_step

BODY = "body"
BODY_SIZE = CAMERA_SIZE


#: The body's error budget, in units of the face's: the silhouette is seen to a pixel or so,
#: not to the face's quarter pixel, and a person's sway is most of what would be sent.
BUDGET_PER_FACE = 4.0


def body_step(budget_px: float) -> float:
    """The ``body`` channel's step, pixels, for a face whose error budget is ``budget_px``
    (no pixel of the frame moves further than twice a value's error, models/camera.py: 1 px
    at the default 0.25)."""
    return camera_step(BUDGET_PER_FACE * budget_px)
