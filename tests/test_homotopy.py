import numpy as np
import pytest

from facewire.models.homotopy import MouthRig, blend, cylindrical_frames, scaling_factors, sweep
from facewire.models.mesh import load_canonical

MARKERS = {"left": 291, "right": 61, "top": 0, "bottom": 17}
CONTOURS = [
    [61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291, 375, 321, 405, 314, 17, 84, 181, 91, 146],
    [76, 184, 74, 73, 72, 11, 302, 303, 304, 408, 306, 307, 320, 404, 315, 16, 85, 180, 90, 77],
    [62, 183, 42, 41, 38, 12, 268, 271, 272, 407, 292, 325, 319, 403, 316, 15, 86, 179, 89, 96],
    [78, 191, 80, 81, 82, 13, 312, 311, 310, 415, 308, 324, 318, 402, 317, 14, 87, 178, 88, 95],
]


@pytest.fixture(scope="module")
def mesh():
    return load_canonical()


@pytest.fixture(scope="module")
def rig(mesh):
    return MouthRig(mesh, MARKERS, CONTOURS)


@pytest.mark.parametrize("n", [-0.9, -0.5, 0.0, 0.2, 0.5, 0.9])
def test_blend_endpoints_and_monotone(n):
    assert blend(0.0, n) == 0.0
    assert blend(1.0, n) == 1.0
    v = np.linspace(0, 1, 201)
    assert np.all(np.diff(blend(v, n)) > 0)
    # G1 ends: zero slope at both ends.
    h = 1e-4
    assert blend(h, n) / h < 1e-2
    assert (1 - blend(1 - h, n)) / h < 1e-2


def test_blend_parameter_shifts_transition():
    assert blend(0.5, 0.0) == pytest.approx(0.5)
    assert blend(0.5, 0.5) > 0.5 > blend(0.5, -0.5)
    with pytest.raises(ValueError, match=r"n must be in \(-1, 1\), got 1.0"):
        blend(0.5, 1.0)


@pytest.mark.parametrize("k1,k2", [(0.5, 0.5), (0.2, 0.7), (1.5, -0.3)])
def test_scaling_vanishes_at_ends(k1, k2):
    assert scaling_factors(0.0, k1, k2) == (0.0, 0.0)
    assert scaling_factors(1.0, k1, k2) == (0.0, 0.0)
    s1, s2 = scaling_factors(0.3, k1, k2)
    assert s1 != 0 and s2 != 0
    assert scaling_factors(k1, k1, k2)[0] == pytest.approx(0.0)
    assert scaling_factors(1 - k2, k1, k2)[1] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="k1=0.0"):
        scaling_factors(0.5, 0.0, 0.5)


def test_sweep_endpoints_random():
    rng = np.random.default_rng(0)
    c1 = rng.normal(size=(30, 3)) * 2
    c2 = c1 + rng.normal(size=(30, 3))
    v1, v2 = rng.normal(size=(2, 30, 3))
    centre, axis = np.array([0.1, -0.2, 0.3]), np.array([0.2, 0.1, 1.0])
    for n in (0.0, (-0.5, 0.3, 0.8)):
        assert np.array_equal(sweep(c1, c2, 0.0, centre, axis, n, 0.4, v1, v2), c1)
        assert np.allclose(sweep(c1, c2, 1.0, centre, axis, n, 0.4, v1, v2), c2, atol=1e-12)
    mid = sweep(c1, c2, 0.5, centre, axis, 0.0, 0.4, v1, v2)
    plain = sweep(c1, c2, 0.5, centre, axis)
    assert np.allclose(plain, 0.5 * (c1 + c2))  # R_0(1/2) = 1/2, no bending
    assert not np.allclose(mid, plain)  # control vectors bend the path


