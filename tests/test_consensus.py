"""Each part held against where the rest of the assembly puts it (``cadio.inspect.consensus``),
and a mate's residual held to the sigma along its own direction (``cadio.inspect.asbuilt``)."""

from __future__ import annotations

import math

import numpy as np

from cadio.inspect.asbuilt import (
    BROKEN,
    HOLDS,
    NOT_INSPECTABLE,
    NOT_OBSERVABLE,
    Limits,
    PartAsBuilt,
    assembly_as_built,
    mate_as_built,
)
from cadio.inspect.consensus import rest_of_assembly
from cadio.inspect.uncertainty import PoseUncertainty, pose_uncertainty, small_motion


def _moved(deg: float, axis: tuple[float, float, float], t: tuple[float, float, float]
           ) -> np.ndarray:
    """Turned ``deg`` about ``axis`` through the origin, then shifted by ``t``."""
    a = np.asarray(axis, dtype=float)
    return small_motion(np.concatenate([math.radians(deg) * a / np.linalg.norm(a), t]),
                        np.zeros(3))


def _part(index: int, pose: np.ndarray, shift_mm: tuple[float, float, float],
          turn_deg: float = 0.05) -> PartAsBuilt:
    """A registered part whose pose errs ``shift_mm`` (sigma along world X, Y, Z) and
    ``turn_deg`` about each axis."""
    turn = math.radians(turn_deg) ** 2
    cov = np.diag([turn] * 3 + [s * s for s in shift_mm])
    return PartAsBuilt(index, pose, PoseUncertainty(pose[:3, 3].copy(), 10.0, cov,
                                                    np.zeros((0, 6))))


# A frame (0) at the origin with a pin (1) on its Z axis through (0, 0, 0), and four more
# parts round it, each on the frame's face (its own mate with it): the assembly as designed.
DESIGN = {0: np.eye(4), 1: _moved(0, (0, 0, 1), (0, 0, 20)),
          **{k: _moved(0, (0, 0, 1), (60 * math.cos(k), 60 * math.sin(k), 5)) for k in range(2, 6)}}
PIN = {"index_a": 0, "index_b": 1, "face_a": 1, "face_b": 2, "relation": "concentric",
       "level": "face", "axis": [0, 0, 1.0], "origin": [0, 0, 0.0]}
FACES = [{"index_a": 0, "index_b": k, "face_a": 3, "face_b": 4, "relation": "coincident",
          "level": "face", "axis": [0, 0, 1.0], "origin": [*DESIGN[k][:2, 3], 5.0]}
         for k in range(2, 6)]
CENTRES = dict.fromkeys(DESIGN, np.zeros(3))
RADII = dict.fromkeys(DESIGN, 10.0)
AXES: dict[int, np.ndarray | None] = dict.fromkeys(DESIGN, None)


def _built(where: np.ndarray, moves: dict[int, np.ndarray], unsure_pin: bool = True,
           pin_seen: bool = True) -> dict[int, PartAsBuilt]:
    """The parts registered where ``where`` (assembly -> world) puts the design, each moved
    by ``moves`` (world motions), the pin's pose unsure by 3 mm and 10 degrees."""
    out = {}
    for i, d in DESIGN.items():
        pose = moves.get(i, np.eye(4)) @ where @ d
        out[i] = _part(i, pose, (3.0, 3.0, 3.0), 10.0) if i == 1 and unsure_pin else \
            _part(i, pose, (0.1, 0.1, 0.1))
    if not pin_seen:
        out[1] = PartAsBuilt(1, None, None, "too little of it visible")
    return out


def _rest(parts: dict[int, PartAsBuilt], nominal: np.ndarray) -> dict:
    return rest_of_assembly(parts, DESIGN, nominal, CENTRES, RADII, AXES)


def test_a_frame_moved_off_its_place_breaks_its_mate_with_an_unsure_pin() -> None:
    where = _moved(20, (1, 1, 1), (300, -40, 15))
    shifted = _moved(0, (0, 0, 1), tuple(where[:3, :3] @ np.array([5.0, 0, 0])))
    parts = _built(where, {0: shifted})
    # read from the two registered poses alone, the pin's 3 mm of sigma hides the 5 mm
    alone = mate_as_built(PIN, parts, DESIGN, Limits.of())
    assert alone.status == HOLDS
    # the four parts on its face say where the frame belongs: it is off by 5 mm there
    # (the alignment the route found was pulled half way by the frame)
    nominal = _moved(0, (0, 0, 1), tuple(where[:3, :3] @ np.array([2.5, 0, 0]))) @ where
    mate = mate_as_built(PIN, parts, DESIGN, Limits.of(), _rest(parts, nominal))
    assert mate.status == BROKEN
    assert "part 0 against part 1 where the rest of the assembly puts it" == mate.reason
    assert abs(mate.row()["axis_distance_mm"] - 5.0) < 0.2
    assert mate.row()["axis_distance_mm_threshold"] < 2.0


