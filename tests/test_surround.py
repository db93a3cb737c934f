"""The head's surroundings (hair, ears, neck) move with the face; the background stays."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from imaging import save

from facewire.models.surround import FADE, HEAD_REACH, STILL_REACH, SurroundWarp, frame_border

H, W = 360, 480
FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def outline(centre=(240.0, 170.0), radius=(50.0, 65.0), k=36) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    return np.c_[centre[0] + radius[0] * np.cos(t), centre[1] + radius[1] * np.sin(t)]


def noise_image() -> np.ndarray:
    rng = np.random.default_rng(3)
    small = rng.integers(0, 256, (H // 8, W // 8, 3), dtype=np.uint8)
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)


def test_a_still_face_leaves_the_frame_untouched() -> None:
    image = noise_image()
    warp = SurroundWarp(image, outline())
    assert np.array_equal(warp.warp(outline()), image)


def test_the_head_ring_moves_with_the_face_and_the_scene_stays() -> None:
    o = outline()
    warp = SurroundWarp(noise_image(), o)
    shift = np.array([15.0, -8.0])
    map_x, map_y = warp.source_map(o + shift)

    def source(p: np.ndarray) -> np.ndarray:
        x, y = np.round(p).astype(int)
        return np.array([map_x[y, x], map_y[y, x]])

    centre = o.mean(0)
    # Hair and ears (between the outline and the head ring, above the mouth) came along, within
    # a fifth of the move (the spline bends a little between the rings).
    for q in (centre + 1.3 * (o - centre))[[27, 24, 30, 0, 18]]:  # top, upper sides, sides
        assert np.allclose(source(q + shift), q, atol=3.0), (q, source(q + shift))
    # Beyond the still ring the background did not move.
    far = centre + (STILL_REACH * FADE + 0.1) * (o - centre)
    for q in far[(far[:, 0] > 0) & (far[:, 0] < W - 1) & (far[:, 1] > 0) & (far[:, 1] < H - 1)]:
        assert np.allclose(source(q), q, atol=0.75), q
    assert HEAD_REACH < STILL_REACH


def test_the_neck_follows_less_than_the_head() -> None:
    o = outline()
    warp = SurroundWarp(noise_image(), o)
    map_x, _ = warp.source_map(o + [20.0, 0.0])
    centre = o.mean(0)
    top = (centre + 1.3 * (o[27] - centre)).round().astype(int)  # above the forehead
    chin = (centre + 1.3 * (o[9] - centre)).round().astype(int)  # under the chin
    moved_top = top[0] + 20 - map_x[top[1], top[0] + 20]
    moved_chin = chin[0] + 20 - map_x[chin[1], chin[0] + 20]
    assert moved_top == pytest.approx(20.0, abs=3.0)
    assert 5.0 < moved_chin < moved_top - 3.0


def test_a_head_turning_away_carries_its_hair_round_without_a_roll() -> None:
    """The outline as a head has it, in 3D: an oval whose sides lie deeper than its middle
    (image space, z away from the camera). Turned 25 degrees about the vertical axis through
    the head's centre, the outline narrows and its far side slides in; the head ring turns
    with it: no point of it rises or sinks (a turn is no roll), and it narrows as the
    outline does (a turn is no shrink). A 2D similarity fitted to the narrowed outline took
    it for a shrink and a roll, and moved the hair above the forehead by 1.6 px here."""
    flat = outline()
    centre = flat.mean(0)
    across = (flat[:, 0] - centre[0]) / 50.0
    depth = 40.0 * (1.0 - np.sqrt(np.clip(1.0 - across**2, 0.0, 1.0)))  # sides 40 px deeper
    then = np.c_[flat, depth]
    pivot = np.array([centre[0], centre[1], 60.0])  # the head turns about its own centre
    a = np.deg2rad(25.0)
    yaw = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    now = (then - pivot) @ yaw.T + pivot
    warp = SurroundWarp(noise_image(), then)
    moved, before = warp.controls(now)
    k = len(flat)
    head_now, head_then = moved[k : 2 * k], before[k : 2 * k]
    above = head_then[:, 1] < centre[1]  # above the mouth: the ring follows the head fully
    assert np.abs(head_now[above, 1] - head_then[above, 1]).max() < 0.5
    narrowing = np.ptp(now[:, 0]) / np.ptp(flat[:, 0])
    assert np.ptp(head_now[above, 0]) / np.ptp(head_then[above, 0]) == pytest.approx(
        narrowing, abs=0.05
    )


def test_camera_motion_moves_the_whole_scene() -> None:
    image = noise_image()
    o = outline()
    warp = SurroundWarp(image, o)
    camera = np.array([[1.0, 0.0, 6.0], [0.0, 1.0, -4.0], [0.0, 0.0, 1.0]])
    got = warp.warp(o + [6.0, -4.0], camera)
    expected = cv2.warpAffine(image, camera[:2], (W, H), borderMode=cv2.BORDER_REPLICATE)
    inner = np.s_[8:-8, 10:-10]
    assert np.abs(got[inner].astype(int) - expected[inner]).mean() < 1.0
    # What comes in at the frame's top (the head's reach spans the frame's height) is the frame
    # reflected: without a person layer the padding is warped as it is (a layer's weight, 0
    # there, must not black it out).
    down = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 5.0], [0.0, 0.0, 1.0]])
    got = warp.warp(o + [0.0, 5.0], down)
    reflected = cv2.warpAffine(image, down[:2], (W, H), borderMode=cv2.BORDER_REFLECT_101)
    top = np.s_[:5, 100:380]
    assert np.abs(got[top].astype(int) - reflected[top]).mean() < 1.0


def test_an_outline_of_another_size_is_refused() -> None:
    warp = SurroundWarp(noise_image(), outline())
    with pytest.raises(ValueError, match=r"expected outline of 36 points, got \(20, 2\)"):
        warp.warp(outline(k=20))


def person_scene() -> tuple[np.ndarray, np.ndarray]:
    """A striped scene (straight lines a person would see bend) with a red person on it:
    head over the outline, shoulders to the bottom. Returns the image and the person mask."""
    image = np.full((H, W, 3), 200, np.uint8)
    image[::12] = 40  # horizontal stripes
    person = np.zeros((H, W), np.uint8)
    cv2.ellipse(person, (240, 170), (58, 75), 0, 0, 360, 1, -1)
    cv2.rectangle(person, (150, 240), (330, H - 1), 1, -1)
    image[person.astype(bool)] = (30, 30, 220)
    return image, person.astype(np.float32)


def test_with_a_person_mask_a_still_face_leaves_the_frame_untouched() -> None:
    image, person = person_scene()
    warp = SurroundWarp(image, outline(), person)
    assert np.array_equal(warp.warp(outline()), image)


def test_with_a_person_mask_the_scene_stays_straight_and_no_old_person_shows() -> None:
    image, person = person_scene()
    o, shift = outline(), np.array([40.0, -10.0])
    layered = SurroundWarp(image, o, person).warp(o + shift)
    whole = SurroundWarp(image, o).warp(o + shift)
    # The head moved right: the red head sits where the face now is.
    centre = np.round(o.mean(0) + shift).astype(int)
    assert layered[centre[1], centre[0], 2] > 180
    # Beside the head, out of the person, the stripes have not moved (the whole-frame warp
    # bends them there).
    beside = np.zeros((H, W), bool)
    beside[60:230, 365:395] = True
    assert np.array_equal(layered[beside], image[beside])
    assert np.abs(whole[beside].astype(int) - image[beside]).mean() > 5.0
    # Left of the old head, where the person was and is no more: scene, not red person.
    left = np.zeros((H, W), bool)
    left[130:200, 185:200] = True
    red = (layered[..., 2].astype(int) - layered[..., 1]) > 100
    assert red[left].mean() < 0.05


def test_the_scene_a_moving_head_uncovers_is_a_smooth_guess_not_streaks() -> None:
    """Book spines behind a person (deadline's shelves): where the head was and is no more,
    the receiver can only guess the scene. Painted in along rays (Telea), the spines'
    colours came out as a star of streaks beside the head, seen as soon as it moved; the
    guess is a smooth blend of what surrounds the person."""
    rng = np.random.default_rng(5)
    spines = rng.integers(20, 240, (1, W // 10, 3), dtype=np.uint8)
    image = cv2.resize(spines, (W, H), interpolation=cv2.INTER_NEAREST)
    person = np.zeros((H, W), np.uint8)
    cv2.ellipse(person, (240, 170), (58, 75), 0, 0, 360, 1, -1)
    cv2.rectangle(person, (150, 240), (330, H - 1), 1, -1)
    image[person.astype(bool)] = (30, 30, 220)
    # The scene within 15 px round the person: what the guess is made of.
    ring = cv2.dilate(person, np.ones((31, 31), np.uint8)).astype(bool) & (person == 0)
    o = outline()
    out = SurroundWarp(image, o, person.astype(np.float32)).warp(o + [60.0, 0.0])
    save("uncovered_scene.png", np.hstack([image, out]))
    # The old head's left half, left of the new head: no red head, and colours that vary
    # little across it (Telea's blotches and rays: 25 grey levels; the spines: 58-66).
    uncovered = out[140:200, 196:232].reshape(-1, 3).astype(np.float64)
    assert (np.abs(uncovered - (30, 30, 220)).sum(axis=1) > 60).all()
    spread = uncovered.std(axis=0).max()
    assert spread < 0.15 * image[:100].reshape(-1, 3).std(axis=0).min(), spread
    # Of the colours round it (a black or grey patch there is no guess of the scene).
    off = np.abs(uncovered.mean(axis=0) - image[ring].mean(axis=0)).max()
    assert off < 25.0, off


def test_the_scene_just_beside_a_moving_head_stays_where_it_is() -> None:
    """The person layer takes in a pixel or two of the scene round the person's mask (the
    segmentation's edge is soft) and carries it with the head. Reaching 5 px and fading over
    5 more at this size, it dragged the shelves beside deadline's head along (frame SSIM
    0.804 against 0.821): 8-11 px beside the moved head the scene is the snapshot's, exactly."""
    rng = np.random.default_rng(6)
    spines = rng.integers(20, 240, (1, W // 6, 3), dtype=np.uint8)
    image = cv2.resize(spines, (W, H), interpolation=cv2.INTER_NEAREST)
    person = np.zeros((H, W), np.uint8)
    cv2.ellipse(person, (240, 170), (58, 75), 0, 0, 360, 1, -1)
    image[person.astype(bool)] = (30, 30, 220)
    o = outline()
    out = SurroundWarp(image, o, person.astype(np.float32)).warp(o + [12.0, 0.0])
    beside = np.s_[150:190, 240 + 58 + 12 + 8 : 240 + 58 + 12 + 12]
    assert np.array_equal(out[beside], image[beside])


def test_a_box_of_the_warp_is_that_part_of_the_whole_warp() -> None:
    """The sender rebuilds only the receiver's surroundings around the face (sender/edge.py):
    the same pixels as the whole frame's warp has there."""
    image, person = person_scene()
    warp = SurroundWarp(image, outline(), person)
    now = outline() + [12.0, -5.0]
    camera = np.array([[1.0, -0.01, 3.0], [0.01, 1.0, -2.0], [0.0, 0.0, 1.0]])
    whole = warp.warp(now, camera)
    for x0, y0, x1, y1 in [(0, 0, W, H), (123, 45, 401, 299), (0, 17, 100, H), (400, 300, W, H)]:
        part = warp.warp(now, camera, (x0, y0, x1, y1))
        assert part.shape == (y1 - y0, x1 - x0, 3)
        # Within a level: the maps' interpolation starts from other nodes.
        assert np.abs(part.astype(int) - whole[y0:y1, x0:x1]).max() <= 1


def test_person_mask_finds_a_real_face() -> None:
    from facewire.models.person import person_mask

    face = cv2.imread(str(FIXTURE))
    canvas = cv2.resize(noise_image(), (960, 540))
    canvas[60:480, 270:690] = face
    mask = person_mask(canvas)
    assert mask.shape == (540, 960) and mask.dtype == np.float32
    assert mask[200:350, 400:560].mean() > 0.8  # the face
    assert mask[:, :150].mean() < 0.1 and mask[:, -150:].mean() < 0.1  # noise, far out


# --- in the call, on a real photographed face ----------------------------------------------------


def _frame(face: np.ndarray, angle: float, shift: tuple[float, float]) -> np.ndarray:
    m = cv2.getRotationMatrix2D((210, 210), angle, 0.8)
    m[:, 2] += (W / 2 - 210 + shift[0], H / 2 - 210 + shift[1])
    return cv2.warpAffine(face, m, (W, H), borderMode=cv2.BORDER_REFLECT)


def test_hair_follows_the_head_and_no_old_face_shows(tmp_path: Path) -> None:
    from facewire.loopback import Loopback
    from facewire.models.mesh import load_canonical
    from facewire.sender.capture import CapturedFrame
    from facewire.sender.encoder import FaceEncoder
    from facewire.sender.landmarks import LandmarkTracker
    from facewire.sender.texture import face_hull_mask

    face = cv2.imread(str(FIXTURE))
    first, moved = _frame(face, 0.0, (0.0, 0.0)), _frame(face, 7.0, (26.0, 10.0))
    encoder = FaceEncoder(W, H, 30.0)
    with Loopback(encoder, CapturedFrame(0, first, 0), seq=None) as both:
        for i, image in enumerate([first, moved, moved, moved], start=0):
            both.step(CapturedFrame(i, image, i * 33_333))
        rebuilt = both.picture()
    cv2.imwrite(str(tmp_path / "rebuilt.png"), np.hstack([moved, rebuilt]))
    tracker, triangles = LandmarkTracker(), load_canonical().triangles
    was, now = (
        face_hull_mask((H, W), tracker.track(img).points, triangles)  # type: ignore[union-attr]
        for img in (first, moved)
    )
    tracker.reset()
    points = tracker.track(moved).points  # type: ignore[union-attr]
    centre = points[:, :2].mean(0)
    ring = cv2.dilate(now.astype(np.uint8), np.ones((41, 41), np.uint8)).astype(bool) & ~now
    ring[int(centre[1]) :] = False  # above the eyes: hair and forehead edge

    def diff(a: np.ndarray, b: np.ndarray, where: np.ndarray) -> float:
        return float(np.abs(a.astype(int) - b.astype(int))[where].mean())

    # The hair moved with the head: far closer to the moved picture than the still one is.
    assert diff(rebuilt, moved, ring) < 0.5 * diff(first, moved, ring)
    # Where the face was and is no longer, the moved scene shows, not a ghost of the old face.
    uncovered = was & ~now
    assert uncovered.sum() > 500
    assert diff(rebuilt, moved, uncovered) < 0.5 * diff(first, moved, uncovered)


def leaning_scene(top: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stripes with a red person whose hair reaches row ``top``: the image, the person mask
    and the face outline (the hair's crown 60 px above the outline's top)."""
    image = np.full((H, W, 3), 200, np.uint8)
    image[::12] = 40
    person = np.zeros((H, W), np.uint8)
    face_top = top + 60
    centre = (240, face_top + 65)
    cv2.ellipse(person, centre, (75, 125), 0, 0, 360, 1, -1)
    cv2.rectangle(person, (140, centre[1] + 90), (340, H - 1), 1, -1)
    image[person.astype(bool)] = (30, 30, 220)
    return image, person.astype(np.float32), outline(centre=centre)


def red(image: np.ndarray) -> np.ndarray:
    return (image[..., 2].astype(int) - image[..., 1]) > 100


def test_a_head_leaning_back_takes_its_hair_along_and_leaves_no_streak_above() -> None:
    """The person leans back: the face shrinks to 0.7 about its centre and sinks 20 px. The
    hair shrinks with it; above the crown the scene shows, not hair drawn out towards a still
    ring (the streak from the top of the head towards the frame's top edge)."""
    image, person, o = leaning_scene(top=60)
    centre = o.mean(0)
    now = centre + [0.0, 20.0] + 0.7 * (o - centre)
    out = SurroundWarp(image, o, person).warp(now)
    crown = int(centre[1] + 20 - 0.7 * (centre[1] - 60))  # the hair's top, carried
    above = np.s_[: crown - 4, 200:280]
    assert red(image)[above].mean() > 0.4  # there was hair there in the snapshot frame
    assert red(out)[above].mean() < 0.02
    assert red(out)[crown + 4 : crown + 30, 225:255].mean() > 0.95  # and the hair is there


def test_the_person_layer_ends_at_the_frame_edge() -> None:
    """Hair cut by the frame's top edge, the head sinking: what the warp would take from
    above the snapshot frame is not the person's (the reflected border mirrored the hair in,
    a streak down to the head); the scene shows there."""
    image, person, o = leaning_scene(top=0)
    now = o + [0.0, 30.0]
    out = SurroundWarp(image, o, person).warp(now)
    assert red(out)[:26, 200:280].mean() < 0.05
    assert red(out)[34:60, 225:255].mean() > 0.95


def test_the_body_moves_the_person_below_the_head_and_the_scene_stays() -> None:
    """The person leans back: head and body shrink to 0.8 about the face's centre. The body
    shrinks with the body's similarity (beyond the head's reach too), still reaching the
    frame's bottom edge; the stripes beside it stay where they were."""
    image, person = person_scene()
    o = outline()
    centre = o.mean(0)
    body = np.array([[0.8, 0.0, 0.2 * centre[0]], [0.0, 0.8, 0.2 * centre[1]], [0.0, 0.0, 1.0]])
    now = centre + 0.8 * (o - centre)
    out = SurroundWarp(image, o, person).warp(now, body=body)
    still = SurroundWarp(image, o, person).warp(now)
    # The body was 150..330 wide: now 168..312 (0.8 about x = 240).
    row = np.s_[290:340]
    assert red(out)[row, 176:304].mean() > 0.95
    assert red(out)[row, 150:162].mean() < 0.05 and red(out)[row, 318:330].mean() < 0.05
    assert red(still)[row, 150:162].mean() > 0.95  # without it the body stays as big
    # It goes on past the bottom edge, which it reached in the snapshot frame.
    assert red(out)[H - 12 :, 176:304].mean() > 0.95
    # Beside the body, beyond the head's reach, the scene has not moved.
    beside = np.s_[250:H, 360:470]
    assert np.abs(out[beside].astype(int) - image[beside]).mean() < 1.0


def test_a_body_moving_with_the_camera_is_the_camera_alone() -> None:
    image, person = person_scene()
    o = outline()
    warp = SurroundWarp(image, o, person)
    camera = np.array([[1.0, 0.0, 6.0], [0.0, 1.0, -4.0], [0.0, 0.0, 1.0]])
    assert np.array_equal(
        warp.warp(o + [6.0, -4.0], camera, body=camera), warp.warp(o + [6.0, -4.0], camera)
    )


def test_a_face_in_a_large_frame_is_warped_as_in_a_small_one_and_the_rest_is_the_frame() -> None:
    # Only the head's reach is warped pixel by pixel: the same small frame with its edges
    # repeated out to 1280x720 (on the spline's grid) warps as the small one does, and beyond
    # the reach the large frame is the snapshot frame itself.
    small = noise_image()
    top, left = 176, 400
    large = cv2.copyMakeBorder(
        small, top, 720 - H - top, left, 1280 - W - left, cv2.BORDER_REPLICATE
    )
    o, move = outline(), np.array([9.0, -6.0])
    want = SurroundWarp(small, o).warp(o + move)
    got = SurroundWarp(large, o + [left, top]).warp(o + [left, top] + move)
    inner = np.s_[top + 40 : top + H - 40, left + 40 : left + W - 40]
    assert np.abs(got[inner].astype(int) - want[40:-40, 40:-40]).max() <= 1
    assert np.abs(got[inner].astype(int) - large[inner]).max() > 50  # the head did move
    far = np.ones(large.shape[:2], bool)
    far[top - 40 : top + H + 40, left - 40 : left + W + 40] = False
    assert np.array_equal(got[far], large[far])


def test_a_camera_that_moves_again_moves_the_picture_again() -> None:
    # The scene moved by the camera is kept while the camera stays: a frame after the camera
    # moved on (or back) is what a fresh warp draws for it, never the last frame's scene.
    image, person = person_scene()
    warp = SurroundWarp(image, outline(), person)
    now = outline() + [5.0, 2.0]
    cameras = [np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]]) for dx, dy in
               [(4.0, -2.0), (4.0, -2.0), (-3.0, 5.0), (4.0, -2.0), (0.0, 0.0)]]  # fmt: skip
    for camera in cameras:
        want = SurroundWarp(image, outline(), person).warp(now, camera)
        assert np.array_equal(warp.warp(now, camera), want)
        part = warp.warp(now, camera, (10, 20, 300, 250)).astype(int)
        assert np.abs(part - want[20:250, 10:300]).max() <= 1  # as any box (above)


def test_a_body_that_moves_again_moves_the_person_again() -> None:
    # The person moved by the body over the scene moved by the camera is kept while both
    # stay: a frame after either moved on (or back) is what a fresh warp draws for it.
    image, person = person_scene()
    warp = SurroundWarp(image, outline(), person)
    now = outline() + [5.0, 2.0]

    def shift(dx: float, dy: float) -> np.ndarray:
        return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])

    still, panned, leaned, other = np.eye(3), shift(4.0, -2.0), shift(3.0, 4.0), shift(-2.0, 6.0)
    moves = [(still, leaned), (still, leaned), (panned, leaned), (panned, other), (still, still),
             (still, leaned)]  # fmt: skip
    for camera, body in moves:
        want = SurroundWarp(image, outline(), person).warp(now, camera, body=body)
        assert np.array_equal(warp.warp(now, camera, body=body), want)
        part = warp.warp(now, camera, (10, 20, 300, 250), body).astype(int)
        assert np.abs(part - want[20:250, 10:300]).max() <= 1
    # A moved body shows: beyond the head's reach the person is not where it was.
    moved = warp.warp(now, body=shift(0.0, 12.0)).astype(int)
    assert np.abs(moved - warp.warp(now).astype(int)).max() > 50


