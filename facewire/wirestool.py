"""``facewire wires``: extract wire curves from an expression template, and apply them.

    facewire wires extract BASE.obj TEMPLATE.obj -o PARAMS.json [--rig RIG.json]
    facewire wires apply BASE.obj PARAMS.json -o OUT.obj

extract fits the wire parameters of seed 000 (Eq. 12-13) that best turn BASE into
TEMPLATE (same topology); apply deforms BASE with them, keeping its vertex order and UVs.
PARAMS.json ("facewire-wires", version 1) holds, per curve: name, feature, vertex chain,
range r (cm), radial scale s, reference and wire control points (cm, model space); and
globally the localizing k, the vertex count and the RMS fit error (cm).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from facewire.models import bspline
from facewire.models.mesh import FaceMesh, load_obj, save_obj
from facewire.models.wires import WireDeformer

logger = logging.getLogger(__name__)

FORMAT = "facewire-wires"
VERSION = 1


def _check_same_topology(base: FaceMesh, other: FaceMesh, base_name: str, other_name: str) -> None:
    if other.n_vertices != base.n_vertices:
        raise ValueError(
            f"{other_name} has {other.n_vertices} vertices but {base_name} has {base.n_vertices}; "
            "the topologies differ"
        )
    if other.triangles.shape != base.triangles.shape or not np.array_equal(
        other.triangles, base.triangles
    ):
        raise ValueError(
            f"{other_name} and {base_name} have different triangles "
            f"({len(other.triangles)} vs {len(base.triangles)}); the topologies differ"
        )


def params_document(w: WireDeformer, params: np.ndarray, rms_cm: float) -> dict[str, Any]:
    """The PARAMS.json content for wire params (P,) of deformer w."""
    s, _ = w.split_params(params)
    wires = w.wire_control_points(params)
    curves = []
    for j, name in enumerate(w.names):
        curve: dict[str, Any] = {
            "name": name,
            "feature": w.features[j],
            "range": float(w.ranges[j]),
            "s": float(s[j]),
            "reference_control_points": w.reference_control_points[j].tolist(),
            "wire_control_points": wires[j].tolist(),
        }
        if w.chains:
            curve["vertices"] = list(w.chains[j])
        curves.append(curve)
    return {
        "format": FORMAT,
        "version": VERSION,
        "vertex_count": w.n_vertices,
        "k": w.k,
        "fit_rms_cm": rms_cm,
        "curves": curves,
    }


def extract(
    base_obj: str | Path,
    template_obj: str | Path,
    out_json: str | Path,
    rig_path: str | Path | None = None,
) -> dict[str, Any]:
    """Fit wire parameters turning base_obj into template_obj; write and return PARAMS.json."""
    from facewire.models.rig import load_rig

    base = load_obj(base_obj)
    template = load_obj(template_obj)
    _check_same_topology(base, template, str(base_obj), str(template_obj))
    rig = load_rig(rig_path)
    rig.validate(base.n_vertices)
    w = WireDeformer.from_rig(base.vertices, rig)
    params = w.fit(template.vertices)
    rms = w.rms_error(params, template.vertices)
    doc = params_document(w, params, rms)
    try:
        Path(out_json).write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        raise ValueError(f"cannot write {out_json}: {exc.strerror or exc}") from exc
    logger.info("%s: %d wires, fit RMS %.4g cm", out_json, w.n_curves, rms)
    return doc


def _field(obj: Any, key: str, where: str) -> Any:
    if not isinstance(obj, dict) or key not in obj:
        raise ValueError(f"{where}: missing {key!r}")
    return obj[key]


def _finite(x: Any, where: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        raise ValueError(f"{where}: expected a finite number, got {x!r}")
    return float(x)


def _points(x: Any, where: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected a list of [x, y, z] points") from None
    if a.ndim != 2 or a.shape[1] != 3 or len(a) < 4 or not np.isfinite(a).all():
        raise ValueError(f"{where}: expected >= 4 finite [x, y, z] points, got shape {a.shape}")
    return a


def read_params(path: str | Path) -> dict[str, Any]:
    """Read and check PARAMS.json. Returns {"vertex_count", "k", "names", "features",
    "ranges", "s", "reference" [(n_ctrl, 3)], "wire" [(n_ctrl, 3)], "chains"}."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from exc
    try:
        return _parse_params(raw)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


