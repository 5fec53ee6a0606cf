"""Surface and volume integrals of B-spline faces, vectorised, from the exact B-rep.

OpenCascade's adaptive integration (``BRepGProp`` with a relative eps of 1e-6) is slow on
B-spline faces with many knot spans (seconds for one face of 212 spans), and it is run twice per
face: once for the part's volume and once for the face's area. Its eps is an estimate, not a
bound: on 87 of 774 real B-spline faces its area differs from this module's by more than 1e-6,
by up to 1.1e-3 on rational patches whose weights spread 9:1, and its own result moves to this
module's as its eps shrinks (``bench/speed/integrals.py``). Its fixed Gauss rule is faster
but off by up to ~2e-2 on real faces. This module integrates the same quantities from
the same exact geometry in one pass, with NumPy:

* the NURBS surface is evaluated from its poles, weights and knots (point and first
  derivatives, vectorised over all quadrature points);
* the trimmed parameter domain is handled with Green's theorem, as OpenCascade does: the
  double integral of g over the domain is the boundary integral of G dv, G(u, v) being the
  integral of g from the first u parameter to u (inner along u, as OpenCascade's: where a
  curve on the face strays from its 3D edge within tolerance, both see the same domain; the
  other way round a real face differed by 9e-6). The outer integral runs along every edge's
  curve on the face, split at its knots and where it crosses a v knot; the inner one is split
  at the u knots; each piece takes a Gauss-Legendre rule;
* a pass is accepted when the pass before it, with a lower-order rule on the same pieces,
  agrees with it within ``REL_TOL`` (the lower order errs far more, so the difference bounds
  the error of the higher); the orders rise 6, 8, 12, then every piece is halved and the
  ladder starts again (after ``_LEVELS`` halvings ``face_integrals`` returns None, and the
  caller falls back to OpenCascade's adaptive rule). A pass costs the square of its points
  per piece (outer points times inner points): a pass of order 12 costs 2.25 times one of
  order 8, one with halved pieces 4 times.

Per face, with N = S_u x S_v oriented as the face: area, the area's first moments, the volume
term (S . N) / 3 and the volume's first moments S (S . N) / 4: the volume and first moment of
the cone from the origin over the face, which sum to the solid's over its closed boundary
(OpenCascade's ``BRepGProp_Vinert`` computes the same cones).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from OCP.BRep import BRep_Tool
from OCP.BRepAdaptor import BRepAdaptor_Curve2d
from OCP.Geom import Geom_BSplineSurface
from OCP.GeomAbs import (
    GeomAbs_BSplineCurve,
    GeomAbs_BSplineSurface,
)
from OCP.GeomAdaptor import GeomAdaptor_Surface
from OCP.gp import gp_Pnt2d, gp_Vec2d
from OCP.TopAbs import TopAbs_EDGE, TopAbs_REVERSED
from OCP.TopExp import TopExp_Explorer
from OCP.TopoDS import TopoDS, TopoDS_Face

from cadio.records import FloatArray

# Agreement asked between a pass and the pass with every piece halved (relative to the
# face's own scale): below OpenCascade's adaptive eps of 1e-6, whose results it replaces.
REL_TOL = 1e-8
_PIECES = 1  # first pass: pieces per interval (each next level halves them)
_LEVELS = 3  # levels after the first before giving up
_CHUNK = 200_000  # quadrature points evaluated at once (memory: ~1 KB per point)
# Gauss-Legendre rules (nodes on [-1, 1], weights) of rising order tried on the same pieces:
# each result is checked against the one before it.
_RULES = tuple(np.polynomial.legendre.leggauss(n) for n in (6, 8, 12))
Rule = tuple[FloatArray, FloatArray]
# An edge whose v spread times its total dv is below this share of the squared v range runs
# along u (the error of treating it so is of that relative order).
_ISO = 1e-9

# Quantities integrated per face (the order of face_integrals' result).
AREA, AREA_MOMENT, VOLUME, VOLUME_MOMENT = 0, slice(1, 4), 4, slice(5, 8)


class _Nurbs:
    """A B-spline surface in arrays: homogeneous poles, flat knots, degrees."""

    def __init__(self, surface: Geom_BSplineSurface, origin: FloatArray) -> None:
        self.origin = origin
        # A periodic direction: parameters are brought into the first period [lo, lo + T)
        # before evaluation, on the non-periodic form of the surface (the same there); the
        # breaks repeat every period (a face may straddle the period's end).
        u0, u1, v0, v1 = surface.Bounds()
        u_period = u1 - u0 if surface.IsUPeriodic() else 0.0
        v_period = v1 - v0 if surface.IsVPeriodic() else 0.0
        u_knots = _array(surface.UKnots())
        v_knots = _array(surface.VKnots())
        s = surface.Copy()
        if s.IsUPeriodic():
            s.SetUNotPeriodic()
        if s.IsVPeriodic():
            s.SetVNotPeriodic()
        nu, nv = s.NbUPoles(), s.NbVPoles()
        poles = s.Poles()
        weights = s.Weights() if (s.IsURational() or s.IsVRational()) else None
        hom = np.empty((nu, nv, 4))
        for i in range(1, nu + 1):
            for j in range(1, nv + 1):
                p = poles.Value(i, j)
                w = weights.Value(i, j) if weights is not None else 1.0
                hom[i - 1, j - 1] = (p.X() * w, p.Y() * w, p.Z() * w, w)
        self.p, self.q = s.UDegree(), s.VDegree()
        self.tu = _array(s.UKnotSequence())
        self.tv = _array(s.VKnotSequence())
        self.u_knots, self.v_knots = np.unique(u_knots), np.unique(v_knots)
        self.u_period, self.v_period, self.u_lo, self.v_lo = u_period, v_period, u0, v0
        self.hom = hom
        self.row_size = nu  # values per row of ``rows`` (memory of the inner chunks)

    def breaks(self, inner: bool, lo: float, hi: float) -> FloatArray:
        """The knots of one direction (u if ``inner``), repeated over [lo, hi] if periodic."""
        knots, period, first = ((self.u_knots, self.u_period, self.u_lo) if inner else
                                (self.v_knots, self.v_period, self.v_lo))
        if not period:
            return knots
        k0, k1 = int(np.floor((lo - first) / period)), int(np.ceil((hi - first) / period))
        return np.unique(np.concatenate([knots + k * period for k in range(k0, k1 + 1)]))

    def rows(self, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The surface's u-curves at each v: their homogeneous poles and those poles'
        derivatives in v, each (len(v), u poles, 4). A tensor-product surface is a curve in u
        at fixed v, so every point of one inner integral (all at one v) evaluates from one row.
        """
        if self.v_period:
            v = self.v_lo + np.mod(v - self.v_lo, self.v_period)
        sv, nv, dnv = _basis(self.tv, self.q, self.hom.shape[1], v)
        iv = sv[:, None] - self.q + np.arange(self.q + 1)
        block = self.hom[:, iv]  # (u poles, m, q+1, 4)
        return (np.einsum("mb,ambk->mak", nv, block), np.einsum("mb,ambk->mak", dnv, block))

    def along_rows(self, u: FloatArray, row: Any, poles: FloatArray, dpoles: FloatArray
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """S, S_u, S_v at the points (u[k], v of row[k]), each (n, 3), from ``rows``."""
        if self.u_period:
            u = self.u_lo + np.mod(u - self.u_lo, self.u_period)
        su, nu, dnu = _basis(self.tu, self.p, self.hom.shape[0], u)
        iu = su[:, None] - self.p + np.arange(self.p + 1)
        q = poles[row[:, None], iu]  # (n, p+1, 4)
        a = np.einsum("na,nak->nk", nu, q)
        au = np.einsum("na,nak->nk", dnu, q)
        av = np.einsum("na,nak->nk", nu, dpoles[row[:, None], iu])
        w = a[:, 3:]
        s = a[:, :3] / w
        return s, (au[:, :3] - s * au[:, 3:]) / w, (av[:, :3] - s * av[:, 3:]) / w


def _array(values: Any) -> FloatArray:
    return np.array([values.Value(i) for i in range(values.Lower(), values.Upper() + 1)])


def _basis(t: FloatArray, p: int, n_poles: int, x: FloatArray
           ) -> tuple[Any, FloatArray, FloatArray]:
    """Span index, the p + 1 non-zero basis functions and their derivatives at each x."""
    span = np.clip(np.searchsorted(t, x, side="right") - 1, p, n_poles - 1)
    n = np.zeros((len(x), p + 1))
    n[:, 0] = 1.0
    left = np.zeros((len(x), p + 1))
    right = np.zeros((len(x), p + 1))
    lower = n[:, :1].copy()
    for j in range(1, p + 1):
        left[:, j] = x - t[span + 1 - j]
        right[:, j] = t[span + j] - x
        saved = np.zeros(len(x))
        for r in range(j):
            denom = right[:, r + 1] + left[:, j - r]
            temp = np.divide(n[:, r], denom, out=np.zeros(len(x)), where=denom != 0)
            n[:, r] = saved + right[:, r + 1] * temp
            saved = left[:, j - r] * temp
        n[:, j] = saved
        if j == p - 1:
            lower = n[:, :p].copy()
    d = np.zeros_like(n)
    for k in range(p + 1):
        i = span - p + k
        if k >= 1:
            den = t[i + p] - t[i]
            d[:, k] += np.divide(p * lower[:, k - 1], den, out=np.zeros(len(x)), where=den != 0)
        if k <= p - 1:
            den = t[i + p + 1] - t[i + 1]
            d[:, k] -= np.divide(p * lower[:, k], den, out=np.zeros(len(x)), where=den != 0)
    return span, n, d


def _integrand(nurbs: _Nurbs, evaluated: tuple[FloatArray, FloatArray, FloatArray],
               sign: float) -> FloatArray:
    """The eight integrands at evaluated points (S, S_u, S_v), (n, 8), per unit du dv, points
    relative to ``nurbs.origin``."""
    s, su, sv = evaluated
    s = s - nurbs.origin
    normal = sign * np.cross(su, sv)
    jac = np.linalg.norm(normal, axis=1)
    out = np.empty((len(s), 8))
    out[:, AREA] = jac
    out[:, AREA_MOMENT] = s * jac[:, None]
    height = np.einsum("nk,nk->n", s, normal)
    out[:, VOLUME] = height / 3.0
    out[:, VOLUME_MOMENT] = s * height[:, None] / 4.0
    return out


@dataclass(frozen=True, eq=False)
class _Edge:
    """One edge's curve on the face, where its outer integrand may lose smoothness, and the
    sign of its traversal."""

    curve: BRepAdaptor_Curve2d
    breaks: FloatArray
    direction: float


def _edges(face: TopoDS_Face, nurbs: _Nurbs) -> list[_Edge] | None:
    """The face's boundary edges, or None when it has none or one is unbounded."""
    edges = []
    explorer = TopExp_Explorer(face, TopAbs_EDGE)
    while explorer.More():
        edge = TopoDS.Edge_s(explorer.Current())
        explorer.Next()
        curve = BRepAdaptor_Curve2d(edge, face)
        a, b = curve.FirstParameter(), curve.LastParameter()
        if not (np.isfinite(a) and np.isfinite(b)) or b <= a:
            return None
        edges.append(_Edge(curve, _edge_breaks(curve, a, b, nurbs),
                           -1.0 if edge.Orientation() == TopAbs_REVERSED else 1.0))
    return edges or None


def _boundary(edges: Sequence[_Edge], pieces: int, rule: Rule
              ) -> tuple[list[FloatArray], list[FloatArray], list[FloatArray]]:
    """Outer quadrature points on the face's boundary, per edge: u, v and weight * dv/dt."""
    us, vs, ws = [], [], []
    p, d = gp_Pnt2d(), gp_Vec2d()
    for edge in edges:
        ts, tw = _pieces(edge.breaks, pieces, rule)
        pts = np.empty((len(ts), 3))
        for k, t in enumerate(ts):
            edge.curve.D1(float(t), p, d)
            pts[k] = (p.X(), p.Y(), d.Y())
        us.append(pts[:, 0])
        vs.append(pts[:, 1])
        ws.append(edge.direction * tw * pts[:, 2])
    return us, vs, ws


def _edge_breaks(curve: BRepAdaptor_Curve2d, a: float, b: float, nurbs: _Nurbs,
                 ) -> FloatArray:
    """Where the outer integrand may lose smoothness: the curve's knots and its v-knot
    crossings (found on a sampling, refined by bisection)."""
    breaks = [a, b]
    if curve.GetType() == GeomAbs_BSplineCurve:
        knots = _array(curve.BSpline().Knots())
        breaks += [k for k in knots if a < k < b]
    def outer(t: float) -> float:
        point = curve.Value(t)
        return float(point.Y())

    ts = np.linspace(a, b, 33)
    vv = np.array([outer(float(t)) for t in ts])
    for knot in nurbs.breaks(False, float(vv.min()), float(vv.max())):
        side = np.sign(vv - knot)
        for k in np.nonzero(side[:-1] * side[1:] < 0)[0]:
            lo, hi = ts[k], ts[k + 1]
            for _ in range(50):
                mid = 0.5 * (lo + hi)
                if np.sign(outer(mid) - knot) == side[k]:
                    lo = mid
                else:
                    hi = mid
            breaks.append(0.5 * (lo + hi))
    return np.unique(np.array(breaks))


def _pieces(breaks: FloatArray, pieces: int, rule: Rule) -> tuple[FloatArray, FloatArray]:
    """Gauss points and weights over [breaks[0], breaks[-1]], ``pieces`` per break interval."""
    edges = np.concatenate([np.linspace(lo, hi, pieces + 1)[:-1]
                            for lo, hi in itertools.pairwise(breaks)]
                           + [breaks[-1:]])
    lo, hi = edges[:-1, None], edges[1:, None]
    half = 0.5 * (hi - lo)
    gx, gw = rule
    return (lo + half * (1.0 + gx)).ravel(), (half * gw).ravel()


def _u_breaks(nurbs: _Nurbs, u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The u breaks from the first u parameter up to the points' largest u, and the points'
    u (none below the first)."""
    start = nurbs.u_lo
    knots = nurbs.breaks(True, min(start, float(u.min())), max(start, float(u.max())))
    knots = knots[knots >= start]
    if knots[0] > start:
        knots = np.concatenate([[start], knots])
    return knots, np.maximum(u, start)


def _inner(nurbs: _Nurbs, u: FloatArray, v: FloatArray, sign: float, pieces: int, rule: Rule
           ) -> FloatArray:
    """G(u_k, v_k): the integrands integrated in u from the first u knot to u_k, (n, 8)."""
    knots, top = _u_breaks(nurbs, u)
    # per outer point k and span j: [knots[j], min(knots[j + 1], u_k)], kept where not empty
    lo = np.broadcast_to(knots[:-1], (len(u), len(knots) - 1))
    hi = np.minimum(knots[1:], top[:, None])
    row, col = np.nonzero(hi > lo)
    lo_a, hi_a = lo[row, col], hi[row, col]
    if pieces > 1:
        frac = np.arange(pieces + 1) / pieces
        cuts = lo_a[:, None] + (hi_a - lo_a)[:, None] * frac
        lo_a, hi_a, row = cuts[:, :-1].ravel(), cuts[:, 1:].ravel(), np.repeat(row, pieces)
    gx, gw = rule
    half = 0.5 * (hi_a - lo_a)
    s = (lo_a[:, None] + half[:, None] * (1.0 + gx)).ravel()
    w = (half[:, None] * gw).ravel()
    owner = np.repeat(row, len(gx))  # ascending: np.nonzero walks row by row
    out = np.zeros((len(u), 8))
    # outer points a chunk at a time: their rows (~u poles x 4 KB each), then their inner points
    step = max(1, _CHUNK // (8 * nurbs.row_size))
    for first in range(0, len(u), step):
        last = min(len(u), first + step)
        at = slice(*np.searchsorted(owner, [first, last]))
        poles, dpoles = nurbs.rows(v[first:last])
        local = owner[at] - first
        vals = _integrand(nurbs, nurbs.along_rows(s[at], local, poles, dpoles), sign) * w[at, None]
        for k in range(8):
            out[first:last, k] += np.bincount(local, vals[:, k], minlength=last - first)
    return out


def _inner_iso(nurbs: _Nurbs, u: FloatArray, v0: float, sign: float, pieces: int, rule: Rule
               ) -> FloatArray:
    """G(u_k, v0) for points on one iso-v line: span integrals once, summed up to each u_k,
    plus the part of u_k's own span."""
    knots, top = _u_breaks(nurbs, u)
    knots = knots[knots <= top.max()]
    spans = _integrate_u(nurbs, knots[:-1], knots[1:], v0, sign, pieces, rule)
    cum = np.concatenate([np.zeros((1, 8)), np.cumsum(spans, axis=0)])
    j = np.clip(np.searchsorted(knots, top, side="right") - 1, 0, len(knots) - 1)
    out: FloatArray = cum[j] + _integrate_u(nurbs, knots[j], top, v0, sign, pieces, rule)
    return out


def _integrate_u(nurbs: _Nurbs, lo: FloatArray, hi: FloatArray, v0: float, sign: float,
                 pieces: int, rule: Rule) -> FloatArray:
    """The integrands integrated in u over each [lo_k, hi_k] at v = v0, (n, 8)."""
    n = len(lo)
    if n == 0:
        return np.zeros((0, 8))
    frac = np.arange(pieces + 1) / pieces
    cuts = lo[:, None] + (hi - lo)[:, None] * frac
    a, b = cuts[:, :-1].ravel(), cuts[:, 1:].ravel()
    gx, gw = rule
    half = 0.5 * (b - a)
    x = (a[:, None] + half[:, None] * (1.0 + gx)).ravel()
    w = (half[:, None] * gw).ravel()
    poles, dpoles = nurbs.rows(np.array([v0]))
    evaluated = nurbs.along_rows(x, np.zeros(len(x), dtype=np.int64), poles, dpoles)
    vals = _integrand(nurbs, evaluated, sign) * w[:, None]
    out: FloatArray = vals.reshape(n, pieces * len(gx), 8).sum(axis=1)
    return out


def _once(edges: Sequence[_Edge], nurbs: _Nurbs, sign: float, pieces: int, rule: Rule
          ) -> FloatArray | None:
    us, vs, ws = _boundary(edges, pieces, rule)
    u, v, w = np.concatenate(us), np.concatenate(vs), np.concatenate(ws)
    # The traversal's sense: the signed parameter area (integral of u dv) must be positive.
    uv_area = float(np.dot(u - nurbs.u_lo, w))
    if uv_area == 0.0:
        return None
    v_range = float(np.ptp(v)) or 1.0
    # Treating an edge as iso-v errs by at most (its v spread) x (its total dv) x dG/dv.
    iso = [float(np.ptp(ev)) * float(np.abs(ew).sum()) <= _ISO * v_range ** 2
           for ev, ew in zip(vs, ws, strict=True)]
    total = np.zeros(8)
    for eu, ev, ew, flat in zip(us, vs, ws, iso, strict=True):
        if flat:
            # An edge along u (v constant up to its curve's wobble): G(., v) there is one
            # function of u, integrated once along the knot spans (the wobble's effect is
            # of second order in it).
            total += (_inner_iso(nurbs, eu, float(ev.mean()), sign, pieces, rule)
                      * ew[:, None]).sum(axis=0)
    mask = np.repeat(np.logical_not(iso), [len(eu) for eu in us])
    if mask.any():
        g = _inner(nurbs, u[mask], v[mask], sign, pieces, rule)
        total += (g * w[mask, None]).sum(axis=0)
    return total if uv_area > 0 else -total


def face_integrals(face: TopoDS_Face, origin: FloatArray | None = None) -> FloatArray | None:
    """The eight integrals of one B-spline face (see the module doc), or None.

    Args:
        face: a face of a solid, oriented as in the solid.
        origin: the point (3,) the moments and the volume term are taken about (default 0).

    Returns:
        (8,) float64, or None: the face is not a B-spline face, its domain is unusual (no
        edges, infinite parameters), or no two successive passes agree within ``REL_TOL``; the
        caller then uses OpenCascade's adaptive rule.
    """
    adaptor = GeomAdaptor_Surface(BRep_Tool.Surface_s(face))  # located: the file's frame
    if adaptor.GetType() != GeomAbs_BSplineSurface:
        return None
    nurbs = _Nurbs(adaptor.BSpline(), np.zeros(3) if origin is None else np.asarray(origin))
    sign = -1.0 if face.Orientation() == TopAbs_REVERSED else 1.0
    edges = _edges(face, nurbs)
    if edges is None:
        return None
    pieces = _PIECES
    for _ in range(_LEVELS + 1):
        check = _once(edges, nurbs, sign, pieces, _RULES[0])
        for rule in _RULES[1:]:
            result = _once(edges, nurbs, sign, pieces, rule)
            if result is None or check is None:
                return None
            area = abs(result[AREA])
            if not area > 0:
                return None
            # Tolerances on the face's own scales: its area, its reach from the origin.
            reach = float(np.abs(result[AREA_MOMENT]).max() / area) + np.sqrt(area)
            tol = REL_TOL * area * np.array([1.0, *(3 * [reach]), reach, *(3 * [reach * reach])])
            if np.all(np.abs(check - result) <= tol):
                return result
            check = result
        pieces *= 2
    return None
