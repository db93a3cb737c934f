"""A cut to another scene: the sender sees it and starts a session from it; the receiver goes on
with that session in the same call and never draws the old face over the new scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facewire.loopback import Loopback
from facewire.models.mesh import load_canonical
from facewire.sender.capture import CapturedFrame
from facewire.sender.encoder import FaceEncoder
from facewire.sender.scene_cut import (
    BETTER_AFTER_S,
    BETTER_FRAMES,
    BETTER_SHARE,
    DRIFT_S,
    FRONTAL_SHARE,
    OPEN_EYES,
    BetterView,
    SceneCut,
    another_face,
    eye_openness,
    face_box,
)
from facewire.sender.session import _SceneStart
from facewire.sender.snapshot_draft import is_draft
from tests.cut_clip import (
    AFTER,
    BEFORE,
    FIXTURE,
    bundled,
    demo_call,
    off,
    other_scene,
    slide,
    spliced,
)


def test_a_talking_head_is_one_scene_and_a_splice_is_a_cut() -> None:
    frames = spliced()
    scene = SceneCut()
    cuts = [i for i, image in enumerate(frames) if scene.changed(image)]
    assert cuts == [BEFORE]


def test_a_phone_held_upright_sees_the_same_cut() -> None:
    # Its thumbnails are turned the way its frames are (a whole factor of 720x1280).
    frames = [cv2.rotate(image, cv2.ROTATE_90_CLOCKWISE) for image in spliced()]
    scene = SceneCut()
    cuts = [i for i, image in enumerate(frames) if scene.changed(image)]
    assert cuts == [BEFORE]
    assert scene.last is not None and scene.last[1].shape == (16, 12)  # upright too


def test_another_face_is_one_that_jumps_or_resizes_in_a_frame() -> None:
    face = (100.0, 100.0, 50.0)
    assert not another_face(face, (120.0, 95.0, 52.0))  # a head moving fast
    assert another_face(face, (180.0, 100.0, 50.0))  # a face width and more away
    assert another_face(face, (100.0, 100.0, 90.0))  # nearly twice as wide


def _call(frames: list[np.ndarray], scenes: bool) -> tuple[list[np.ndarray], int]:
    height, width = frames[0].shape[:2]
    encoder = FaceEncoder(width, height, 30.0, scenes=scenes)
    pictures = []
    with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as both:
        for i, image in enumerate(frames):
            both.step(CapturedFrame(i, image, i * 33_333))
            pictures.append(both.picture())
        return pictures, both.scenes


def test_after_a_cut_the_receiver_draws_the_new_scene() -> None:
    frames = spliced()
    pictures, scenes = _call(frames, scenes=True)
    still, floated = _call(frames, scenes=False)
    assert scenes == 1
    # The new scene from its first frame on: the snapshot is made of it.
    for i in (BEFORE, BEFORE + AFTER // 2, len(frames) - 1):
        assert off(pictures[i], frames[i]) < 12.0, i
    # Without it, the old scene stays, with the new face pasted over it.
    assert off(still[-1], frames[-1]) > 3 * off(pictures[-1], frames[-1])


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[np.ndarray], list, dict]:
    """``facewire demo`` (two processes, ZeroMQ on loopback, EGL) on the spliced clip."""
    return demo_call(tmp_path_factory.mktemp("scene"), spliced())


def test_a_call_goes_on_across_a_cut_in_a_new_session(demo: tuple) -> None:
    inputs, rebuilt, stats = demo
    assert stats["ended_by"] == "bye" and stats["malformed"] == 0
    assert stats["scenes"] == 1 and len(stats["scene_first_s"]) == 1
    read = stats["frames_in"] + stats["frames_dropped"]  # sent, or left out by a busy machine
    assert stats["frames_out"] == read == len(inputs) == len(rebuilt)
    assert off(rebuilt[-1], inputs[-1]) < 12.0


def test_until_the_new_scene_comes_the_old_picture_stays(demo: tuple) -> None:
    """Every picture after the cut is the old scene held, or the new scene: nowhere the old
    scene with the new face on it (it would be closer to neither)."""
    inputs, rebuilt, _ = demo
    old = rebuilt[BEFORE - 1]
    new = [off(rebuilt[i], inputs[i]) < 12.0 for i in range(BEFORE, len(inputs))]
    held = [off(rebuilt[i], old) < 2.0 for i in range(BEFORE, len(inputs))]
    assert all(a or b for a, b in zip(new, held, strict=True))
    first = new.index(True)
    assert all(new[first:])


def test_a_black_frame_is_no_new_scene() -> None:
    """A frame that shows nothing (a flash, a hand over the lens) and then the same scene
    again: no session is started, the call goes on with its own."""
    frames = bundled(40)
    frames[20] = np.zeros_like(frames[20])
    pictures, scenes = _call(frames, scenes=True)
    assert scenes == 0
    assert off(pictures[-1], frames[-1]) < 12.0


def test_a_face_that_comes_back_after_the_tracker_strayed_is_no_new_scene() -> None:
    """A second face in view (a child beside her mother) and the first one hidden for longer
    than the tracker waits for it (a hand over it; the mother bowing her head): the tracker
    takes the second face, which jumps. When the first face is back where it was, the call
    goes on in its session: started there, the new session had been made from the moment of
    the jump (mother-daughter: her hair for a texture, and her face drawn from it)."""
    second = cv2.resize(cv2.imread(str(FIXTURE))[:300, 80:340], (156, 180))
    frames = bundled(50)
    for i, image in enumerate(frames):
        image[300:480, :156] = second
        if 20 <= i < 38:
            cv2.ellipse(image, (330, 230), (110, 150), 0, 0, 360, (90, 120, 160), -1)
    encoder = FaceEncoder(640, 480, 30.0, scenes=True)
    with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as both:
        strayed = False
        for i, image in enumerate(frames):
            both.step(CapturedFrame(i, image, i * 33_333))
            strayed |= encoder._new_scene
            if i == 40:
                assert off(both.picture(), image) < 6.0
        scenes = both.scenes
    assert strayed  # the tracker did take the second face
    assert scenes == 0
    assert abs(face_box(encoder.points)[0] - 320) < 20  # her face, not the other


def test_a_face_in_profile_shows_less_of_itself_than_one_looking_into_the_camera() -> None:
    mesh = load_canonical()
    shares = []
    for yaw in (0.0, 30.0, 60.0):
        # Model space (y up, z out of the face) to image space (y down, z away).
        turned = (
            np.diag([1.0, -1.0, -1.0]) @ Rotation.from_euler("y", yaw, degrees=True).as_matrix()
        )
        shares.append(mesh.facing_share(mesh.vertices @ turned.T))
    assert shares[0] > FRONTAL_SHARE > shares[1] > shares[2] + BETTER_SHARE
    assert shares[2] < 0.65


def test_a_better_view_is_one_held_and_comes_once() -> None:
    fps = 30.0
    wait = round(BETTER_AFTER_S * fps)
    box = (100.0, 100.0, 60.0)
    view = BetterView(0.6, box, fps)
    # Frontal from the start: not before the session is BETTER_AFTER_S old.
    assert not any(view.seen(0.87, box) for _ in range(wait - 1))
    view = BetterView(0.6, box, fps)
    for _ in range(wait):
        view.seen(0.6, box)
    # A turn that passes through frontal is no view to keep.
    assert not any(view.seen(s, box) for s in [0.87] * (BETTER_FRAMES - 1) + [0.7])
    assert [view.seen(0.87, box) for _ in range(BETTER_FRAMES)][-1]
    assert not any(view.seen(0.87, box) for _ in range(3 * BETTER_FRAMES))  # once
    # A snapshot already near frontal: nothing is much better.
    view = BetterView(0.84, box, fps)
    assert not any(view.seen(0.92, box) for _ in range(wait + 3 * BETTER_FRAMES))


def test_a_face_grown_past_what_its_texture_is_sharp_for_is_a_better_view() -> None:
    """A person who leans in: the face wider than the snapshot's texture holds (at least
    1.25 texels a pixel) for BETTER_FRAMES frames. vtc1nw leaning in from half its size: face
    SSIM 0.708 -> 0.794 with the new session (bench_body.py --motion closer)."""
    fps = 30.0
    wait = round(BETTER_AFTER_S * fps)
    view = BetterView(0.86, (100.0, 100.0, 54.0), fps, sharp_up_to=102.4)  # 128 texels
    assert not any(view.seen(0.86, (100.0, 100.0, 100.0)) for _ in range(wait + BETTER_FRAMES))
    assert [view.seen(0.86, (100.0, 100.0, 110.0)) for _ in range(BETTER_FRAMES)][-1]
    # A texture sized at the least the face needs: past it as the head comes a little closer,
    # and no better for that.
    view = BetterView(0.86, (100.0, 100.0, 200.0), fps, sharp_up_to=204.8)
    assert not any(view.seen(0.86, (100.0, 100.0, 223.0)) for _ in range(wait + BETTER_FRAMES))
    # The largest texture there is: no size is past it.
    view = BetterView(0.86, (100.0, 100.0, 54.0), fps)
    assert not any(view.seen(0.86, (100.0, 100.0, 2000.0)) for _ in range(wait + BETTER_FRAMES))


def test_a_face_far_from_where_its_snapshot_saw_it_is_a_better_view() -> None:
    """A person who walked across the room (bowing): a face width from the snapshot's place,
    held. Talking heads move at most 0.6 of one."""
    fps = 30.0
    wait = round(BETTER_AFTER_S * fps)
    view = BetterView(0.86, (100.0, 100.0, 60.0), fps)
    assert not any(view.seen(0.86, (136.0, 100.0, 60.0)) for _ in range(wait + BETTER_FRAMES))
    assert [view.seen(0.86, (100.0, 165.0, 60.0)) for _ in range(BETTER_FRAMES)][-1]


def test_eyes_opened_where_the_snapshot_had_them_shut_are_a_better_view() -> None:
    """A call begun looking down (sign_irene: lids 0.10 of the eye's width, then 0.34 once
    she looks up): face SSIM over frames 40-200 0.583 -> 0.642 with the new session."""
    fps = 30.0
    wait = round(BETTER_AFTER_S * fps)
    box = (100.0, 100.0, 60.0)
    view = BetterView(0.86, box, fps, eyes=0.1)
    assert not any(view.seen(0.86, box, 0.34) for _ in range(wait - 1))
    assert any(view.seen(0.86, box, 0.34) for _ in range(BETTER_FRAMES))
    assert not any(view.seen(0.86, box, 0.34) for _ in range(3 * BETTER_FRAMES))  # once
    # A blink's lids (or a squint) are no open eyes; nor are eyes a little more open than the
    # snapshot's, nor open eyes in a face turned away.
    for snapshot, now, share in ((0.1, 0.15, 0.86), (0.25, 0.4, 0.86), (0.1, 0.34, 0.7)):
        view = BetterView(0.86, box, fps, eyes=snapshot)
        assert not any(view.seen(share, box, now) for _ in range(wait + 3 * BETTER_FRAMES))
    # Without the eyes looked at (markers), nothing changes.
    view = BetterView(0.86, box, fps)
    assert not any(view.seen(0.86, box, 0.34) for _ in range(wait + 3 * BETTER_FRAMES))


def test_open_eyes_measure_open_and_a_blink_shut() -> None:
    frames = bundled(150)
    from facewire.sender.landmarks import LandmarkTracker

    tracker = LandmarkTracker()
    opened = [eye_openness(tracker.track(frames[i]).points) for i in (0, 60, 120)]  # type: ignore[union-attr]
    blink = eye_openness(tracker.track(frames[140]).points)  # type: ignore[union-attr]
    assert min(opened) > 2 * OPEN_EYES * 0.9
    assert blink < 0.6 * min(opened)


def test_the_face_seen_far_better_than_in_its_snapshot_begins_a_new_session() -> None:
    """A snapshot taken in profile (here: said to be) has no texture for the face's far side,
    one taken looking down (said to be: eyes shut) has its lids; once the face has looked
    into the camera for BETTER_FRAMES frames, the call goes on in a session made from that
    view (mad900: face SSIM 0.527 -> 0.635)."""
    frames = bundled(90)
    apart = []
    for worse in ("profile", "eyes shut", None):
        encoder = FaceEncoder(640, 480, 30.0, scenes=True)
        with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as both:
            assert encoder.better_view is not None
            if worse == "profile":
                encoder.better_view.share = 0.6  # as a face in profile shows
            elif worse == "eyes shut":
                encoder.better_view.eyes = 0.1  # as a face looking down shows
            pictures = []
            for i, image in enumerate(frames):
                both.step(CapturedFrame(i, image, i * 33_333))
                pictures.append(both.picture())
            assert both.scenes == (0 if worse is None else 1), worse
            apart.append([off(p, f) for p, f in zip(pictures[60:], frames[60:], strict=True)])
            # The new session's snapshot saw the face as it is: no other is due.
            assert encoder.better_view.share > FRONTAL_SHARE
            assert encoder.better_view.eyes is not None and encoder.better_view.eyes > OPEN_EYES
    # The call goes on in the new session, drawn frame by frame as the old one was.
    assert max(np.mean(apart[0]), np.mean(apart[1])) < np.mean(apart[2]) + 1.0


def test_a_new_scenes_versions_for_a_thin_link_are_made_with_it_off_the_calls_loop() -> None:
    """The draft and the sharper versions of a new scene's snapshot (0.1-0.25 s of WebP
    encoding at 640x480 and 1280x720) are made on the scene's own thread, with the snapshot,
    so the call's loop serves all three at once and never waits for them."""
    encoder = FaceEncoder(640, 480, 30.0)
    first = bundled(1)[0]
    encoder.start(CapturedFrame(0, first, 0))
    scene = _SceneStart(encoder, CapturedFrame(1, other_scene(1)[0], 33_333))
    assert scene.done(wait=True)
    assert scene.snapshot is not None
    assert scene.draft is not None and is_draft(scene.draft)
    assert scene.draft.session_id == scene.snapshot.session_id
    assert scene.sharper[-1] is scene.snapshot  # 640x480's fits in a datagram message


def test_a_dissolve_is_a_new_scene_once_it_has_gone_far() -> None:
    """A second's dissolve from the bundled clip to a slide: no two frames in a row are a cut,
    but once the frame has been far from the session's snapshot frame for DRIFT_S it is
    another scene, once; the scene left is the snapshot frame's. (Claire dissolving into Miss
    America: her face drawn over Claire's studio, frame SSIM 0.34 after it.) The bundled
    clip itself never drifts that far."""
    head, other = bundled(90), slide(60)
    fade = [cv2.addWeighted(head[60 + k], 1 - k / 30, other[k], k / 30, 0.0) for k in range(1, 30)]
    frames = head[:60] + fade + other[30:]
    scene = SceneCut(30.0)
    scene.begin(frames[0])
    changed, left_like_now = [], []
    for i, image in enumerate(frames):
        if scene.changed(image):
            changed.append(i)
            assert scene.before is not None
            left_like_now.append(scene.like(scene.before))
    assert len(changed) == 1 and 60 + 15 <= changed[0] <= 60 + 29 + round(DRIFT_S * 30)
    assert left_like_now == [False]  # else the encoder takes the scene left for back
    still = SceneCut(30.0)
    still.begin(head[0])
    assert not any(still.changed(image) for image in bundled(300))
