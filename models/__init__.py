"""The face model and its rig, shared by sender and receiver.

Pure numpy/scipy: importing this package needs no camera, no OpenGL and no network.

Coordinate frames used across facewire:

- model space: the canonical mesh's frame, centimetres, x towards the face's left
  (image right for a frontal face), y up, z out of the face towards the viewer.
- image space: pixels of the input frame, x right, y down, z away from the camera
  (same scale as x). Landmarks and rendered vertices live here.
- a ``Pose`` (models.pose) is the similarity that maps model space to image space:
  ``image = scale * R @ model + t``; a frontal, upright face has R = diag(1, -1, -1).
"""
