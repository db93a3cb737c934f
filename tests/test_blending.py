import numpy as np
import pytest

from facewire.models.blending import BLEND_FUNCTIONS, blend, resolve

GROUPS = {"eyes": np.array([0, 1]), "mouth": np.array([2, 3]), "brows": np.array([4])}


@pytest.fixture
def endpoints():
    rng = np.random.default_rng(0)
    return rng.normal(size=6), rng.normal(size=6)


def test_endpoints_are_exact(endpoints):
    p0, p1 = endpoints
    np.testing.assert_array_equal(blend(p0, p1, 0.0, GROUPS), p0)
    np.testing.assert_array_equal(blend(p0, p1, 1.0, GROUPS), p1)


@pytest.mark.parametrize("name", sorted(BLEND_FUNCTIONS))
def test_registry_functions_run_from_0_to_1_monotonically(name):
    g = BLEND_FUNCTIONS[name]
    ts = np.linspace(0, 1, 101)
    vals = np.array([g(t) for t in ts])
    assert vals[0] == 0.0 and vals[-1] == 1.0
    assert (np.diff(vals) >= 0).all()


def test_eyes_lead_the_mouth_early_and_trail_late(endpoints):
    p0, p1 = endpoints
    span = p1 - p0

    def progress(t):
        return (blend(p0, p1, t, GROUPS) - p0) / span

    early, late = progress(0.1), progress(0.9)
    np.testing.assert_allclose(early[[0, 1]], np.sqrt(0.1))
    np.testing.assert_allclose(early[[2, 3]], 0.1**3)
    np.testing.assert_allclose(early[[4, 5]], 0.1)  # other feature and ungrouped: linear
    assert early[0] > early[4] > early[2]
    # Near t = 1 the mouth moves faster (larger slope) than the eyes.
    d = progress(0.95) - late
    assert d[2] > d[4] > d[0]


def test_functions_are_configurable_by_name_or_callable(endpoints):
    p0, p1 = endpoints
    out = blend(p0, p1, 0.5, GROUPS, {"eyes": "linear", "brows": lambda t: 1.0}, default="cube")
    np.testing.assert_allclose(out[[0, 1]], p0[[0, 1]] + 0.5 * (p1 - p0)[[0, 1]])
    np.testing.assert_allclose(out[4], p1[4])
    np.testing.assert_allclose(out[[2, 3, 5]], p0[[2, 3, 5]] + 0.125 * (p1 - p0)[[2, 3, 5]])


def test_errors_name_the_bad_value(endpoints):
    p0, p1 = endpoints
    with pytest.raises(ValueError, match="in \\[0, 1\\], got 1.5"):
        blend(p0, p1, 1.5, GROUPS)
    with pytest.raises(ValueError, match="unknown blending function 'wobble'"):
        resolve("wobble")
    with pytest.raises(ValueError, match=r"got \(6,\) and \(5,\)"):
        blend(p0, p1[:5], 0.5, GROUPS)
    with pytest.raises(ValueError, match="group 'eyes': index 9 out of range 0..5"):
        blend(p0, p1, 0.5, {"eyes": np.array([9])})


def test_with_a_wire_deformer_only_the_grouped_features_lag():
    from facewire.models.mesh import load_canonical
    from facewire.models.wires import WireCurveSpec, WireDeformer

    v = load_canonical().vertices
    w = WireDeformer(
        v,
        [
            WireCurveSpec(
                "lip", (61, 185, 40, 39, 37, 0, 267, 269, 270, 409, 291), 6, 1.2, "mouth"
            ),
            WireCurveSpec("brow", (70, 63, 105, 66, 107), 4, 1.5, "brows"),
        ],
        2.0,
    )
    p0 = w.rest_params()
    p1 = p0.copy()
    p1[w.q_slices[0]] = 0.5  # open/shift the lip wire
    p1[w.q_slices[1]] = 0.5  # raise the brow wire
    mid = blend(p0, p1, 0.5, w.feature_groups())
    _, q = w.split_params(mid)
    np.testing.assert_allclose(q[0], 0.5 * 0.125)
    np.testing.assert_allclose(q[1], 0.5 * 0.5)
