"""Where the rest of the assembly puts each part: a robust consensus of the parts' poses.

A mate's residual read from its two registered parts is only as sure as the less sure of them:
a frame shifted 5 mm against a small pin whose tilt its few pixels leave open reads as "holds"
within the pin's three sigmas. But the design says where every part stands relative to all the
others, and an assembly of many parts says where it stands as a whole far more surely than one
small part does. So each part is also held against the place the *rest* of the assembly gives
it: the nominal (assembly -> world) corrected by the parts' registered poses, each weighted by
what its points constrain (``uncertainty.PoseUncertainty``, nothing in the directions its view
leaves open), robustly (a Cauchy weight: the few parts a defect moved count for little), and
leaving the part itself out (a moved frame would otherwise carry the consensus with it).

``Rest.place(j)`` is part ``j`` where the rest of the assembly without the tested part puts it,
with the consensus's own uncertainty carried to it; ``asbuilt.mate_as_built`` holds each part of
a mate against its partner so placed, beside the two registered poses. The design route's
parts are the input; nothing here sees a planted defect or a true pose.

Small corrections are (turn, shift): a turn (radians) about ``centre`` (world mm), then a
shift (mm), as in ``uncertainty``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from cadio.inspect.asbuilt import PartAsBuilt
from cadio.inspect.routes import AssemblyModel
from cadio.inspect.uncertainty import PoseUncertainty, point_motion, small_motion
from cadio.records import FloatArray

# Cauchy weight's scale, in the Mahalanobis distance of a part's deviation from the consensus.
CAUCHY = 3.0
ITERATIONS = 10
# The least number of views for the consensus: from one view a part's fit errs beyond its
# Hessian's sigma more often than a reading against its own sigma alone can bear. On the
# development assemblies (OCCT as1, a handwheel, a pillow block, the AeroAssembly; intact, the
# D435 model, every mate's residual held to the sigma along its own direction) the consensus
# raised the false alarms of one view from 2 to 5 of 25 parts, and lowered those of four views
# from 3 to 3 of 27 (none added).
MIN_VIEWS = 2
# A consensus whose information is this small against its largest in some direction leaves it
# open (every part blind to it: a ring of balls turned about its axis): no consensus.
MIN_SHARE = 1e-6


@dataclass(frozen=True)
class Rest:
    """The consensus of every part but one: the correction of the nominal (world motion,
    (4, 4)), its covariance (6, 6 over turn about ``centre`` and shift), and the parts'
    designed places in the world (part -> world, at the uncorrected nominal), their scales
    for turns and their centroids there."""

    correction: FloatArray
    covariance: FloatArray
    centre: FloatArray
    designed: Mapping[int, FloatArray]
    radii: Mapping[int, float]
    centres: Mapping[int, FloatArray]

    def place(self, index: int) -> PartAsBuilt:
        """Part ``index`` where the rest of the assembly puts it, with the uncertainty of
        that place (the consensus's covariance carried to its centroid)."""
        centre = self.centres[index]
        jac = _carry(centre - self.centre)
        cov = jac @ self.covariance @ jac.T
        moved = np.asarray(self.correction @ self.designed[index], dtype=np.float64)
        uncertainty = PoseUncertainty(self.correction[:3, :3] @ centre + self.correction[:3, 3],
                                      self.radii[index], cov, np.zeros((0, 6)))
        return PartAsBuilt(index, moved, uncertainty)


def rest_of_assembly(parts: Mapping[int, PartAsBuilt], design: Mapping[int, FloatArray],
                     nominal: FloatArray, centres: Mapping[int, FloatArray],
                     radii: Mapping[int, float], axes: Mapping[int, FloatArray | None],
                     min_parts: int = 3) -> dict[int, Rest]:
    """Per registered part, the consensus of the others (``Rest``); none where fewer than
    ``min_parts`` others were registered or they leave a direction open.

    Args:
        parts: each part as the scan shows it (pose and uncertainty where registered).
        design: each part's designed pose (part -> assembly, mm).
        nominal: the alignment of the assembly (assembly -> world, mm).
        centres: each part's centroid in its own frame (mm); radii: its scale for turns.
        axes: each revolved part's axis in its own frame (None: not revolved): its turn about
            it is no deviation (the fit's roll is anyone's).
    """
    designed = {i: nominal @ design[i] for i in design}
    world_centres = {i: designed[i][:3, :3] @ centres[i] + designed[i][:3, 3] for i in design}
    seen = {i: p for i, p in parts.items()
            if p.pose is not None and p.uncertainty is not None and not p.problem
            and np.all(np.isfinite(p.uncertainty.covariance))}  # a fit without inliers: none
    if len(seen) < min_parts + 1:
        return {}
    origin = np.mean([world_centres[i] for i in seen], axis=0)
    deviations, information = {}, {}
    for i, p in seen.items():
        assert p.pose is not None and p.uncertainty is not None
        free = _free(designed[i], axes.get(i))
        deviations[i] = free @ _deviation(p.pose, designed[i], world_centres[i])
        information[i] = free @ _information(p.uncertainty) @ free
    jacobians = {i: _carry(world_centres[i] - origin) for i in seen}
    out = {}
    for left in seen:
        others = [i for i in seen if i != left]
        found = _robust(others, deviations, information, jacobians)
        if found is None:
            continue
        delta, covariance = found
        out[left] = Rest(small_motion(delta, origin), covariance, origin, designed, radii,
                         world_centres)
    return out


def _deviation(pose: FloatArray, designed: FloatArray, centre: FloatArray) -> FloatArray:
    """(6,) the part's motion from its designed place to its registered pose: its turn
    (rotation vector) and its centroid's shift."""
    motion = pose @ np.linalg.inv(designed)
    turn = Rotation.from_matrix(motion[:3, :3]).as_rotvec()
    shift = motion[:3, :3] @ centre + motion[:3, 3] - centre
    return np.concatenate([turn, shift])


def _free(designed: FloatArray, axis: FloatArray | None) -> FloatArray:
    """(6, 6) the projection leaving out the turn about a revolved part's axis."""
    out = np.eye(6)
    if axis is not None:
        w = designed[:3, :3] @ np.asarray(axis, dtype=np.float64)
        w = w / np.linalg.norm(w)
        out[:3, :3] -= np.outer(w, w)
    return out


def _information(u: PoseUncertainty) -> FloatArray:
    """The inverse of the pose's covariance in its observable directions (zero in the
    others)."""
    info: FloatArray = np.asarray(np.linalg.pinv(u.covariance, rcond=1e-10, hermitian=True),
                                  dtype=np.float64)
    return info


def _carry(offset: FloatArray) -> FloatArray:
    """(6, 6): a small (turn, shift) of the whole about a point, as (turn, shift) of a part
    whose centroid lies ``offset`` from that point."""
    return np.vstack([np.hstack([np.eye(3), np.zeros((3, 3))]),
                      point_motion(offset, np.zeros(3))])


def _robust(others: list[int], deviations: Mapping[int, FloatArray],
            information: Mapping[int, FloatArray], jacobians: Mapping[int, FloatArray]
            ) -> tuple[FloatArray, FloatArray] | None:
    """The correction (turn, shift) that best explains the parts' deviations, each weighted by
    its information and a Cauchy weight on its Mahalanobis distance; and its covariance. None
    where the parts leave a direction open."""
    weights = dict.fromkeys(others, 1.0)
    delta: FloatArray = np.zeros(6)
    a: FloatArray = np.zeros((6, 6))
    for _ in range(ITERATIONS):
        a = np.zeros((6, 6))
        b = np.zeros(6)
        for i in others:
            jw = jacobians[i].T @ information[i] * weights[i]
            a += jw @ jacobians[i]
            b += jw @ deviations[i]
        values = np.linalg.eigvalsh(a)
        if values.max() <= 0 or values.min() < MIN_SHARE * values.max():
            return None
        delta = np.asarray(np.linalg.solve(a, b), dtype=np.float64)
        for i in others:
            r = deviations[i] - jacobians[i] @ delta
            d2 = max(float(r @ information[i] @ r), 0.0)
            weights[i] = 1.0 / (1.0 + d2 / CAUCHY ** 2)
    return delta, np.asarray(np.linalg.inv(a), dtype=np.float64)


def rest_in(model: AssemblyModel, parts: Mapping[int, PartAsBuilt], nominal: FloatArray,
            views: int = MIN_VIEWS) -> dict[int, Rest] | None:
    """``rest_of_assembly`` of an assembly's parts as registered in ``views`` views at the
    alignment ``nominal`` (its parts' centroids, scales and revolved axes from the model);
    None from fewer than ``MIN_VIEWS`` views."""
    if views < MIN_VIEWS:
        return None
    return rest_of_assembly(
        parts, dict(enumerate(model.design)), nominal,
        {i: p.centre for i, p in enumerate(model.parts)},
        {i: max(p.diameter / 2, 1.0) for i, p in enumerate(model.parts)},
        {i: np.array(s.axis) if s.continuous and s.axis is not None else None
         for i, s in enumerate(model.symmetries)})