def literal_sweep(c1, c2, t, centre, axis, n, k, v1, v2, big_n):
    """Eq. 3-9 as printed (with Eq. 7 corrected), one point at a time."""
    out = []
    for a, b, w1, w2 in zip(c1, c2, v1, v2, strict=True):
        uz = axis / np.linalg.norm(axis)
        rel = a - centre
        ur = rel - (rel @ uz) * uz
        ur /= np.linalg.norm(ur)
        ut = np.cross(uz, ur)
        c1r, c1z = rel @ ur, rel @ uz
        assert abs(rel @ ut) < 1e-12  # A = [C1r, 0, C1z]
        rb = b - centre
        c2r, c2t, c2z = rb @ ur, rb @ ut, rb @ uz
        p1 = np.array([w1 @ ur / c1r, w1 @ ut / big_n, w1 @ uz / c1z])  # Eq. 9
        p2 = np.array([w2 @ ur / c2r, w2 @ ut / (c2t + big_n), w2 @ uz / c2z])
        sc1 = t * (t - 1) * (t / k - 1) * p1  # Eq. 8
        sc2 = -t * (t - 1) * (t / (1 - k) - 1) * p2
        rn = (1 + n) * t**2 / ((1 + n) * t**2 + (1 - n) * (1 - t) ** 2)
        r = (1 - rn) * (1 + sc1[0]) * c1r + rn * (1 + sc2[0]) * c2r  # Eq. 4
        th = (1 - rn) * (1 + sc1[1]) * big_n + rn * (1 + sc2[1]) * (c2t + big_n) - big_n  # Eq. 5
        z = (1 - rn) * (1 + sc1[2]) * c1z + rn * (1 + sc2[2]) * c2z  # Eq. 6
        out.append(centre + r * ur + th * ut + z * uz)  # Eq. 3
    return np.array(out)


def test_sweep_matches_equations_4_to_6_on_hand_made_contour():
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False) + 0.1
    c1 = np.stack([2 * np.cos(ang), np.sin(ang), 0.3 + 0.1 * np.cos(ang)], axis=1)
    c2 = c1 * [1.2, 1.5, 1.0] + [0.1, -0.2, 0.4]
    v1 = np.tile([0.3, -0.2, 0.5], (6, 1))
    v2 = np.stack([-np.sin(ang), np.cos(ang), np.zeros(6)], axis=1)
    centre, axis = np.zeros(3), np.array([0.0, 0.0, 1.0])
    for t in (0.0, 0.25, 0.6, 1.0):
        got = sweep(c1, c2, t, centre, axis, 0.3, 0.5, v1, v2)
        for big_n in (1.0, 7.5):  # the offset N of Eq. 5 cancels
            want = literal_sweep(c1, c2, t, centre, axis, 0.3, 0.5, v1, v2, big_n)
            assert np.allclose(got, want, atol=1e-12)


def test_frames_are_orthonormal_and_right_handed():
    pts = np.array([[1.0, 0, 0.5], [0, 2.0, -1], [0, 0, 3.0]])  # the last lies on the axis
    f = cylindrical_frames(pts, np.zeros(3), np.array([0, 0, 2.0]))
    for frame in f:
        assert np.allclose(frame @ frame.T, np.eye(3))
        assert np.allclose(np.cross(frame[0], frame[1]), frame[2])
    assert np.allclose(f[0, 0], [1, 0, 0]) and np.allclose(f[1, 1], [-1, 0, 0])


def test_zero_displacement_neutral(mesh, rig):
    for t in (0.3, 1.0):
        assert np.array_equal(rig.deform(mesh.vertices, np.zeros((4, 3)), t), mesh.vertices)


def test_translating_markers_translates_rings(mesh, rig):
    shift = np.array([0.2, -0.3, 0.1])
    out = rig.deform(mesh.vertices, np.tile(shift, (4, 1)))
    ring = np.unique(np.concatenate(CONTOURS))
    assert np.allclose(out[ring] - mesh.vertices[ring], shift, atol=1e-12)
    half = rig.deform(mesh.vertices, np.tile(shift, (4, 1)), t=0.5)
    assert np.allclose(half[ring] - mesh.vertices[ring], blend(0.5) * shift, atol=1e-12)
    moved = np.linalg.norm(out - mesh.vertices, axis=1)
    others = np.setdiff1d(np.arange(len(moved)), ring)
    assert moved[others].max() <= np.linalg.norm(shift) + 1e-12
    assert (moved[others] > 0).sum() == len(rig.follow_vertices) > 0


