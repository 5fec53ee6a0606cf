"""Benchmark: what the exact integrals of ingest cost, and what the cheaper routes would lose.

Command (from the repository root)::

    PYTHONPATH=$PWD .venv/bin/python bench/speed/integrals.py [STEP_DIR]

Ingest integrates every solid's volume and centroid and every face's area and centroid
(``part_integrals`` with OpenCascade's relative eps 1e-6; the ground truth's face mates and
part relations are made of them). On the real library this is the largest stage of a worker's
job, larger than the STEP read. Printed, all on the same solids in this one process (CPU time):

1. the product's route, the reference;
2. the same with a looser eps (1e-5, 1e-4, 1e-3);
3. OpenCascade's fixed-order rule (no eps) on the faces the product gives OpenCascade;
   the NumPy quadrature on every B-spline face (the adaptive rule on the others);
4. per B-spline face, the adaptive rule's area against the NumPy quadrature's of
   ``face_integrals`` (which the product uses only on many-span rational faces): the faces
   whose areas differ, and for the worst the adaptive rule's own result as its eps shrinks (it
   moves towards the NumPy value: eps 1e-6 does not hold on them).

For each route: seconds, and the largest error against the reference: solid volume (relative),
solid centroid (relative to the cube root of the volume), face area (relative) and face
centroid (mm).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DIR = REPO.parent / "shared" / "data" / "step"


def _fixed_rule_terms(face, origin):  # type: ignore[no-untyped-def]
    """The eight terms of ``_occt_terms`` from OpenCascade's fixed-order rule (no eps)."""
    from OCP.BRepGProp import BRepGProp, BRepGProp_Domain, BRepGProp_Face, BRepGProp_Vinert
    from OCP.gp import gp_Pnt
    from OCP.GProp import GProp_GProps
    from OCP.TopoDS import TopoDS_Iterator

    out = np.zeros(8)
    sprops = GProp_GProps()
    BRepGProp.SurfaceProperties_s(face, sprops)
    c = sprops.CentreOfMass()
    out[0] = sprops.Mass()
    out[1:4] = out[0] * (np.array([c.X(), c.Y(), c.Z()]) - origin)
    vprops = BRepGProp_Vinert()
    vprops.SetLocation(gp_Pnt(*origin))
    if TopoDS_Iterator(face).More():
        vprops.Perform(BRepGProp_Face(face, True), BRepGProp_Domain(face))
    else:
        vprops.Perform(BRepGProp_Face(face, True))
    vc = vprops.CentreOfMass()
    out[4] = vprops.Mass()
    out[5:8] = out[4] * (np.array([vc.X(), vc.Y(), vc.Z()]) - origin)
    return out


def _mixed(shape, faces, numpy_on, other):  # type: ignore[no-untyped-def]
    """``part_integrals`` with the NumPy quadrature on the faces ``numpy_on`` picks and
    ``other(face, origin)`` (eight terms) on the rest and where the quadrature declines."""
    from cadio.cad.integrate import face_integrals
    from cadio.cad.solid_props import _vertex_mean, summed

    origin = _vertex_mean(shape)
    terms = []
    for face in faces:
        got = face_integrals(face, origin) if numpy_on(face) else None
        terms.append(other(face, origin) if got is None else got)
    return summed(origin, terms)


def _is_bspline(face) -> bool:  # type: ignore[no-untyped-def]
    from OCP.BRep import BRep_Tool
    from OCP.GeomAbs import GeomAbs_BSplineSurface
    from OCP.GeomAdaptor import GeomAdaptor_Surface

    return bool(GeomAdaptor_Surface(BRep_Tool.Surface_s(face)).GetType()
                == GeomAbs_BSplineSurface)


