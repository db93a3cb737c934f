import copy
import json

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from skimage.measure import points_in_poly

from facewire.models.mesh import data_path, load_canonical
from facewire.models.rig import FEATURES, load_rig, parse_rig
from facewire.models.subdivision import loop_subdivide


@pytest.fixture(scope="module")
def mesh():
    return load_canonical()


@pytest.fixture(scope="module")
def rig():
    return load_rig()


@pytest.fixture()
def raw():
    return json.loads(data_path("rig.json").read_text())


def is_adjacent_loop(mesh, loop):
    a = mesh.adjacency
    return all(a[i, j] for i, j in zip(loop, loop[1:] + loop[:1], strict=True))


def test_loads_and_validates(rig, mesh):
    rig.validate(mesh.n_vertices)
    assert 20 <= len(rig.markers) <= 30
    assert 14 <= len(rig.curves) <= 16
    assert rig.localize_k == pytest.approx(2.0)
    assert set(rig.features()) == set(FEATURES)
    assert [m.name for m in rig.markers_with_role("mouth")] == [
        "mouth_right",
        "mouth_left",
        "lip_top",
        "lip_bottom",
    ]
    assert rig.marker("nose_tip").vertex == 1
    with pytest.raises(KeyError, match="no marker 'nose'"):
        rig.marker("nose")
    # indices stay valid on the subdivided mesh (coarse vertices come first)
    fine, _ = loop_subdivide(mesh, 1)
    rig.validate(fine.n_vertices)


def test_lip_markers_agree(rig):
    by_vertex = {m.vertex: m.name for m in rig.markers_with_role("mouth")}
    assert {by_vertex[v] for v in rig.lips.markers.values()} == set(by_vertex.values())
    assert rig.lips.markers == {"left": 291, "right": 61, "top": 0, "bottom": 17}


def test_gde_per_moving_marker(rig):
    moving = [m for m in rig.markers if m.role != "pose"]
    assert {(g.name, g.control_vertex) for g in rig.gdes} == {(m.name, m.vertex) for m in moving}
    for g in rig.gdes:
        if g.name in ("mouth_right", "mouth_left", "lip_top", "lip_bottom"):
            assert g.metric == "edges"
        if "lid" in g.name:
            assert g.metric == "euclidean"


def test_chains_follow_mesh_edges(rig, mesh):
    for c in rig.curves:
        chain = list(c.vertices)
        p = mesh.vertices[chain]
        steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
        assert all(mesh.adjacency[i, j] for i, j in zip(chain[:-1], chain[1:], strict=True)), c.name
        # the canonical mesh is coarse on the cheeks (edges up to 2.3 cm), fine elsewhere
        assert steps.max() < (2.5 if c.feature == "cheeks" else 1.8), (c.name, steps.max())
        assert 4 <= c.control_points <= min(6, len(c.vertices))


def test_moving_parts_are_reached_by_a_wire(rig, mesh):
    v = mesh.vertices
    # distance from every vertex to each chain (as points densely sampled along the polyline)
    reached = np.zeros(mesh.n_vertices, bool)
    for c in rig.curves:
        p = v[list(c.vertices)]
        t = np.linspace(0, 1, 20)[:, None, None]
        samples = (p[:-1] + t * (p[1:] - p[:-1])).reshape(-1, 3)
        d = np.linalg.norm(v[:, None] - samples[None], axis=2).min(axis=1)
        reached |= d < c.range
    # every moving feature is reached (a vertex no range reaches never moves)
    features = {m.vertex for m in rig.markers if m.role != "pose"}
    for ring in rig.lips.contours:
        features.update(ring)
    assert sorted(i for i in features if not reached[i]) == []
    # and most of the front of the face moves
    front = v[:, 2] > 3.0
    assert reached[front].mean() > 0.8


def test_lip_rings_are_nested_adjacent_loops(rig, mesh):
    rings = [list(r) for r in rig.lips.contours]
    assert len(rings) == 4
    xy = mesh.vertices[:, :2]
    for r in rings:
        assert is_adjacent_loop(mesh, r), r
    all_ring_vertices = [i for r in rings for i in r]
    assert len(set(all_ring_vertices)) == len(all_ring_vertices)
    # the outer ring encloses the others in the frontal projection
    for inner in rings[1:]:
        assert points_in_poly(xy[inner], xy[rings[0]]).all()
    # the lips curl, so the middle rings cross in projection; nest them on the surface:
    # cutting ring k out of the mesh leaves a disc around the mouth that holds ring k + 1
    for k, ring in enumerate(rings):
        keep = np.setdiff1d(np.arange(mesh.n_vertices), ring)
        _, label = connected_components(mesh.adjacency[keep][:, keep], directed=False)
        comp = dict(zip(keep.tolist(), label.tolist(), strict=True))
        face = comp[1]  # nose tip: outside every lip ring
        outside = {i for i, lab in comp.items() if lab == face}
        assert len(outside) > mesh.n_vertices - 100
        for inner in rings[k + 1 :]:
            assert not outside & set(inner), (k, sorted(outside & set(inner)))
    m = rig.lips.markers
    assert m["left"] in rings[0] and m["right"] in rings[0]
    assert m["top"] in rings[0] and m["bottom"] in rings[0]