def test_a_head_following_control_carried_onto_a_held_one_does_not_fold_the_warp() -> None:
    """The head drops until a point of the still ring that follows it (beside the eyes) lands
    1 px from its neighbour held with the shoulders: the two need displacements 27 px apart.
    A spline through both folds (on Claire's shoulder, a blob of the wall behind; here pixels
    from 90 px away): no output pixel may show a snapshot pixel from much further away than
    the head moved, and the map stays one-to-one (its Jacobian positive) all over the frame.
    The hair still follows."""
    image, person = person_scene()
    o = outline(k=72)
    warp = SurroundWarp(image, o, person)
    k = len(o)
    moved, then = warp.controls(o + [0.0, 1.0])
    follows = (moved - then)[2 * k :, 1] > 0.99
    held = (moved - then)[2 * k :, 1] < 0.01
    ring = then[2 * k :]
    # The following point nearest a held one, and the head's shift that lands it next to it.
    gaps = np.hypot(*(ring[follows][:, None] - ring[held][None]).transpose(2, 0, 1))
    i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
    shift = ring[held][j] + [1.0, 0.0] - ring[follows][i]
    assert np.hypot(*shift) > 25.0
    map_x, map_y = warp.source_map(o + shift)
    xs, ys = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    assert np.hypot(map_x - xs, map_y - ys).max() <= 1.5 * np.hypot(*shift)
    dxx, dxy = np.gradient(map_x, axis=1), np.gradient(map_x, axis=0)
    dyx, dyy = np.gradient(map_y, axis=1), np.gradient(map_y, axis=0)
    assert (dxx * dyy - dxy * dyx).min() > 0.0
    centre = o.mean(0)
    for q in (centre + 1.3 * (o - centre))[[54, 48, 60]]:  # hair above and beside
        x, y = np.round(q + shift).astype(int)
        assert np.allclose([map_x[y, x], map_y[y, x]], q, atol=3.0), q


