"""What the export writes for one assembly: its parts as the STEP names them, and per pair the
predicted relations and joint beside the CAD's, each with a status. Plain pandas, no CAD.

The product's answers (``reports.methods.product``: the LTN on completed inputs) come as
``relations_pairs`` rows, one per view of a pair and relation. The views of a pair are pooled:
each view's calibrated confidence gives the probability that the relation holds (the
confidence of a "yes", one minus that of a "no"); their mean is the pair's probability, the
answer is whether it reaches one half and the confidence is that of the answer. The joint is
the network's own (its joint head's answer, a ``joint`` of the rows): the one most views give,
with the share of views that give it as its confidence (ties: the first name in alphabetical
order). Rows without one (a method without a joint head) read it with ``predicted_joint``
from the pooled concentric and coincident answers, with the product of their confidences.

Nothing is dropped: a pair the CAD mates name but no view saw is exported as ``not-captured``
with the CAD's answers and no prediction; an assembly without any prediction is exported with
status ``no-predictions`` and the reason.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from cadio.inspect.asbuilt import MateAsBuilt, verdict
from cadio.records import CONVERSE, Relation
from cadio.truth.joints import CAD_NAMES, NONE, predicted_joint

RELATIONS = tuple(str(r) for r in Relation)
# Relations that a CAD constraint can carry, with the face-level mates that give its geometry.
CONSTRAINED = ("concentric", "coincident")
# Statuses of a pair and of an assembly (the JSON Schema lists the same).
PREDICTED, NOT_CAPTURED = "predicted", "not-captured"
OK, PARTIAL, NO_PREDICTIONS, FAILED = "ok", "partial", "no-predictions", "failed"


@dataclass(frozen=True)
class PartRef:
    """A part as the STEP file names it.

    index: the solid's position in the file's assembly tree (``cadio.cad.step.read_step``
    order); name: its product name (``name#k`` for the k-th solid of a multi-solid shape);
    path: the product path from the root; placement: its 4x4 placement in the file's frame
    (row-major, mm).
    """

    index: int
    part_id: str
    name: str
    path: str
    placement: tuple[float, ...]


@dataclass(frozen=True)
class RelationCall:
    """One relation of a pair: the pooled prediction (None when not captured) and the CAD's."""

    relation: str
    predicted: bool | None
    confidence: float | None
    p_true: float | None
    views: int
    views_true: int
    cad: bool | None

    @property
    def agrees(self) -> bool | None:
        if self.predicted is None or self.cad is None:
            return None
        return self.predicted == self.cad


@dataclass(frozen=True)
class JointCall:
    """The joint of a pair: predicted (None when not captured) and the CAD's kinematic and
    suggested joints ("none" without a joint)."""

    predicted: str | None
    confidence: float | None
    cad_kinematic: str
    cad_suggested: str

    @property
    def agrees(self) -> bool | None:
        return None if self.predicted is None else self.predicted == self.cad_kinematic

    def cad_names(self) -> dict[str, str | None]:
        """The predicted joint in each CAD system's vocabulary (None: no such joint)."""
        names = CAD_NAMES.get(self.predicted or NONE, {})
        return {system: names.get(system) for system in ("onshape", "freecad", "fusion360")}


@dataclass(frozen=True)
class FaceGeometry:
    """A CAD face-level mate of the pair: ``axis`` is the mate's axis (concentric) or the
    outward normal of part a's face (coincident), ``origin`` a point of it, assembly frame."""

    relation: str
    face_a: int
    face_b: int
    axis: tuple[float, float, float]
    origin: tuple[float, float, float]


@dataclass(frozen=True)
class PairMates:
    """One pair (a.index < b.index): its status, relations, joint and CAD face geometry."""

    a: PartRef
    b: PartRef
    status: str
    views: int
    relations: tuple[RelationCall, ...]
    joint: JointCall
    faces: tuple[FaceGeometry, ...] = ()

    def call(self, relation: str) -> RelationCall:
        return next(r for r in self.relations if r.relation == relation)

    def constraints(self) -> tuple[FaceGeometry, ...]:
        """The CAD's face mates of the relations predicted to hold: what a constraint solver
        can use. (A bolt in a plate's hole has a concentric face mate although the two parts'
        principal axes are not coaxial: the face mate decides, not the part-level truth.)"""
        held = {r.relation for r in self.relations if r.predicted}
        return tuple(f for f in self.faces if f.relation in held)


def mate_checks(rows: pd.DataFrame) -> tuple[MateAsBuilt, ...]:
    """The as-built checks of an assembly's rows of ``as_built.csv``."""
    return tuple(MateAsBuilt.from_row(r) for r in rows.to_dict("records"))


@dataclass(frozen=True)
class AssemblyMates:
    """Everything exported for one assembly."""

    assembly: str
    category: str
    source: str
    source_sha256: str
    status: str
    parts: tuple[PartRef, ...]
    pairs: tuple[PairMates, ...]
    reason: str = ""
    run_id: str = ""
    models: Mapping[str, str] = field(default_factory=dict)
    tolerances: Mapping[str, float] = field(default_factory=dict)
    as_built: tuple[MateAsBuilt, ...] = ()  # each CAD face mate as built (the inspection)

    def as_built_verdict(self) -> str:
        """``holds``, ``N mates broken``, ``not inspectable``, or "" (not inspected)."""
        return verdict(self.as_built) if self.as_built else ""

    def agreement(self) -> dict[str, Any]:
        """Agreement with the CAD over the predicted pairs: relation accuracy (all pair x
        relation answers), per relation F1 of the frame-free ones, joint agreement."""
        calls = [c for p in self.pairs for c in p.relations if c.agrees is not None]
        joints = [p.joint for p in self.pairs if p.joint.agrees is not None]
        out: dict[str, Any] = {
            "relation_answers": len(calls),
            "relation_accuracy": _mean([bool(c.agrees) for c in calls]),
            "joints": len(joints),
            "joint_agreement": _mean([bool(j.agrees) for j in joints]),
            "per_relation": {},
        }
        for rel in RELATIONS:
            mine = [c for c in calls if c.relation == rel]
            tp = sum(bool(c.predicted and c.cad) for c in mine)
            fp = sum(bool(c.predicted and not c.cad) for c in mine)
            fn = sum(bool(c.cad and not c.predicted) for c in mine)
            out["per_relation"][rel] = {
                "n": len(mine), "n_cad": tp + fn, "n_predicted": tp + fp,
                "f1": (2 * tp / (2 * tp + fp + fn)) if (tp + fp + fn) else None}
        return out


def _mean(values: Sequence[bool]) -> float | None:
    return float(np.mean(values)) if values else None


def part_refs(catalog: pd.DataFrame) -> tuple[PartRef, ...]:
    """The parts of one assembly from its catalog rows (ok solids), in file order."""
    rows = catalog.sort_values("solid_index")
    return tuple(PartRef(index=int(r.solid_index), part_id=str(r.part_id), name=str(r.name),
                         path=str(r.path_in_assembly),
                         placement=_placement(r.placement))
                 for r in rows.itertuples())


def _placement(value: Any) -> tuple[float, ...]:
    """A catalog placement (a JSON list, or an array) as 16 floats, row-major."""
    data = json.loads(value) if isinstance(value, str) else value
    return tuple(float(v) for v in np.asarray(data, dtype=np.float64).ravel())


def pool_views(rows: pd.DataFrame) -> dict[str, tuple[bool, float | None, float | None, int,
                                                       int, bool]]:
    """Per relation of one ordered pair's rows: (predicted, confidence, p_true, views,
    views_true, cad), pooled over views as the module says."""
    out = {}
    for rel, g in rows.groupby("relation", sort=False):
        said = g["predicted"].to_numpy(bool)
        conf = g["confidence"].to_numpy(np.float64)
        if np.isfinite(conf).all():
            p_true = float(np.mean(np.where(said, conf, 1.0 - conf)))
            predicted = p_true >= 0.5
            confidence: float | None = p_true if predicted else 1.0 - p_true
            p: float | None = p_true
        else:  # a method without calibrated confidences: the majority of views
            predicted, confidence, p = bool(said.mean() >= 0.5), None, None
        cad = bool(g["truth"].to_numpy(bool).mean() >= 0.5)
        out[str(rel)] = (bool(predicted), confidence, p, len(g), int(said.sum()), cad)
    return out


def _cad_part_relations(mates: pd.DataFrame, a: str, b: str) -> set[str]:
    rows = mates[(mates["level"] == "part") & (mates["part_a"] == a) & (mates["part_b"] == b)]
    return {str(r) for r in rows["relation"]}


def _cad_joint(mates: pd.DataFrame, a: str, b: str) -> tuple[str, str]:
    rows = mates[(mates["level"] == "joint") & (mates["part_a"] == a) & (mates["part_b"] == b)]
    if rows.empty:
        return NONE, NONE
    row = rows.iloc[0]
    return str(row["kinematic"]), str(row["relation"])


def _faces(mates: pd.DataFrame, a: str, b: str) -> tuple[FaceGeometry, ...]:
    rows = mates[(mates["level"] == "face") & (mates["part_a"] == a) & (mates["part_b"] == b)
                 & mates["relation"].isin(CONSTRAINED)]
    out = []
    for r in rows.itertuples():
        if r.axis is None or r.origin is None:
            continue
        ax, org = np.asarray(r.axis, float), np.asarray(r.origin, float)
        out.append(FaceGeometry(relation=str(r.relation), face_a=int(r.face_a),
                                face_b=int(r.face_b), axis=(ax[0], ax[1], ax[2]),
                                origin=(org[0], org[1], org[2])))
    return tuple(out)


def _swapped(rows: pd.DataFrame) -> pd.DataFrame:
    """Rows of the pair (b, a) read as rows of (a, b): directional relations take their
    converse (r(b, a) iff converse(r)(a, b))."""
    converse = {str(k): str(v) for k, v in CONVERSE.items()}
    out = rows.copy()
    out["relation"] = out["relation"].map(lambda r: converse.get(str(r), str(r)))
    out[["part_a", "part_b"]] = out[["part_b", "part_a"]].to_numpy()
    return out


def assembly_mates(assembly: str, category: str, source: str, source_sha256: str,
                   catalog: pd.DataFrame, mates: pd.DataFrame, predictions: pd.DataFrame,
                   **meta: Any) -> AssemblyMates:
    """The export record of one assembly.

    Args:
        catalog: the assembly's catalog rows; mates: its CAD mates table; predictions: the
            product's ``relations_pairs`` rows of its capture (empty when it was not captured
            or the relations stage failed).
        meta: run_id, models, tolerances and reason, copied to the record.
    """
    parts = part_refs(catalog)
    by_id = {p.part_id: p for p in parts}
    pairs_cad = dict.fromkeys(
        (str(a), str(b)) for a, b in zip(mates["part_a"], mates["part_b"], strict=True))
    known = predictions[predictions["part_a"].isin(by_id) & predictions["part_b"].isin(by_id)]
    for a, b in zip(known["part_a"], known["part_b"], strict=True):
        first, second = sorted((str(a), str(b)), key=lambda pid: by_id[pid].index)
        pairs_cad.setdefault((first, second), None)
    pairs = []
    for a, b in pairs_cad:
        if by_id[a].index > by_id[b].index:
            a, b = b, a
        mine = known[(known["part_a"] == a) & (known["part_b"] == b)]
        theirs = known[(known["part_a"] == b) & (known["part_b"] == a)]
        rows = pd.concat([mine, _swapped(theirs)], ignore_index=True)
        pairs.append(_pair(by_id[a], by_id[b], rows, mates))
    captured = [p for p in pairs if p.status == PREDICTED]
    if not pairs or not captured:
        status = NO_PREDICTIONS
    else:
        status = OK if len(captured) == len(pairs) else PARTIAL
    reason = str(meta.pop("reason", "") or "")
    if status == NO_PREDICTIONS and not reason:
        reason = "no prediction for any pair (the assembly was not captured or not related)"
    return AssemblyMates(assembly=assembly, category=category, source=source,
                         source_sha256=source_sha256, status=status, parts=parts,
                         pairs=tuple(pairs), reason=reason, **meta)


def _pair(a: PartRef, b: PartRef, rows: pd.DataFrame, mates: pd.DataFrame) -> PairMates:
    kinematic, suggested = _cad_joint(mates, a.part_id, b.part_id)
    faces = _faces(mates, a.part_id, b.part_id)
    if rows.empty:
        cad = _cad_part_relations(mates, a.part_id, b.part_id)
        calls = tuple(RelationCall(rel, None, None, None, 0, 0, rel in cad) for rel in RELATIONS)
        return PairMates(a=a, b=b, status=NOT_CAPTURED, views=0, relations=calls,
                         joint=JointCall(None, None, kinematic, suggested), faces=faces)
    pooled = pool_views(rows)
    calls = tuple(RelationCall(rel, *pooled[rel]) if rel in pooled else
                  RelationCall(rel, None, None, None, 0, 0, None) for rel in RELATIONS)
    views = int(rows["view"].nunique())
    conc, coin = (next(c for c in calls if c.relation == r) for r in CONSTRAINED)
    joint_name: str | None = None
    confidence: float | None = None
    said = rows.groupby("view")["joint"].first() if "joint" in rows.columns else pd.Series()
    said = said[said.astype(str) != ""]
    if len(said):  # the method's own joint per view: the most views' answer
        counts = said.astype(str).value_counts()
        top = counts[counts == counts.max()].index
        joint_name = str(sorted(top)[0])
        confidence = float(counts.max() / len(said))
    elif conc.predicted is not None and coin.predicted is not None:
        joint_name = predicted_joint(conc.predicted, coin.predicted)
        if conc.confidence is not None and coin.confidence is not None:
            confidence = conc.confidence * coin.confidence
    joint = JointCall(joint_name, confidence, kinematic, suggested)
    return PairMates(a=a, b=b, status=PREDICTED, views=views, relations=calls, joint=joint,
                     faces=faces)


def finite(value: float | None) -> float | None:
    """JSON has no NaN: a missing number is null."""
    return None if value is None or not math.isfinite(value) else float(value)