def test_left_right_names_mirror(rig, mesh):
    v = mesh.vertices
    mirror = np.array([-1.0, 1.0, 1.0])
    groups = {
        "marker": {m.name: [m.vertex] for m in rig.markers},
        "curve": {c.name: list(c.vertices) for c in rig.curves},
        "gde": {g.name: [g.control_vertex] for g in rig.gdes},
        "rem": {r.name: list(r.polygon) for r in rig.rem},
    }
    pairs = 0
    for kind, named in groups.items():
        for name, idx in named.items():
            if not name.endswith("_right"):
                continue
            other = named.get(name[: -len("right")] + "left")
            assert other is not None, f"{kind} {name} has no _left twin"
            assert len(other) == len(idx)
            np.testing.assert_allclose(v[idx] * mirror, v[other], atol=1e-3)
            assert np.all(v[idx, 0] < 0), f"{kind} {name} is not on the face's right (x < 0)"
            pairs += 1
    assert pairs >= 15


def test_rem_spectacles_enclose_the_eyes(rig, mesh):
    xy = mesh.vertices[:, :2]
    rem = {r.name: list(r.polygon) for r in rig.rem}
    assert set(rem) == {"eye_right", "eye_left"}
    for side, other in (("right", "left"), ("left", "right")):
        poly = rem[f"eye_{side}"]
        assert is_adjacent_loop(mesh, poly)
        inside = [
            rig.marker(f"{n}_{side}").vertex
            for n in ("eye_outer", "eye_inner", "upper_lid", "lower_lid")
        ]
        assert points_in_poly(xy[inside], xy[poly]).all()
        lids = [i for c in rig.curves if c.name.endswith(f"lid_{side}") for i in c.vertices]
        assert points_in_poly(xy[lids], xy[poly]).all()
        assert not points_in_poly(xy[[rig.marker(f"eye_outer_{other}").vertex]], xy[poly]).any()


def test_curves_lie_on_their_features(rig, mesh):
    v = mesh.vertices
    c = {c.name: v[list(c.vertices)] for c in rig.curves}
    eye_y = v[[33, 133], 1].mean()
    assert c["brow_right"][:, 1].min() > v[159, 1]  # brows above the upper lid
    assert c["upper_lid_right"][:, 1].mean() > c["lower_lid_right"][:, 1].mean()
    assert abs(c["upper_lid_right"][:, 1].mean() - eye_y) < 0.5
    assert c["upper_lip"][:, 1].mean() > c["lower_lip"][:, 1].mean()
    assert c["chin"][:, 1].max() < v[17, 1]
    assert c["forehead"][:, 1].min() > c["brow_right"][:, 1].max()
    nl = c["nasolabial_right"]  # from the nose wing down and out to beside the mouth corner
    assert nl[0, 1] > v[61, 1] + 1.5 and abs(nl[-1, 1] - v[61, 1]) < 1.0
    assert nl[-1, 0] < v[61, 0]


def test_error_unknown_role(raw):
    raw["markers"][0]["role"] = "wobble"
    with pytest.raises(ValueError, match=r"marker 'nose_bridge' role: unknown value 'wobble'"):
        parse_rig(raw)


def test_error_index_out_of_range(rig):
    with pytest.raises(
        ValueError,
        match=r"marker 'nose_bridge': vertex 168 out of range for a mesh of 100 vertices",
    ):
        rig.validate(100)


def test_error_chain_too_short(raw):
    raw["wires"]["curves"][0]["control_points"] = 6
    with pytest.raises(
        ValueError, match=r"wire curve 'brow_right': chain of 5 vertices too short for 6"
    ):
        parse_rig(raw)


def test_error_duplicate_names(raw):
    raw["markers"].append(copy.deepcopy(raw["markers"][0]))
    with pytest.raises(ValueError, match=r"duplicate marker name 'nose_bridge'"):
        parse_rig(raw)
    raw["markers"].pop()
    raw["wires"]["curves"][1]["name"] = "brow_right"
    with pytest.raises(ValueError, match=r"duplicate wire curve name 'brow_right'"):
        parse_rig(raw)


def test_error_bad_values(raw, tmp_path):
    bad = copy.deepcopy(raw)
    bad["gdes"][0]["metric"] = "geodesic"
    with pytest.raises(ValueError, match=r"metric: unknown value 'geodesic'"):
        parse_rig(bad)
    bad = copy.deepcopy(raw)
    bad["wires"]["curves"][0]["feature"] = "ears"
    with pytest.raises(ValueError, match=r"feature: unknown value 'ears'"):
        parse_rig(bad)
    bad = copy.deepcopy(raw)
    bad["version"] = 2
    with pytest.raises(ValueError, match=r"unsupported rig version 2"):
        parse_rig(bad)
    path = tmp_path / "rig.json"
    path.write_text("{not json")
    with pytest.raises(ValueError, match=r"not valid JSON"):
        load_rig(path)
