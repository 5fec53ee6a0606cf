"""The ``geometric`` baseline: fixed tests on a pair's evidence, and the evidence the relation
networks read.

The tests decide the symmetric relations on the pair evidence of
``cadio.evidence.pair_features`` (each the CAD definition, its tolerances widened by what the
points resolve) and the directional ones on the clouds' centroids, with the truth's own cones.

A network may read the four symmetric answers beside the encoded evidence
(``network_evidence``). Where the evidence is exact (the CAD samples of the ``truth`` input,
whose normals are their faces'), the answers are the CAD's own tests on it: a network trained
on a few hundred assemblies learns from them where its thresholds on the raw evidence would not
reach unseen parts (held-out assemblies: ltn on ``truth`` 0.798 -> 0.844 mean F1, see the
relation card).

Every network also reads the direction from b's centre to a's in the observer frame
(``PAIR_DIRECTION``: the unit vector times ``DIRECTION_GAIN``): the directional relations are
15 degree cones about it, a threshold on one of its coordinates. From the two clouds alone a
network placed those cones a few degrees wide of the truth (held-out assemblies, ltn on
``truth``: 94% of the clear pairs right on above and below). A cone's edge is a coordinate of
0.966, and a degree moves it by 0.005: read as the unit vector, the edges stayed degrees wide
at Adam's step sizes; ten times it raised ltn on ``truth`` from 0.933 to 0.945 validation
mean F1 (see the relation card). A part's centre is the centroid of its solid where the
input knows the solid (``truth``: the CAD's), else the mean of its points.

Beside the direction, each axis's cone codes (``PAIR_CONES``, ``cone_codes``): how far inside
the truth's cone about either end of the axis the direction lies, crossing 1 on the cone's
edge over a few degrees. With the direction alone the networks' cones stayed a few degrees
wide (held-out assemblies, ltn on ``truth``: clear pairs 16 to 20 degrees off the vertical
called above or below, 96.5% and 95.8% right); with the codes every clear pair of the six
directional relations was right (see the relation card). The direction and the codes are
ordered: the swapped pair reads them negated (``swap_evidence``, ``ORDERED_COLUMNS``).

``network_evidence`` gives every column of ``EVIDENCE``; a network reads the columns its config
names (``RelationConfig.evidence``; checkpoints from before the names read the first
``pair_features`` columns). A network of ``completed`` reads the observed points of the same
view and their evidence, beside the completion's evidence (``RelationInput.observed_by``,
``with_observed``: ``ALL_EVIDENCE``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.evidence.pair_features import (
    FAR_MM,
    PAIR_FEATURES,
    encode_features,
    pair_features_many,
)
from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import directional_truth
from models.relation_inputs import INPUTS

__all__ = ["ALL_EVIDENCE", "ANSWER_GAINS", "CONE_SOFTNESS_DEG",
           "DIRECTION_GAIN", "EVIDENCE", "GEOMETRIC_ANSWERS",
           "OBSERVED_PREFIX", "OBSERVER_VIEW_AXIS", "ORDERED_COLUMNS", "PAIR_CONES",
           "PAIR_DIRECTION", "POSE_LENGTHS", "GeometricTests", "cone_codes", "evidence_gains",
           "evidence_names", "geometric_decisions", "geometric_symmetric", "network_evidence",
           "pair_direction", "reads_observed", "swap_evidence", "tests_for", "with_observed",
           "within_pose"]

# In the observer frame the view axis is +Y (behind), whatever the camera.
OBSERVER_VIEW_AXIS = (0.0, 1.0, 0.0)
# The names of the tests' answers in a network's evidence, after ``PAIR_FEATURES``.
GEOMETRIC_ANSWERS = ("geometric_parallel", "geometric_perpendicular", "geometric_concentric",
                     "geometric_coincident")
# The networks of the exact inputs (``RelationInput.exact``) are trained to read the answers.
# On ``completed`` the answers of fits to voxel surfaces added nothing (held-out mean F1 0.619
# with them, 0.621 without), so those networks read the evidence alone.
# Their gains where they read them (``RelationConfig.evidence_gains``). The coincident answer
# reads at 10: at 1 the ``truth`` ltn called a stacked pair 0.42 mm apart coincident on 8 of 8
# held-out views (clear-pair coincident 98.7%); at 10, 100% and 99.9% (seeds 0 and 1). The
# concentric answer stays at 1: at 10 it cost held-out clear-pair concentric 2-7 points (the
# exact coaxial test errs on 1.6% of those pairs).
ANSWER_GAINS = (("geometric_coincident", 10.0),)
# The unit vector from b's centre to a's in the observer frame (right, behind, up): ordered.
PAIR_DIRECTION = ("direction_right", "direction_behind", "direction_up")
DIRECTION_GAIN = 10.0  # the direction's scale in the evidence (the unit vector's edges blur)
# Each axis's cones read at the truth's own half-angle (``cone_codes``), in ``PAIR_DIRECTION``'s
# axis order: ordered too.
PAIR_CONES = ("cone_right", "cone_behind", "cone_up")
CONE_SOFTNESS_DEG = 2.0  # a cone code moves across its edge over about this many degrees
# Every column ``network_evidence`` gives, in order.
EVIDENCE = (*PAIR_FEATURES, *GEOMETRIC_ANSWERS, *PAIR_DIRECTION, *PAIR_CONES)
# An input's networks may read the observed points (``partial``) of the same view and their
# evidence, beside the input's own evidence (``RelationInput.observed_by``, ``with_observed``):
# a network reading any observed column reads the observed points, not its input's
# (``reads_observed``). A completion gives the hidden side, but as voxel centres where the
# camera saw fine points: on its own points and evidence ltn found perpendicular mates of the
# held-out assemblies at F1 0.09-0.11 (two seeds), reading both 0.36 (validation mean F1
# 0.780 -> 0.795; relation card).
OBSERVED_PREFIX = "observed_"
# Every column a network may read: the input's own evidence, then the observed points'.
ALL_EVIDENCE = (*EVIDENCE, *(OBSERVED_PREFIX + n for n in EVIDENCE))
# The ordered columns: odd in the direction, so the swapped pair (b, a) reads them negated.
ORDERED_COLUMNS = [ALL_EVIDENCE.index(p + n) for p in ("", OBSERVED_PREFIX)
                   for n in (*PAIR_DIRECTION, *PAIR_CONES)]


def evidence_names(input_name: str) -> list[str]:
    """The evidence a network of one input is trained to read (``ALL_EVIDENCE`` names): its
    own (the tests' answers where the input is exact), then the observed points' where it
    reads them (``RelationInput.observed_by``)."""
    spec = INPUTS.get(input_name)
    answers = GEOMETRIC_ANSWERS if spec.exact else ()
    own = [*PAIR_FEATURES, *answers, *PAIR_DIRECTION, *PAIR_CONES]
    observed = spec.observed_by
    return own + ([OBSERVED_PREFIX + n for n in evidence_names(observed)] if observed else [])


def reads_observed(names: Sequence[str]) -> bool:
    """Whether a network reading these evidence columns reads the observed points and
    ``with_observed``'s width of evidence."""
    return any(n.startswith(OBSERVED_PREFIX) for n in names)


def with_observed(evidence: npt.NDArray[np.floating],
                  observed: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
    """(N, len(``ALL_EVIDENCE``)): an input's ``network_evidence`` and, after it, that of the
    observed points of the same views (``RelationInput.observed_by``).

    Raises:
        ValueError: either is not (N, len(``EVIDENCE``)) for one N.
    """
    if evidence.ndim != 2 or evidence.shape != observed.shape \
            or evidence.shape[1] != len(EVIDENCE):
        raise ValueError(f"evidence and observed evidence must both be (N, {len(EVIDENCE)}); "
                         f"got {evidence.shape} and {observed.shape}")
    return np.concatenate([evidence, observed], axis=1).astype(np.float32)


def evidence_gains(input_name: str) -> tuple[tuple[str, float], ...]:
    """The gains of a network of one input's evidence columns (``ANSWER_GAINS`` where it
    reads the answers: an exact input)."""
    return ANSWER_GAINS if INPUTS.get(input_name).exact else ()


@dataclass(frozen=True)
class GeometricTests:
    """The ``geometric`` baseline's tests on the pair evidence (``pair_features``). A fit
    cannot meet the CAD's tolerances (0.1 mm, 0.5 degree: those stay the truth's), so each test
    widens them by what the points themselves cannot resolve: their spacing."""

    spacings: float = 1.0  # a length test passes within tolerance + this many point spacings
    coaxial_deg: float = 5.0  # axes of a fit agree within this (the CAD's 0.5 is far finer)
    # a face pair (planes of the two parts facing each other with overlap) is coincident
    # within this angle, at most the CAD's 0.1 mm apart plus the spacing, the parts on either side
    face_deg: float = 5.0
    flatness: float = 0.2  # the contact region's normals share an axis below this
    parallel_deg: float = 3.0  # dominant directions within this of 0 or 90 degrees
    dominant_ratio: float = 1.5  # the truth's own rule for a dominant direction
    # The evidence's planes are the faces' own (CAD samples, each with its face's normal): a
    # face pair's offset then takes no spacing. Held-out night, truth: coincident pairs' faces
    # 0.0035 mm apart at most, bolt heads on a washer 1.59 mm over the flange (spacing 2.7 mm).
    exact_planes: bool = False
    # ...and its cylinders the faces' own: a concentric mate is then a coaxial cylinder pair
    # (the ``coax_*`` evidence: one's points about the other's axis) whose own faces lie within
    # the CAD's 1 mm, not parts that touch somewhere near coaxial faces. Held-out night, truth:
    # six bolts of a pipe flange stand coaxial over its holes 1.59 mm above them, their washers
    # touching it.
    # The two knobs were chosen on the training corpus's train and validation splits
    # (``bench/studies/exact_tests.py``), where the exact tests agree with the clear concentric
    # labels 97.3 and 96.1% (the tests before: 97.1 and 95.9%) with 8 and 0 false mates (103
    # and 19): what they miss is a mate's cylinder that the samples of a large part hardly
    # cover (3,000 of them, 3.4 mm apart).
    coaxial_faces: bool = False
    coaxial_spread_mm: float = 0.5  # the points' rms about the other's axis
    face_gap_mm: float = 0.5  # a face gap passes within the CAD's 1 mm plus this


# The evidence's lengths that say where two parts' faces lie against each other, which a
# registered pose's uncertainty blurs (``within_pose``); radii and residuals are the parts' own.
POSE_LENGTHS = ("gap_mm", "face_offset_mm", "contact_axis_offset_mm", "axis_offset_mm",
                "cyl_offset_mm", "coax_spread_mm", "coax_face_gap_mm")


def within_pose(features: npt.NDArray[np.floating], slack_mm: npt.ArrayLike,
                slack_deg: npt.ArrayLike | None = None) -> npt.NDArray[np.float32]:
    """Raw pair evidence (N, ``N_PAIR_FEATURES``) read within each pair's pose uncertainty
    (N,) mm: its ``POSE_LENGTHS`` less the slack, never below 0, so that the tests and the
    networks take two faces the poses cannot tell apart from touching as touching; and (N,)
    degrees: the dominant directions' angle that much nearer to 0 or 90 degrees. The
    ``registered`` input's poses carry millimetres and degrees where the CAD's tolerances are
    0.1 mm and 3 degrees: read at those, its coincident mates held in 2 of 10 pair views, and
    its parallel pairs F1 0.89 against 0.96 within the turn (held-out night). The angles of
    the faces a concentric or coincident mate pairs are not read within the turn: so read,
    that night's concentric F1 fell from 0.92 to 0.85 and coincident from 0.942 to 0.937,
    their lengths' slack already passing faces the poses cannot tell apart."""
    out = np.array(features, dtype=np.float32)
    slack = np.asarray(slack_mm, dtype=np.float32)
    for name in POSE_LENGTHS:
        col = PAIR_FEATURES.index(name)
        found = out[:, col] < FAR_MM  # a length not measured stays "far"
        out[found, col] = np.maximum(out[found, col] - slack[found], 0.0)
    if slack_deg is None:
        return out
    turn = np.asarray(slack_deg, dtype=np.float32)
    col = PAIR_FEATURES.index("dom_angle_deg")
    angle = out[:, col]
    out[:, col] = np.where(angle < 45.0, np.maximum(angle - turn, 0.0),
                           np.minimum(angle + turn, 90.0))
    return out


def tests_for(input_name: str) -> GeometricTests:
    """The tests for one input's evidence: exact planes and cylinders where the input is the
    CAD's own surface (``RelationInput.exact``)."""
    exact = INPUTS.get(input_name).exact
    return GeometricTests(exact_planes=exact, coaxial_faces=exact)


def geometric_symmetric(features: npt.NDArray[np.floating],
                        tests: GeometricTests = GeometricTests()) -> npt.NDArray[np.bool_]:
    """(N, 4) parallel, perpendicular, concentric, coincident of pairs by their raw evidence
    (N, ``N_PAIR_FEATURES``): coincident, an opposed face pair; concentric, a coaxial contact
    axis, parts stacked on one axis, or a coaxial cylinder pair (each of the three found mates
    the others missed on the training corpus's validation split; on exact evidence, a coaxial
    cylinder pair whose faces lie within 1 mm, ``coaxial_faces``); parallel and perpendicular,
    the angle between dominant plane directions."""
    raw = np.asarray(features)
    f = {name: raw[:, i].astype(np.float64) for i, name in enumerate(PAIR_FEATURES)}
    slack = tests.spacings * f["spacing_mm"]
    plane_slack = 0.0 if tests.exact_planes else slack
    coincident = ((f["face_found"] > 0) & (f["gap_mm"] <= 0.1 + slack)
                  & (f["face_angle_deg"] <= tests.face_deg)
                  & (f["face_offset_mm"] <= 0.1 + plane_slack) & (f["face_opposed"] > 0))
    if tests.coaxial_faces:
        concentric = ((f["coax_found"] > 0) & (f["coax_spread_mm"] <= tests.coaxial_spread_mm)
                      & (f["coax_normal_deg"] <= tests.coaxial_deg)
                      & (f["coax_face_gap_mm"] <= 1.0 + tests.face_gap_mm))
    else:
        concentric = ((f["contact_axis_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
                      & (f["contact_axis_flatness"] <= tests.flatness)
                      & (f["contact_axis_offset_mm"] <= 0.1 + slack)) | (
            (f["axis_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
            & (f["axis_angle_deg"] <= tests.coaxial_deg)
            & (f["axis_offset_mm"] <= 0.1 + slack)) | (
            (f["cyl_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
            & (f["cyl_angle_deg"] <= tests.coaxial_deg) & (f["cyl_offset_mm"] <= 0.1 + slack))
    dominant = (f["dom_found"] > 0) & (f["dom_ratio"] >= tests.dominant_ratio)
    parallel = dominant & (f["dom_angle_deg"] <= tests.parallel_deg) & ~coincident
    perpendicular = dominant & (f["dom_angle_deg"] >= 90.0 - tests.parallel_deg)
    return np.column_stack([parallel, perpendicular, concentric, coincident])


def geometric_decisions(points: npt.NDArray[np.float32], mm_per_unit: npt.NDArray[Any],
                        features: npt.NDArray[np.float32] | None = None,
                        keys: Sequence[tuple[Any, Any]] | None = None,
                        tests: GeometricTests = GeometricTests(),
                        centres: npt.NDArray[np.floating] | None = None
                        ) -> npt.NDArray[np.bool_]:
    """(N, 10) the geometric baseline's relations of pairs in the observer frame.

    Directional relations: the truth's 15 degree cones on the offset of the parts' centres.
    Symmetric ones: ``geometric_symmetric``.

    Args:
        points: (N, 2, k, 3) observer-frame points (the view axis is +Y there).
        mm_per_unit: (N,) millimetres of the CAD per unit of ``points`` (1 / scale_m_per_mm).
        features: (N, F) raw pair evidence (``pair_features_many``), computed when None.
        keys: per row, a key of each part's cloud (a cloud met again is analysed once).
        centres: (N, 2, 3) each part's centre in the units and frame of ``points`` (the
            centroid of its solid where the input knows it); None: the clouds' means.
    """
    mm = np.asarray(mm_per_unit, dtype=np.float64)
    raw = pair_features_many(points, mm, list(keys) if keys is not None else None) \
        if features is None else features
    c = _centres(points, centres)
    offsets = (c[:, 0] - c[:, 1]) * mm[:, None]
    directional, _ = directional_truth(offsets, OBSERVER_VIEW_AXIS)
    return np.column_stack([directional, geometric_symmetric(raw, tests)])


def _centres(points: npt.NDArray[np.floating], centres: npt.NDArray[np.floating] | None
             ) -> npt.NDArray[np.float64]:
    if centres is None:
        return np.asarray(points, dtype=np.float64).mean(axis=2)
    c = np.asarray(centres, dtype=np.float64)
    if c.shape != (len(points), 2, 3):
        raise ValueError(f"centres must be ({len(points)}, 2, 3); got {c.shape}")
    return c


def pair_direction(centres: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
    """(N, 3) the unit vector from b's centre to a's, of centres (N, 2, 3); zero where the
    centres coincide (no direction: every directional relation is false there)."""
    c = np.asarray(centres, dtype=np.float64)
    offset = c[:, 0] - c[:, 1]
    norm = np.linalg.norm(offset, axis=1, keepdims=True)
    out = np.divide(offset, norm, out=np.zeros_like(offset), where=norm > 0)
    return out.astype(np.float32)


def cone_codes(centres: npt.NDArray[np.floating],
               tol: Tolerances = DEFAULT_TOLERANCES) -> npt.NDArray[np.float32]:
    """(N, 3) each observer axis's cones of the pair's direction (right, behind, up), of
    centres (N, 2, 3) in the observer frame: t(angle to +axis) - t(angle to -axis), where
    t(x) = tanh((cone - x) / ``CONE_SOFTNESS_DEG``) and cone is the truth's half-angle. Near 2
    inside the + cone, -2 inside the - cone, 0 between, and +-1 on an edge: a threshold a
    network meets in one step, where the direction's coordinates move by 0.005 a degree there.
    Odd in the direction (the swapped pair's codes are negated); 0 where the centres coincide."""
    c = np.asarray(centres, dtype=np.float64)
    _, angles = directional_truth(c[:, 0] - c[:, 1], OBSERVER_VIEW_AXIS, tol)
    t = np.tanh((tol.direction_cone_deg - angles) / CONE_SOFTNESS_DEG)  # DIRECTIONAL order
    codes = np.column_stack([t[:, 1] - t[:, 0], t[:, 5] - t[:, 4], t[:, 2] - t[:, 3]])
    return np.nan_to_num(codes, nan=0.0).astype(np.float32)


def network_evidence(features: npt.NDArray[np.floating],
                     points: npt.NDArray[np.floating],
                     centres: npt.NDArray[np.floating] | None = None,
                     tests: GeometricTests = GeometricTests()) -> npt.NDArray[np.float32]:
    """(N, len(``EVIDENCE``)) what a relation network may read of its pairs: the encoded raw
    evidence (``encode_features`` of ``features``), the tests' four symmetric answers (0 or 1,
    in ``GEOMETRIC_ANSWERS`` order), ``DIRECTION_GAIN`` times the pair's direction
    (``pair_direction``) and its ``cone_codes``, of the parts' ``centres`` (N, 2, 3), or of the
    means of ``points`` (N, 2, k, 3) when None. ``tests``: the input's (``tests_for``)."""
    raw = np.asarray(features)
    answers = geometric_symmetric(raw, tests).astype(np.float32)
    c = _centres(points, centres)
    direction = DIRECTION_GAIN * pair_direction(c)
    return np.concatenate([encode_features(raw), answers, direction, cone_codes(c)],
                          axis=1).astype(np.float32)


def swap_evidence(evidence: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """The evidence of the swapped pairs (b, a): the ordered columns (``ORDERED_COLUMNS``)
    negated, the rest as it is, for ``EVIDENCE`` or ``ALL_EVIDENCE`` columns. A matrix of
    another width (pair evidence alone) is symmetric and comes back."""
    width = evidence.shape[-1]
    if width not in (len(EVIDENCE), len(ALL_EVIDENCE)):
        return evidence
    cols = [c for c in ORDERED_COLUMNS if c < width]
    out = evidence.copy()
    out[..., cols] = -out[..., cols]
    return out