def _errors(got, ref) -> tuple[float, float, float, float]:  # type: ignore[no-untyped-def]
    vol = cen = area = fcen = 0.0
    for a, b in zip(got, ref, strict=True):
        size = abs(b.volume) ** (1 / 3)
        vol = max(vol, abs(a.volume - b.volume) / abs(b.volume))
        cen = max(cen, float(np.linalg.norm(a.centroid - b.centroid)) / size)
        for (fa, fc), (ra, rc) in zip(a.face_props, b.face_props, strict=True):
            area = max(area, abs(fa - ra) / max(ra, 1e-12))
            fcen = max(fcen, float(np.linalg.norm(fc - rc)))
    return vol, cen, area, fcen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step_dir", nargs="?", type=Path, default=DEFAULT_DIR)
    args = parser.parse_args()
    if not args.step_dir.is_dir():
        sys.exit(f"no STEP library at {args.step_dir}")

    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    from cadio.cad.faces import indexed_faces
    from cadio.cad.ingest import discover
    from cadio.cad.solid_props import _occt_terms, part_integrals, prefer_numpy
    from cadio.cad.step import read_step
    from cadio.cad.tessellate import MASS_PROPS_REL_EPS

    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # OpenCascade's parser chatter
    out = sys.stderr
    shapes, names = [], []
    for found in discover(args.step_dir):
        try:
            solids = read_step(found.path)
            shapes += [s.shape for s in solids]
            names += [f"{found.path.name} solid {s.info.index}" for s in solids]
        except Exception as exc:  # a bad file: ingest reports it; skipped here
            print(f"skipped {found.path.name}: {exc}", file=out)
    faces = [indexed_faces(s) for s in shapes]
    print(f"{len(shapes)} solids, {sum(map(len, faces))} faces", file=out)

    def timed(route):  # type: ignore[no-untyped-def]
        start = time.process_time()
        result = [route(s, f) for s, f in zip(shapes, faces, strict=True)]
        return time.process_time() - start, result

    seconds, ref = timed(lambda s, f: part_integrals(s, f, MASS_PROPS_REL_EPS))
    print(f"{'route':28s} {'CPU s':>7s} {'volume':>9s} {'centroid':>9s} {'area':>9s} "
          f"{'face c mm':>9s}", file=out)
    print(f"{'product (eps 1e-6)':28s} {seconds:7.2f} {'ref':>9s} {'ref':>9s} {'ref':>9s} "
          f"{'ref':>9s}", file=out)
    routes = [(f"looser eps {eps:g}", lambda s, f, e=eps: part_integrals(s, f, e))
              for eps in (1e-5, 1e-4, 1e-3)]
    routes.append(("fixed-order rule (no eps)",
                   lambda s, f: _mixed(s, f, prefer_numpy, _fixed_rule_terms)))
    routes.append(("NumPy on every B-spline face", lambda s, f: _mixed(
        s, f, _is_bspline, lambda face, o: _occt_terms(face, o, MASS_PROPS_REL_EPS))))
    results = {}
    for name, route in routes:
        seconds, got = timed(route)
        results[name] = got
        print(f"{name:28s} {seconds:7.2f} " + " ".join(f"{e:9.2g}" for e in _errors(got, ref)),
              file=out)

    # Face by face, the B-spline faces the product leaves to the adaptive rule: its areas (the
    # reference) against the NumPy route's.
    differ = []
    for name, shape_faces, occt, numpy in zip(
            names, faces, ref, results["NumPy on every B-spline face"], strict=True):
        for index, face in enumerate(shape_faces):
            if _is_bspline(face) and not prefer_numpy(face):
                a_occt, a_numpy = occt.face_props[index][0], numpy.face_props[index][0]
                differ.append((abs(a_numpy - a_occt) / max(a_occt, 1e-12), name, index, a_occt,
                               a_numpy, face))
    differ.sort(key=lambda d: -d[0])
    print(f"\n{len(differ)} B-spline faces OpenCascade integrates in the product: areas differ "
          f"from the NumPy quadrature's by more than 1e-6 (relative) on "
          f"{sum(d[0] > 1e-6 for d in differ)}, by more than 1e-4 on "
          f"{sum(d[0] > 1e-4 for d in differ)}; the largest:", file=out)
    for rel, name, index, a_occt, a_numpy, face in differ[:4]:
        tighter = []
        for eps in (1e-8, 1e-10):  # the adaptive rule's own result as its eps shrinks
            props = GProp_GProps()
            BRepGProp.SurfaceProperties_s(face, props, eps)
            tighter.append(f"eps {eps:g}: {props.Mass():.6f}")
        print(f"  {name} face {index}: NumPy {a_numpy:.6f} mm^2; adaptive rule eps 1e-6: "
              f"{a_occt:.6f} ({rel:.2g} off), " + ", ".join(tighter), file=out)


if __name__ == "__main__":
    main()
