"""Every geometric tolerance of mateqa, in one place, each with the reason for its value.

Tests import these objects rather than repeating numbers; reports print them next to results
so that a figure is never separated from the rule that produced it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


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
    # Parallel / perpendicular principal plane directions (within 1 degree of 0 or 90).
    parallel_deg: float = 1.0
    # Concentric principal axes: angle and distance between the axis lines.
    coaxial_deg: float = 0.5
    coaxial_mm: float = 0.1
    # Coincident / coplanar faces: offset between the planes.
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

    def as_dict(self) -> dict[str, float]:
        """The tolerances as a flat dict, for reports and parquet metadata."""
        return asdict(self)


DEFAULT_TOLERANCES = Tolerances()