def test_a_capture_s_black_column_stays_at_the_frame_edge_when_the_camera_pans() -> None:
    # An analogue capture's black first columns and an encoder's dark last row (foreman's):
    # the camera's, not the scene's. A pan must not carry them in as lines across the scene.
    image = noise_image()
    image[:, :2] = (2, 2, 2)
    image[-1] = image[-1] // 3
    o = outline()
    warp = SurroundWarp(image, o, person_scene()[1])
    assert np.array_equal(warp.warp(o), image)  # still: the frame as it came, border and all
    pan = np.array([[1.0, 0.0, 12.0], [0.0, 1.0, -6.0], [0.0, 0.0, 1.0]])
    got = warp.warp(o + [12.0, -6.0], pan)
    grey = cv2.cvtColor(got, cv2.COLOR_BGR2GRAY).astype(int)
    # Where the old edge column went (x 12-13) no column is darker than its neighbours.
    columns = grey[20:-20, 4:40].mean(axis=0)
    assert columns.min() > np.median(columns) - 25
    # Where the old bottom row went (6 rows up) no row is.
    rows = grey[-30:-2, 20:-20].mean(axis=1)
    assert rows.min() > np.median(rows) - 25
    # The border itself stays where the camera puts it.
    assert np.array_equal(got[:, :2], image[:, :2])
    assert np.array_equal(got[-1], image[-1])


def test_a_black_bar_above_a_head_that_bows_stays_at_the_top_edge() -> None:
    """Bowing's 16 blank lines above the picture (a tape's head-switching line bright in
    them), the head's hair reaching into them: the head sinks 40 px, and the warp carried the
    bar down with the hair, a black wedge above the head. The bar is the camera's border: it
    stays at the top, and the scene or the hair shows below it."""
    image, person, o = leaning_scene(top=10)
    image[:16] = 0
    image[11:14, 300:340] = 230
    assert frame_border(image)[0] == 16
    out = SurroundWarp(image, o, person).warp(o + [0.0, 40.0])
    assert np.array_equal(out[:16], image[:16])
    dark = cv2.cvtColor(out, cv2.COLOR_BGR2GRAY)[16:120, 180:300] < 20
    assert dark.mean() < 0.01
