"""Tests of cadio.truth.labels: one truth for placed parts, scenes and assemblies alike.

Built solids (a drilled plate, a bolt, a block, pins and rings) are placed by poses; the labels
must be those of the assembly's mates table for the same placement, unchanged by a rigid motion
of everything, and flag the answers within the margins of a tolerance.
"""

from __future__ import annotations

import build123d as bd
import numpy as np
import pytest
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS
from scipy.spatial.transform import Rotation

from cadio.cad.step import StepSolid
from cadio.records import Relation, SolidInfo
from cadio.tolerances import DEFAULT_TOLERANCES as TOL
from cadio.truth.contact import pose_trsf
from cadio.truth.labels import label_placed, part_model
from cadio.truth.mates import extract_mates

CONCENTRIC, COINCIDENT = Relation.CONCENTRIC, Relation.COINCIDENT
K = {r: i for i, r in enumerate(Relation)}


def at(x: float = 0.0, y: float = 0.0, z: float = 0.0, rot: np.ndarray | None = None
       ) -> np.ndarray:
    m = np.eye(4)
    if rot is not None:
        m[:3, :3] = rot
    m[:3, 3] = (x, y, z)
    return m


@pytest.fixture(scope="module")
def models() -> dict:
    plate = bd.Box(60, 40, 10, align=bd.Align.MIN) - bd.Pos(20, 20, 0) * bd.Cylinder(5, 30)
    bolt = bd.Cylinder(5, 15, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MAX)) + \
        bd.Cylinder(8, 3, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
    shapes = {"plate": plate, "bolt": bolt, "block": bd.Box(20, 20, 5, align=bd.Align.MIN),
              "pin": bd.Cylinder(4, 20, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN)),
              "ring": bd.Cylinder(9, 6, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))
              - bd.Cylinder(4, 6, align=(bd.Align.CENTER, bd.Align.CENTER, bd.Align.MIN))}
    return {k: part_model(TopoDS.Solid_s(v.solids()[0].wrapped), k) for k, v in shapes.items()}


def test_a_placed_set_reads_as_its_assembly_does(models: dict) -> None:
    """The bolt through the plate's hole with its head on the plate, the block on the plate:
    the labels of the placed set are the part-level rows of the same parts as an assembly."""
    names = ["plate", "bolt", "block"]
    poses = [at(), at(20, 20, 10, Rotation.from_euler("z", 30, degrees=True).as_matrix()),
             at(35, 10, 10)]
    labels = label_placed([models[n] for n in names], poses)
    solids = [StepSolid(SolidInfo(k, n, "", np.eye(4), f"asm/{n}"),
                        TopoDS.Solid_s(models[n].part.shape.Moved(
                            TopLoc_Location(pose_trsf(p)))))
              for k, (n, p) in enumerate(zip(names, poses, strict=True))]
    table = extract_mates(solids).level("part")
    for i in range(3):
        for j in range(i + 1, 3):
            rows = table[(table.index_a == i) & (table.index_b == j)]
            assert set(rows.relation) == {r.value for r in labels.relation(i, j).holding()}
    assert labels.relation(0, 1)[CONCENTRIC] and labels.relation(0, 1)[COINCIDENT]
    assert labels.relation(0, 2)[COINCIDENT] and not labels.relation(0, 2)[CONCENTRIC]
    assert labels.relation(1, 0).truth[6:] == labels.relation(0, 1).truth[6:]
    assert labels.relation(1, 0)[Relation.LEFT] and labels.relation(0, 1)[Relation.RIGHT]


def test_moving_everything_changes_nothing(models: dict) -> None:
    names = ["plate", "bolt", "block", "pin"]
    poses = [at(), at(20, 20, 10), at(35, 10, 10.05), at(80, 0, 0)]
    rot = Rotation.from_euler("xyz", [-23, 48, 131], degrees=True).as_matrix()
    motion = at(-500, 42, 3000, rot)
    before = label_placed([models[n] for n in names], poses)
    after = label_placed([models[n] for n in names], [motion @ p for p in poses],
                         view_axis=rot @ np.array([0.0, 1.0, 0.0]))
    for i, j in before.ordered_pairs():
        b, a = before.relation(i, j), after.relation(i, j)
        # the directional relations follow the view axis, which turned out of the ground
        assert b.truth[6:] == a.truth[6:] and b.near[6:] == a.near[6:], (i, j)
        assert b.contact.to_dict() == pytest.approx(a.contact.to_dict(), abs=1e-6, nan_ok=True)


def test_one_part_placed_twice_is_two_parts(models: dict) -> None:
    """Two instances of the ring stacked on one axis: coaxial bores 0 mm apart, faces flat."""
    labels = label_placed([models["ring"], models["ring"]], [at(), at(0, 0, 6)])
    rr = labels.relation(0, 1)
    assert rr[CONCENTRIC] and rr[COINCIDENT] and rr[Relation.BELOW]
    with pytest.raises(ValueError, match="itself"):
        labels.relation(1, 1)


@pytest.mark.parametrize(("lift", "holds", "near"), [
    (0.0, True, False), (0.05, True, True), (TOL.contact_mm, True, True),
    (0.15, False, True), (0.25, False, False)])
def test_coincident_near_the_contact_tolerance(models: dict, lift: float, holds: bool,
                                               near: bool) -> None:
    rr = label_placed([models["plate"], models["block"]], [at(), at(35, 10, 10 + lift)]
                      ).relation(0, 1)
    assert rr[COINCIDENT] is holds and rr.near[K[COINCIDENT]] is near
    assert rr[Relation.PARALLEL] is not holds  # parallel faces not in contact


@pytest.mark.parametrize(("gap", "holds", "near"), [
    (0.5, True, False), (0.9, True, True), (1.1, False, True), (1.3, False, False)])
def test_concentric_near_the_gap(models: dict, gap: float, holds: bool, near: bool) -> None:
    """A pin standing on a ring's bore: the bore and the pin's side meet at the rim when the
    gap closes (radii 4 and 4), so the faces are ``gap`` mm apart."""
    rr = label_placed([models["ring"], models["pin"]], [at(), at(0, 0, 6 + gap)]).relation(1, 0)
    measured = gap if gap <= 1.2 else float("nan")  # beyond the loosened limit: not measured
    assert rr.contact.concentric_gap_mm == pytest.approx(measured, abs=1e-6, nan_ok=True)
    assert rr[CONCENTRIC] is holds and rr.near[K[CONCENTRIC]] is near


def test_an_axis_shifted_past_the_coaxial_tolerance_is_near_and_not_concentric(
        models: dict) -> None:
    inside = label_placed([models["ring"], models["pin"]], [at(), at(0.05, 0, 6)]).relation(0, 1)
    outside = label_placed([models["ring"], models["pin"]], [at(), at(0.2, 0, 6)]).relation(0, 1)
    assert inside[CONCENTRIC] and inside.near[K[CONCENTRIC]]
    assert not outside[CONCENTRIC] and outside.near[K[CONCENTRIC]]


def test_parts_apart_need_no_mesh(models: dict) -> None:
    labels = label_placed([models["plate"], models["pin"]], [at(), at(200, 0, 0)])
    assert labels.face_mates.coincident == () and labels.face_mates.concentric == ()
    assert labels.proxies.built() == 0
    assert not labels.relation(0, 1).near[K[CONCENTRIC]]


def test_bad_poses_are_refused(models: dict) -> None:
    with pytest.raises(ValueError, match="poses"):
        label_placed([models["pin"]], [])
    with pytest.raises(ValueError, match="4, 4"):
        label_placed([models["pin"]], [np.eye(3)])
