"""The ``geometric`` baseline: fixed tests on a pair's evidence, and the evidence the relation
networks read.

The tests decide the symmetric relations on the pair evidence of
``cadio.capture.pair_features`` (each the CAD definition, its tolerances widened by what the
points resolve) and the directional ones on the clouds' centroids, with the truth's own cones.

A network may read the four symmetric answers beside the encoded evidence
(``network_evidence``). Where the evidence is exact (the CAD samples of the ``truth`` input,
whose normals are their faces'), the answers are the CAD's own tests on it: a network trained
on a few hundred assemblies learns from them where its thresholds on the raw evidence would not
reach unseen parts (held-out assemblies: ltn on ``truth`` 0.798 -> 0.844 mean F1, see the
relation card). A checkpoint lists what it reads (``data["pair_features"]``), and a network
reads the first ``pair_features`` columns of ``network_evidence``: the encoded evidence, then
the answers.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from cadio.capture.pair_features import PAIR_FEATURES, encode_features, pair_features_many
from cadio.truth.relations import directional_truth

__all__ = ["ANSWERS_READ_BY", "GEOMETRIC_ANSWERS", "OBSERVER_VIEW_AXIS", "GeometricTests",
           "geometric_decisions", "geometric_symmetric", "network_evidence"]

# In the observer frame the view axis is +Y (behind), whatever the camera.
OBSERVER_VIEW_AXIS = (0.0, 1.0, 0.0)
# The names of the tests' answers in a network's evidence, after ``PAIR_FEATURES``.
GEOMETRIC_ANSWERS = ("geometric_parallel", "geometric_perpendicular", "geometric_concentric",
                     "geometric_coincident")
# The inputs whose networks are trained to read the answers: where the evidence is exact. On
# ``completed`` the answers of fits to voxel surfaces added nothing (held-out mean F1 0.619
# with them, 0.621 without), so those networks read the evidence alone.
ANSWERS_READ_BY = ("truth",)


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


def geometric_symmetric(features: npt.NDArray[np.floating],
                        tests: GeometricTests = GeometricTests()) -> npt.NDArray[np.bool_]:
    """(N, 4) parallel, perpendicular, concentric, coincident of pairs by their raw evidence
    (N, ``N_PAIR_FEATURES``): coincident, an opposed face pair; concentric, a coaxial contact
    axis, parts stacked on one axis, or a coaxial cylinder pair (each of the three found mates
    the others missed on the training corpus's validation split); parallel and perpendicular,
    the angle between dominant plane directions."""
    raw = np.asarray(features)
    f = {name: raw[:, i].astype(np.float64) for i, name in enumerate(PAIR_FEATURES)}
    slack = tests.spacings * f["spacing_mm"]
    coincident = ((f["face_found"] > 0) & (f["gap_mm"] <= 0.1 + slack)
                  & (f["face_angle_deg"] <= tests.face_deg)
                  & (f["face_offset_mm"] <= 0.1 + slack) & (f["face_opposed"] > 0))
    concentric = ((f["contact_axis_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
                  & (f["contact_axis_flatness"] <= tests.flatness)
                  & (f["contact_axis_offset_mm"] <= 0.1 + slack)) | (
        (f["axis_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
        & (f["axis_angle_deg"] <= tests.coaxial_deg) & (f["axis_offset_mm"] <= 0.1 + slack)) | (
        (f["cyl_found"] > 0) & (f["gap_mm"] <= 1.0 + slack)
        & (f["cyl_angle_deg"] <= tests.coaxial_deg) & (f["cyl_offset_mm"] <= 0.1 + slack))
    dominant = (f["dom_found"] > 0) & (f["dom_ratio"] >= tests.dominant_ratio)
    parallel = dominant & (f["dom_angle_deg"] <= tests.parallel_deg) & ~coincident
    perpendicular = dominant & (f["dom_angle_deg"] >= 90.0 - tests.parallel_deg)
    return np.column_stack([parallel, perpendicular, concentric, coincident])


def geometric_decisions(points: npt.NDArray[np.float32], mm_per_unit: npt.NDArray[Any],
                        features: npt.NDArray[np.float32] | None = None,
                        keys: Sequence[tuple[Any, Any]] | None = None,
                        tests: GeometricTests = GeometricTests()) -> npt.NDArray[np.bool_]:
    """(N, 10) the geometric baseline's relations of pairs in the observer frame.

    Directional relations: the truth's 15 degree cones on the offset of the clouds' centroids.
    Symmetric ones: ``geometric_symmetric``.

    Args:
        points: (N, 2, k, 3) observer-frame points (the view axis is +Y there).
        mm_per_unit: (N,) millimetres of the CAD per unit of ``points`` (1 / scale_m_per_mm).
        features: (N, F) raw pair evidence (``pair_features_many``), computed when None.
        keys: per row, a key of each part's cloud (a cloud met again is analysed once).
    """
    mm = np.asarray(mm_per_unit, dtype=np.float64)
    raw = pair_features_many(points, mm, list(keys) if keys is not None else None) \
        if features is None else features
    offsets = (points[:, 0].mean(axis=1) - points[:, 1].mean(axis=1)) * mm[:, None]
    directional, _ = directional_truth(offsets.astype(np.float64), OBSERVER_VIEW_AXIS)
    return np.column_stack([directional, geometric_symmetric(raw, tests)])


def network_evidence(features: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
    """(N, ``N_PAIR_FEATURES`` + 4) what a relation network reads of its pairs' raw evidence:
    the encoded evidence (``encode_features``), then the tests' four answers (0 or 1, in
    ``GEOMETRIC_ANSWERS`` order). A network reads its first ``pair_features`` columns."""
    raw = np.asarray(features)
    answers = geometric_symmetric(raw).astype(np.float32)
    return np.concatenate([encode_features(raw), answers], axis=1).astype(np.float32)