def test_an_intact_assembly_holds_wherever_it_stands_and_however_it_was_aligned() -> None:
    where = _moved(35, (0, 1, 1), (-120, 80, 40))
    rng = np.random.default_rng(3)
    noise = {i: _moved(rng.normal(0, 0.03), tuple(rng.normal(size=3)),
                       tuple(rng.normal(0, 0.05, 3))) for i in DESIGN}
    parts = _built(where, noise)
    for nominal in (where, _moved(1.0, (1, 0, 0), (2.0, -1.0, 0.5)) @ where):
        built = assembly_as_built([PIN, *FACES], parts, DESIGN, Limits.of(),
                                  _rest(parts, nominal))
        assert [m.status for m in built] == [HOLDS] * 5, built


def test_a_part_seen_too_little_is_held_where_the_rest_of_the_assembly_puts_it() -> None:
    where = np.eye(4)
    parts = _built(where, {}, pin_seen=False)
    intact = mate_as_built(PIN, parts, DESIGN, Limits.of(), _rest(parts, where))
    assert intact.status == NOT_INSPECTABLE
    moved = _built(where, {0: _moved(0, (0, 0, 1), (0, 4.0, 0))}, pin_seen=False)
    mate = mate_as_built(PIN, moved, DESIGN, Limits.of(), _rest(moved, where))
    assert mate.status == BROKEN and abs(mate.row()["axis_distance_mm"] - 4.0) < 0.2


def test_too_few_parts_make_no_consensus() -> None:
    few = {i: p for i, p in _built(np.eye(4), {}).items() if i < 3}
    assert _rest(few, np.eye(4)) == {}


def test_a_residual_is_held_to_the_sigma_along_its_own_direction() -> None:
    """A pin whose pose is sure across X but not across Y: moved 1 mm along X it is off its
    axis, though the least sure direction across the axis would allow 3 mm."""
    design = {0: np.eye(4), 1: DESIGN[1]}
    frame = _part(0, np.eye(4), (0.05, 0.05, 0.05))
    along_x = _part(1, _moved(0, (0, 0, 1), (1.0, 0, 20)), (0.1, 1.0, 0.1))
    mate = mate_as_built(PIN, {0: frame, 1: along_x}, design, Limits.of())
    assert mate.status == BROKEN
    assert mate.row()["axis_distance_mm_threshold"] < 1.0
    along_y = _part(1, _moved(0, (0, 0, 1), (0, 1.0, 20)), (0.1, 1.0, 0.1))
    assert mate_as_built(PIN, {0: frame, 1: along_y}, design, Limits.of()).status == HOLDS


def test_a_mate_holds_only_where_every_direction_across_it_is_seen() -> None:
    """A pin whose fit leaves its slide along Y open: off its axis along X it is broken (that
    direction is seen); within its threshold it is not observable, never a pass."""
    design = {0: np.eye(4), 1: DESIGN[1]}
    frame = _part(0, np.eye(4), (0.05, 0.05, 0.05))

    def blind_y(pose: np.ndarray) -> PartAsBuilt:
        hessian = np.diag([1e4, 1e4, 1e4, 1e4, 0.0, 1e4])
        return PartAsBuilt(1, pose, pose_uncertainty(hessian, 0.5, 100, pose[:3, 3], 10.0, 1.0))

    off = mate_as_built(PIN, {0: frame, 1: blind_y(_moved(0, (0, 0, 1), (2.0, 0, 20)))},
                        design, Limits.of())
    assert off.status == BROKEN
    on = mate_as_built(PIN, {0: frame, 1: blind_y(_moved(0, (0, 0, 1), (0.1, 0, 20)))},
                       design, Limits.of())
    assert on.status == NOT_OBSERVABLE


def test_a_fit_without_inliers_is_left_out_of_the_consensus() -> None:
    where = np.eye(4)
    parts = _built(where, {0: _moved(0, (0, 0, 1), (0, 4.0, 0))})
    lost = pose_uncertainty(np.eye(6), math.inf, 0, np.zeros(3), 10.0)  # no inliers: no sigma
    parts[3] = PartAsBuilt(3, DESIGN[3], lost)
    rest = _rest(parts, where)
    assert 3 not in rest and 0 in rest
    mate = mate_as_built(PIN, parts, DESIGN, Limits.of(), rest)
    assert mate.status == BROKEN and abs(mate.row()["axis_distance_mm"] - 4.0) < 0.2