def test_markers_reach_their_displacement_and_rings_interpolate(mesh, rig):
    rng = np.random.default_rng(1)
    d = rng.normal(scale=0.3, size=(4, 3))
    e = rng.normal(scale=0.3, size=(4, 3))
    out = rig.deform(mesh.vertices, d, inner_disp=e)
    markers = [MARKERS[m] for m in ("left", "top", "right", "bottom")]
    assert np.allclose(out[markers] - mesh.vertices[markers], d, atol=1e-12)
    # Inner markers take the same ellipse angles as the vertices beside them; middle rings
    # sit 1/3 and 2/3 of the way from the outer to the inner ring's field.
    idx = {v: i for i, v in enumerate(rig.ring_vertices)}
    outer_field = rig.ring_targets(d, d)
    inner_field = rig.ring_targets(e, e)
    for ring, alpha in zip(CONTOURS, (0, 1 / 3, 2 / 3, 1), strict=True):
        rows = [idx[v] for v in ring]
        want = (1 - alpha) * outer_field[rows] + alpha * inner_field[rows]
        assert np.allclose(out[ring] - mesh.vertices[ring], want, atol=1e-12)


def test_mouth_opening_moves_lips_apart_and_leaves_far_face(mesh, rig):
    d = np.zeros((4, 3))
    d[1] = [0, 0.3, 0]  # top up
    d[3] = [0, -0.6, 0]  # bottom down
    out = rig.deform(mesh.vertices, d)
    dy = out[:, 1] - mesh.vertices[:, 1]
    assert dy[13] > 0.2 and dy[14] < -0.4  # inner lips follow by angle
    assert abs(dy[61]) < 1e-9 and abs(dy[291]) < 1e-9  # corners stay
    far = np.linalg.norm(mesh.vertices - mesh.vertices[0], axis=1) > 6
    assert np.array_equal(out[far], mesh.vertices[far])


def test_bad_inputs(mesh, rig):
    with pytest.raises(ValueError, match=r"expected marker_disp \(4, 3\).*got \(3, 3\)"):
        rig.deform(mesh.vertices, np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"t must be in \[0, 1\], got 1.5"):
        rig.deform(mesh.vertices, np.zeros((4, 3)), t=1.5)
    with pytest.raises(ValueError, match="expected 4 lip contours"):
        MouthRig(mesh, MARKERS, CONTOURS[:3])
    with pytest.raises(ValueError, match=r"expected c2 \(3, 3\) float array, got \(2, 3\)"):
        sweep(np.zeros((3, 3)), np.zeros((2, 3)), 0.5, np.zeros(3), np.array([0, 0, 1.0]))


def test_from_rig_accepts_rig_or_lips(mesh):
    class Lips:
        markers = MARKERS
        contours = CONTOURS

    class Rig:
        lips = Lips()

    a = MouthRig.from_rig(mesh, Rig(), falloff=0.8)
    b = MouthRig.from_rig(mesh, Lips(), falloff=0.8)
    d = np.full((4, 3), 0.1)
    assert np.array_equal(a.deform(mesh.vertices, d), b.deform(mesh.vertices, d))


def test_bundled_rig(mesh):
    from facewire.models.rig import load_rig

    rig = MouthRig.from_rig(mesh, load_rig())
    assert np.array_equal(rig.deform(mesh.vertices, np.zeros((4, 3))), mesh.vertices)