def _parse_params(raw: Any) -> dict[str, Any]:
    if _field(raw, "format", "params") != FORMAT:
        raise ValueError(f"not a {FORMAT} file (format {raw.get('format')!r})")
    if _field(raw, "version", "params") != VERSION:
        raise ValueError(f"unsupported version {raw['version']!r}, expected {VERSION}")
    count = _field(raw, "vertex_count", "params")
    if isinstance(count, bool) or not isinstance(count, int) or count <= 0:
        raise ValueError(f"vertex_count: expected a positive integer, got {count!r}")
    curves = _field(raw, "curves", "params")
    if not isinstance(curves, list) or not curves:
        raise ValueError("curves: expected a non-empty list")
    out: dict[str, Any] = {
        "vertex_count": count,
        "k": _finite(_field(raw, "k", "params"), "k"),
        "names": [],
        "features": [],
        "ranges": [],
        "s": [],
        "reference": [],
        "wire": [],
        "chains": [],
    }
    for i, c in enumerate(curves):
        where = f"curves[{i}]"
        out["names"].append(str(_field(c, "name", where)))
        out["features"].append(str(c.get("feature", "other")))
        out["ranges"].append(_finite(_field(c, "range", where), f"{where}.range"))
        out["s"].append(_finite(_field(c, "s", where), f"{where}.s"))
        ref = _points(_field(c, "reference_control_points", where), f"{where}.reference")
        wire = _points(_field(c, "wire_control_points", where), f"{where}.wire")
        if wire.shape != ref.shape:
            raise ValueError(
                f"{where}: {len(wire)} wire control points for {len(ref)} reference ones"
            )
        out["reference"].append(ref)
        out["wire"].append(wire)
        out["chains"].append(c.get("vertices"))
    return out


def apply(base_obj: str | Path, params_json: str | Path, out_obj: str | Path) -> FaceMesh:
    """Deform base_obj with PARAMS.json and write out_obj (vertex order and UVs of base)."""
    base = load_obj(base_obj)
    doc = read_params(params_json)
    if doc["vertex_count"] != base.n_vertices:
        raise ValueError(
            f"{params_json} was extracted for {doc['vertex_count']} vertices but {base_obj} "
            f"has {base.n_vertices}; the topologies differ"
        )
    w = WireDeformer.from_control_points(
        base.vertices, doc["reference"], doc["ranges"], doc["k"], doc["names"], doc["features"]
    )
    _warn_if_other_base(base, doc, str(base_obj))
    q = [wire - ref for wire, ref in zip(doc["wire"], doc["reference"], strict=True)]
    params = w.join_params(np.asarray(doc["s"]), q)
    out = base.with_vertices(w.deform(params))
    try:
        save_obj(out, out_obj)
    except OSError as exc:
        raise ValueError(f"cannot write {out_obj}: {exc.strerror or exc}") from exc
    return out


def _warn_if_other_base(base: FaceMesh, doc: dict[str, Any], base_name: str) -> None:
    # The reference curves come from the file; a different BASE (say a person-specific
    # model) would move vertices relative to curves that no longer lie on its features.
    for name, chain, ref in zip(doc["names"], doc["chains"], doc["reference"], strict=True):
        try:
            idx = np.asarray(chain, dtype=np.int64)
            fitted = bspline.fit_control_points(base.vertices[idx], len(ref))
        except (ValueError, IndexError, TypeError):
            continue
        dev = float(np.abs(fitted - ref).max())
        if dev > 1e-4:
            logger.warning(
                "%s differs from the base the wires were extracted on "
                "(reference curve %r is %.3g cm off its vertex chain)",
                base_name,
                name,
                dev,
            )
            return


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``wires extract`` and ``wires apply`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "wires",
        help="extract wire curves from an expression template, or apply them",
        description="Seed 000's wires as a tool: extract the wire curves that turn BASE.obj "
        "into an expression TEMPLATE.obj (same topology), or apply them to BASE.obj.",
    )
    sub = p.add_subparsers(dest="wires_command", required=True)

    ex = sub.add_parser("extract", help="fit wire parameters turning BASE into TEMPLATE")
    ex.add_argument("base", metavar="BASE.obj")
    ex.add_argument("template", metavar="TEMPLATE.obj", help="same topology as BASE")
    ex.add_argument("-o", "--output", metavar="PARAMS.json", required=True)
    ex.add_argument("--rig", metavar="RIG.json", help="rig file (default: the bundled rig)")

    def run_extract(args: argparse.Namespace) -> int:
        doc = extract(args.base, args.template, args.output, args.rig)
        print(f"{args.output}: {len(doc['curves'])} wires, fit RMS {doc['fit_rms_cm']:.4g} cm")
        return 0

    ex.set_defaults(func=run_extract)

    ap = sub.add_parser("apply", help="deform BASE with PARAMS.json")
    ap.add_argument("base", metavar="BASE.obj")
    ap.add_argument("params", metavar="PARAMS.json")
    ap.add_argument("-o", "--output", metavar="OUT.obj", required=True)

    def run_apply(args: argparse.Namespace) -> int:
        mesh = apply(args.base, args.params, args.output)
        print(f"{args.output}: {mesh.n_vertices} vertices")
        return 0

    ap.set_defaults(func=run_apply)
