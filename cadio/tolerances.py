"""Every geometric tolerance of mateqa, in one place, each with the reason for its value.

One ``Tolerances`` object is the only route for a tolerance: the nightly flow takes it as a
parameter and hands it to ingest, mates, scenes and capture; the CLI's ``--tol NAME=VALUE``
options and ``--tolerances FILE.json`` map onto it (``with_overrides``); every run writes the
one it used beside its results (``tolerances.json``, and the metadata of the mates tables).
Tests import these objects rather than repeating numbers.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

from cadio.errors import InputFileError
from cadio.inputs import read_text
from cadio.workspace import write_json


@dataclass(frozen=True)
class Tolerances:
    """Tolerances for tessellation, face recognition, the ten spatial relations and face mates.

    Lengths are millimetres, angles degrees unless the name says radians.
    """

    # Tessellation: chordal deviation 0.1 mm keeps the mesh volume within ~1% of the B-rep for
    # parts of a few millimetres and up; 0.5 rad angular deflection bounds the triangle count
    # on small fillets (it drives the count far more than the linear value).
    mesh_linear_mm: float = 0.1
    mesh_angular_rad: float = 0.5
    # ...but never more than this fraction of the part's bbox diagonal: small parts (bearing
    # balls, washers) would otherwise lose several percent of their volume.
    mesh_relative: float = 0.0025
    # ...and never less than this fraction: a 200 m part (a file in metres declared as mm) at
    # 0.1 mm sag becomes millions of triangles and minutes of meshing for no useful accuracy.
    mesh_relative_coarse: float = 0.0005
    # A freeform (B-spline) face is recognised as a plane, cylinder or cone when it fits within
    # 1 micrometre: real files (CAx-IF AS1) store every cylinder as a B-spline.
    freeform_fit_mm: float = 1e-3
    # Directional relations: centre-to-centre direction within 15 degrees of the axis (paper).
    direction_cone_deg: float = 15.0
    # Parallel / perpendicular dominant plane directions (within 1 degree of 0 or 90).
    parallel_deg: float = 1.0
    # A part's dominant plane direction: planar face normals within 1 degree are one direction
    # (sign ignored), and the one carrying the largest planar area is dominant when it carries at
    # least 1.5 times the runner-up's (95% of real parts with planar faces have one; a part
    # whose second direction carries nearly as much has no stable choice).
    dominant_group_deg: float = 1.0
    dominant_area_ratio: float = 1.5
    # Concentric face mates: cylinder and cone axis lines within this angle and distance.
    coaxial_deg: float = 0.5
    coaxial_mm: float = 0.1
    # Coincident estimated without faces (primitives fitted to points have no boundary to
    # intersect): opposed planes of two touching parts within this offset.
    coplanar_mm: float = 0.1
    # Face-level mates: opposite normals (and the semi-angles of two cones of a fit) within 0.5
    # degree, contact within 0.1 mm.
    mate_angle_deg: float = 0.5
    contact_mm: float = 0.1
    # Concentric face mates: coaxial faces of two parts at most this far apart (exact distance):
    # a gland beside a shaft across fillets, a bolt in an ISO 273 medium hole up to M24 (1 mm).
    concentric_gap_mm: float = 1.0
    # A concentric mate is a "fit" when the radii agree within this (the contact tolerance: the
    # faces are one surface), else a "clearance".
    fit_radius_mm: float = 0.1
    # Coincident faces overlap by more than this, mm^2: faces sharing only an edge leave slivers.
    min_overlap_mm2: float = 1e-6
    # Fuzzy value of the Boolean common of two faces laid on one plane, as freeform_fit_mm: a
    # face's group normal is off its own by rounding (PM4 covers: 1e-7 rad), leaving exactly
    # touching faces 1e-5 mm apart and sharing nothing without it; 0.1 mm blurs outlines.
    overlap_fuzzy_mm: float = 1e-3
    # Groups of planar faces by normal direction: directions within this angle are one group.
    group_angle_deg: float = 0.5
    # Voxel grids: the cube's side is the part's largest extent times (1 + margin), so that
    # surface voxels are not cut by the grid's border. The completion's oracle-box grids must
    # share it to be the ingest's truth grids voxel for voxel.
    grid_margin: float = 0.05

    def as_dict(self) -> dict[str, float]:
        """The tolerances as a flat dict, for reports and parquet metadata."""
        return asdict(self)

    def with_overrides(self, overrides: Mapping[str, float | str]) -> Tolerances:
        """These tolerances with some values replaced (values may be numeric strings).

        Raises:
            ValueError: an unknown name (the message lists the known ones) or a value that is
                not a finite, non-negative number.
        """
        known = {f.name for f in fields(self)}
        values: dict[str, float] = {}
        for name, raw in overrides.items():
            if name not in known:
                raise ValueError(f"unknown tolerance {name!r}; known: {', '.join(sorted(known))}")
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise ValueError(f"tolerance {name} must be a number, got {raw!r}") from None
            if not value >= 0.0 or value == float("inf"):
                raise ValueError(f"tolerance {name} must be finite and >= 0, got {raw!r}")
            values[name] = value
        return replace(self, **values)


DEFAULT_TOLERANCES = Tolerances()


def read_tolerances(path: Path) -> Tolerances:
    """Tolerances from a JSON object of overrides (a ``tolerances.json`` of a run reads back).

    Raises:
        ValueError: the file cannot be read, is not a JSON object, or names an unknown
            tolerance or a value that is no finite number >= 0; the message names the file.
    """
    try:
        data = json.loads(read_text(path, "tolerances file", max_bytes=1 << 20))
    except InputFileError as exc:
        raise ValueError(str(exc)) from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: tolerances file is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of tolerance names to values")
    try:
        return DEFAULT_TOLERANCES.with_overrides(data)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def write_tolerances(path: Path, tol: Tolerances) -> None:
    """Write the tolerances a run used, as JSON (atomically)."""
    write_json(path, tol.as_dict())