def test_a_contour_with_a_larger_n_moves_earlier(mesh):
    rig0 = MouthRig(mesh, MARKERS, CONTOURS)
    rig1 = MouthRig(mesh, MARKERS, CONTOURS, n=(0.0, 0.0, 0.0, 0.6))
    disp = np.tile([0.0, -0.4, 0.1], (4, 1))
    v = mesh.vertices
    early = rig1.deform(v, disp, t=0.3) - rig0.deform(v, disp, t=0.3)
    inner_only = np.setdiff1d(CONTOURS[3], np.concatenate(CONTOURS[:3]))
    outer_only = np.setdiff1d(CONTOURS[0], np.concatenate(CONTOURS[1:]))
    assert np.all(early[inner_only, 1] < -0.01)  # further along the way down
    assert np.allclose(early[outer_only], 0.0)
    assert np.allclose(rig1.deform(v, disp, t=1.0), rig0.deform(v, disp, t=1.0))
    with pytest.raises(ValueError, match=r"n must be in \(-1, 1\)"):
        MouthRig(mesh, MARKERS, CONTOURS, n=(0.0, 0.0, 0.0, 1.0))


def test_sweep_takes_a_blending_parameter_per_point():
    rng = np.random.default_rng(1)
    c1 = rng.normal(size=(5, 3))
    c2 = c1 + 1.0
    centre, axis = np.zeros(3), np.array([0.0, 0.0, 1.0])
    n = np.zeros((5, 3))
    n[2] = 0.5
    got = sweep(c1, c2, 0.3, centre, axis, n)
    assert np.allclose(got[[0, 1, 3, 4]], sweep(c1, c2, 0.3, centre, axis)[[0, 1, 3, 4]])
    assert np.allclose(got[2], sweep(c1, c2, 0.3, centre, axis, 0.5)[2])
    with pytest.raises(ValueError, match=r"expected n of shape"):
        sweep(c1, c2, 0.3, centre, axis, np.zeros((4, 3)))


def test_control_vectors_spread_a_common_marker_velocity_unchanged(rig):
    velocity = np.tile([0.1, -0.2, 0.05], (4, 1))
    assert np.allclose(rig.control_vectors(velocity), velocity[0])


def test_between_leaves_and_reaches_the_key_frames_at_the_markers_speed(mesh, rig):
    v = mesh.vertices
    step = np.zeros_like(v)
    step[rig.ring_vertices] = [0.0, -0.3, 0.0]  # the lips drop 3 mm a key frame interval
    before, a, b = v - step, v, v + step
    rings = rig.ring_vertices
    assert np.allclose(rig.between(a, a, b, 0.0, before)[rings], a[rings])
    assert np.allclose(rig.between(b, a, b, 1.0, before)[rings], b[rings])
    h = 1e-4
    start = (rig.between(a, a, b, h, before) - a)[rings] / h
    end = (b - rig.between(b, a, b, 1.0 - h, before))[rings] / h
    assert np.allclose(start, step[rings], atol=1e-3)  # at the markers' velocity
    assert np.allclose(end, step[rings], atol=1e-3)
    # The blending function alone leaves and arrives at rest.
    still = (rig.between(a, a, b, h, before, control=False) - a)[rings] / h
    assert np.abs(still).max() < 1e-2
    # The skin around the lips is carried with them, the far face is not.
    moved = rig.between(a, a, b, 0.5, before) - a
    assert np.abs(moved[rig.follow_vertices]).max() > 0.01
    far = np.setdiff1d(np.arange(len(v)), np.concatenate([rings, rig.follow_vertices]))
    assert np.allclose(moved[far], 0.0)


def test_deform_with_marker_velocities_bends_the_path_not_its_ends(mesh, rig):
    v = mesh.vertices
    disp = np.tile([0.0, -0.3, 0.0], (4, 1))
    fast = (np.tile([0.0, -0.6, 0.0], (4, 1)), np.zeros((4, 3)))
    rings = rig.ring_vertices
    assert np.allclose(rig.deform(v, disp, 1.0, velocities=fast), rig.deform(v, disp, 1.0))
    h = 1e-4
    start = (rig.deform(v, disp, h, velocities=fast) - v)[rings] / h
    assert np.allclose(start, [0.0, -0.6, 0.0], atol=1e-3)  # leaves at the markers' speed
    quarter = rig.deform(v, disp, 0.25, velocities=fast) - rig.deform(v, disp, 0.25)
    assert np.all(quarter[rings, 1] < 0)  # ahead of the unbent path
