"""The face rig: markers, wire curves, GDEs, lip contours and REM regions by vertex index.

The rig is data (``models/data/rig.json``) that names vertices of the canonical mesh; vertex i
is MediaPipe landmark i, and Loop subdivision (models.subdivision) keeps the coarse vertices
first, so the same indices stay valid on a subdivided mesh.

Schema (version 1)::

    {"version": 1,
     "markers": [{"name": str, "vertex": int, "role": "pose" | "deform" | "mouth"}, ...],
     "wires": {"localize_k": float,
               "curves": [{"name": str, "vertices": [int, ...], "control_points": int >= 4,
                           "range": float (cm), "feature": one of FEATURES}, ...]},
     "gdes": [{"name": str, "control_vertex": int, "size": number,
               "metric": "edges" | "euclidean"}, ...],
     "lips": {"markers": {"left": int, "right": int, "top": int, "bottom": int},
              "contours": [[outer loop], [loop], [loop], [inner loop]]},
     "rem": [{"name": "eye_right" | "eye_left", "polygon": [vertex loop]}, ...]}

GDE ``size`` is an edge depth (integer) for ``"edges"`` and centimetres for ``"euclidean"``.
Contours and REM polygons are closed loops: the last vertex connects back to the first.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facewire.models.mesh import data_path

logger = logging.getLogger(__name__)

RIG_VERSION = 1
ROLES = ("pose", "deform", "mouth")
FEATURES = ("eyes", "brows", "mouth", "nose", "cheeks", "chin", "forehead")
METRICS = ("edges", "euclidean")
LIP_MARKERS = ("left", "right", "top", "bottom")
REM_NAMES = ("eye_right", "eye_left")
MIN_CONTROL_POINTS = 4


@dataclass(frozen=True)
class Marker:
    """A named tracked point on vertex ``vertex``; role is "pose", "deform" or "mouth"."""

    name: str
    vertex: int
    role: str


@dataclass(frozen=True)
class WireCurve:
    """A wire reference curve: a cubic B-spline with ``control_points`` control points fitted
    along the vertex chain ``vertices`` (ordered along the feature); ``range`` in cm."""

    name: str
    vertices: tuple[int, ...]
    control_points: int
    range: float
    feature: str


@dataclass(frozen=True)
class GdeSpec:
    """A geometry deformation element centred on ``control_vertex``.

    size : edge depth (int) when metric == "edges", centimetres when metric == "euclidean"
    """

    name: str
    control_vertex: int
    size: float
    metric: str


@dataclass(frozen=True)
class LipRig:
    """Lip markers (left/right corner, top/bottom mid) and four nested closed contours,
    outermost first, innermost (the mouth opening) last."""

    markers: dict[str, int]
    contours: list[tuple[int, ...]]


@dataclass(frozen=True)
class RemRegion:
    """A region effective for merging: a closed vertex loop around an eye (its lids and one
    ring of skin beyond them: where ``facewire rem-map`` finds texture change outweighing
    shape change; seed 003's "spectacles" reached up over the brows, which the wires move)."""

    name: str
    polygon: tuple[int, ...]


@dataclass(frozen=True)
class Rig:
    """Everything the deformers and trackers need to know about the face model, by index."""

    markers: list[Marker]
    localize_k: float
    curves: list[WireCurve]
    gdes: list[GdeSpec]
    lips: LipRig
    rem: list[RemRegion]
    _by_name: dict[str, Marker] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_unique("marker", [m.name for m in self.markers])
        _check_unique("wire curve", [c.name for c in self.curves])
        _check_unique("GDE", [g.name for g in self.gdes])
        _check_unique("REM region", [r.name for r in self.rem])
        self._by_name.update({m.name: m for m in self.markers})

    def marker(self, name: str) -> Marker:
        """The marker called ``name``; KeyError naming the known markers otherwise."""
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no marker {name!r}; known: {sorted(self._by_name)}") from None

    def markers_with_role(self, role: str) -> list[Marker]:
        """Markers of one role, in file order."""
        if role not in ROLES:
            raise ValueError(f"unknown marker role {role!r}, expected one of {ROLES}")
        return [m for m in self.markers if m.role == role]

    def wire_layout(self) -> list[tuple[str, int]]:
        """(curve name, control point count) per wire, in file order: the order of the wire
        parameters on the wire (``Snapshot.wire_layout``)."""
        return [(c.name, c.control_points) for c in self.curves]

    def features(self) -> dict[str, list[int]]:
        """Feature name -> indices into ``curves`` of the wires of that feature (file order)."""
        out: dict[str, list[int]] = {}
        for i, c in enumerate(self.curves):
            out.setdefault(c.feature, []).append(i)
        return out

    def validate(self, n_vertices: int) -> None:
        """Raise ValueError if any index is outside 0..n_vertices-1."""
        where: list[tuple[str, Sequence[int]]] = [
            (f"marker {m.name!r}", [m.vertex]) for m in self.markers
        ]
        where += [(f"wire curve {c.name!r}", c.vertices) for c in self.curves]
        where += [(f"GDE {g.name!r}", [g.control_vertex]) for g in self.gdes]
        where += [(f"lip marker {k!r}", [v]) for k, v in self.lips.markers.items()]
        where += [(f"lip contour {i}", c) for i, c in enumerate(self.lips.contours)]
        where += [(f"REM region {r.name!r}", r.polygon) for r in self.rem]
        for label, indices in where:
            for v in indices:
                if not 0 <= v < n_vertices:
                    raise ValueError(
                        f"{label}: vertex {v} out of range for a mesh of {n_vertices} vertices"
                    )


def load_rig(path: str | Path | None = None) -> Rig:
    """Read and check a rig file (default: the bundled ``models/data/rig.json``)."""
    path = data_path("rig.json") if path is None else Path(path)
    try:
        raw = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ValueError(f"cannot read rig {path}: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from exc
    try:
        rig = parse_rig(raw)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    logger.debug(
        "rig %s: %d markers, %d wires, %d GDEs",
        path,
        len(rig.markers),
        len(rig.curves),
        len(rig.gdes),
    )
    return rig


def parse_rig(raw: Any) -> Rig:
    """Build a Rig from the decoded JSON object, checking types and enumerations."""
    obj = _mapping(raw, "rig")
    version = obj.get("version")
    if version != RIG_VERSION:
        raise ValueError(f"unsupported rig version {version!r}, expected {RIG_VERSION}")
    markers = [_marker(m, i) for i, m in enumerate(_list(obj, "markers", "rig"))]
    wires = _mapping(obj.get("wires"), "wires")
    k = _number(wires.get("localize_k"), "wires.localize_k")
    if k <= 0:
        raise ValueError(f"wires.localize_k must be > 0, got {k}")
    curves = [_curve(c, i) for i, c in enumerate(_list(wires, "curves", "wires"))]
    gdes = [_gde(g, i) for i, g in enumerate(_list(obj, "gdes", "rig"))]
    lips = _lips(obj.get("lips"))
    rem = [_rem(r, i) for i, r in enumerate(_list(obj, "rem", "rig"))]
    return Rig(markers, k, curves, gdes, lips, rem)


def _check_unique(kind: str, names: list[str]) -> None:
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise ValueError(f"duplicate {kind} name {n!r}")
        seen.add(n)


def _mapping(x: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(x, Mapping):
        raise ValueError(f"{where}: expected an object, got {type(x).__name__}")
    return x


def _list(obj: Mapping[str, Any], key: str, where: str) -> list[Any]:
    x = obj.get(key)
    if not isinstance(x, list):
        raise ValueError(f"{where}.{key}: expected a list, got {type(x).__name__}")
    return x


def _int(x: Any, where: str) -> int:
    # bool is an int subclass; a vertex index of True is a typo, not 1
    if not isinstance(x, int) or isinstance(x, bool):
        raise ValueError(f"{where}: expected an integer, got {x!r}")
    return x


def _number(x: Any, where: str) -> float:
    if not isinstance(x, int | float) or isinstance(x, bool) or not math.isfinite(x):
        raise ValueError(f"{where}: expected a finite number, got {x!r}")
    return float(x)


def _str(x: Any, where: str) -> str:
    if not isinstance(x, str) or not x:
        raise ValueError(f"{where}: expected a non-empty string, got {x!r}")
    return x


def _choice(x: Any, options: tuple[str, ...], where: str) -> str:
    if x not in options:
        raise ValueError(f"{where}: unknown value {x!r}, expected one of {options}")
    return str(x)


def _indices(x: Any, where: str) -> tuple[int, ...]:
    if not isinstance(x, list):
        raise ValueError(f"{where}: expected a list of vertex indices, got {type(x).__name__}")
    return tuple(_int(v, f"{where}[{i}]") for i, v in enumerate(x))


def _marker(raw: Any, i: int) -> Marker:
    m = _mapping(raw, f"markers[{i}]")
    name = _str(m.get("name"), f"markers[{i}].name")
    return Marker(
        name,
        _int(m.get("vertex"), f"marker {name!r} vertex"),
        _choice(m.get("role"), ROLES, f"marker {name!r} role"),
    )


def _curve(raw: Any, i: int) -> WireCurve:
    c = _mapping(raw, f"wires.curves[{i}]")
    name = _str(c.get("name"), f"wires.curves[{i}].name")
    where = f"wire curve {name!r}"
    verts = _indices(c.get("vertices"), f"{where} vertices")
    ncp = _int(c.get("control_points"), f"{where} control_points")
    if ncp < MIN_CONTROL_POINTS:
        raise ValueError(f"{where}: control_points {ncp} < {MIN_CONTROL_POINTS} (cubic B-spline)")
    if len(verts) < ncp:
        raise ValueError(
            f"{where}: chain of {len(verts)} vertices too short for {ncp} control points"
        )
    if len(set(verts)) != len(verts):
        raise ValueError(f"{where}: chain repeats a vertex: {list(verts)}")
    rng = _number(c.get("range"), f"{where} range")
    if rng <= 0:
        raise ValueError(f"{where}: range must be > 0 cm, got {rng}")
    feature = _choice(c.get("feature"), FEATURES, f"{where} feature")
    return WireCurve(name, verts, ncp, rng, feature)


def _gde(raw: Any, i: int) -> GdeSpec:
    g = _mapping(raw, f"gdes[{i}]")
    name = _str(g.get("name"), f"gdes[{i}].name")
    where = f"GDE {name!r}"
    vertex = _int(g.get("control_vertex"), f"{where} control_vertex")
    metric = _choice(g.get("metric"), METRICS, f"{where} metric")
    if metric == "edges":
        size: float = _int(g.get("size"), f"{where} size (edge depth)")
    else:
        size = _number(g.get("size"), f"{where} size (cm)")
    if size <= 0:
        raise ValueError(f"{where}: size must be > 0, got {size}")
    return GdeSpec(name, vertex, size, metric)


def _lips(raw: Any) -> LipRig:
    lips = _mapping(raw, "lips")
    mk = _mapping(lips.get("markers"), "lips.markers")
    if set(mk) != set(LIP_MARKERS):
        raise ValueError(f"lips.markers: expected keys {LIP_MARKERS}, got {sorted(mk)}")
    markers = {k: _int(mk[k], f"lips.markers.{k}") for k in LIP_MARKERS}
    contours = [
        _indices(c, f"lips.contours[{i}]") for i, c in enumerate(_list(lips, "contours", "lips"))
    ]
    if len(contours) != 4:
        raise ValueError(f"lips.contours: expected 4 nested loops, got {len(contours)}")
    for i, c in enumerate(contours):
        if len(c) < 3 or len(set(c)) != len(c):
            raise ValueError(f"lips.contours[{i}]: not a simple loop of >= 3 vertices: {list(c)}")
    return LipRig(markers, contours)


def _rem(raw: Any, i: int) -> RemRegion:
    r = _mapping(raw, f"rem[{i}]")
    name = _choice(r.get("name"), REM_NAMES, f"rem[{i}].name")
    polygon = _indices(r.get("polygon"), f"REM region {name!r} polygon")
    if len(polygon) < 3 or len(set(polygon)) != len(polygon):
        raise ValueError(f"REM region {name!r}: not a simple loop of >= 3 vertices")
    return RemRegion(name, polygon)
