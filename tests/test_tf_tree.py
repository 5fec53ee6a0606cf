"""The transform tree of a recording: chains, static and timed edges, interpolation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadio.recordings.recording import TransformMsg
from cadio.recordings.tf_tree import TransformTree

S = 10**9


def edge(ns: int, parent: str, child: str, xyz: tuple[float, float, float],
         yaw_deg: float = 0.0, static: bool = False) -> TransformMsg:
    q = Rotation.from_euler("z", yaw_deg, degrees=True).as_quat()
    return TransformMsg(ns, parent, child, xyz, tuple(q), static=static)


def matrix(xyz: tuple[float, float, float], yaw_deg: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    m[:3, 3] = xyz
    return m


@pytest.fixture()
def tree() -> TransformTree:
    """map -> base (timed: 1 m/s along x, turning 10 deg/s) -> camera_link (static) ->
    optical (static, with a ROS 1 style leading slash)."""
    t = TransformTree()
    t.add(edge(0, "base", "camera_link", (0.1, 0.0, 0.5), 90.0, static=True))
    t.add(edge(0, "camera_link", "/optical", (0.0, 0.02, 0.0), static=True))
    for s in (2, 0, 1):  # out of order: the tree sorts them
        t.add(edge(s * S, "map", "base", (float(s), 0.0, 0.0), 10.0 * s))
    return t


def test_a_chain_composes_static_and_timed_edges(tree: TransformTree) -> None:
    got = tree.lookup("optical", 1 * S)
    assert got is not None and got.root == "map" and got.gap_ns == 0
    want = matrix((1, 0, 0), 10) @ matrix((0.1, 0, 0.5), 90) @ matrix((0, 0.02, 0))
    assert got.matrix == pytest.approx(want, abs=1e-12)
    assert tree.chain("/optical") == ["optical", "camera_link", "base", "map"]


def test_between_samples_it_interpolates(tree: TransformTree) -> None:
    got = tree.lookup("base", S // 2)
    assert got is not None and got.gap_ns == 0
    assert got.matrix == pytest.approx(matrix((0.5, 0, 0), 5.0), abs=1e-12)


def test_outside_the_samples_the_nearest_stands_in_and_says_how_far(tree: TransformTree) -> None:
    late = tree.lookup("base", 3 * S)
    assert late is not None and late.gap_ns == S
    assert late.matrix == pytest.approx(matrix((2, 0, 0), 20.0), abs=1e-12)
    early = tree.lookup("optical", -S // 4)
    assert early is not None and early.gap_ns == S // 4


def test_a_fixed_frame_and_the_path_between_two_frames(tree: TransformTree) -> None:
    in_base = tree.lookup("optical", 2 * S, fixed="base")
    assert in_base is not None and in_base.root == "base"
    assert in_base.matrix == pytest.approx(matrix((0.1, 0, 0.5), 90) @ matrix((0, 0.02, 0)),
                                           abs=1e-12)
    assert tree.between("camera_link", "optical", 5 * S) == pytest.approx(
        matrix((0, 0.02, 0)), abs=1e-12)
    tree.add(edge(0, "odom", "other", (1.0, 1.0, 1.0), static=True))
    assert tree.between("other", "optical", 0) is None  # two trees
    assert tree.lookup("optical", 0, fixed="odom") is None
    assert tree.lookup("camera_0", 0) is None  # a frame no edge names


def test_pruning_keeps_what_later_lookups_need(tree: TransformTree) -> None:
    for s in range(3, 10):
        tree.add(edge(s * S, "map", "base", (float(s), 0.0, 0.0)))
    tree.prune(5 * S + S // 2)
    got = tree.lookup("base", 5 * S + S // 2)  # still interpolated between 5 s and 6 s
    assert got is not None and got.gap_ns == 0
    assert got.matrix[:3, 3] == pytest.approx([5.5, 0.0, 0.0])


def test_a_reparented_frame_keeps_its_new_edge_and_a_cycle_ends(tree: TransformTree) -> None:
    tree.add(edge(0, "odom", "base", (0.0, 0.0, 0.0), static=True))
    assert tree.chain("optical")[-1] == "odom"
    tree.add(edge(0, "optical", "odom", (0.0, 0.0, 0.0), static=True))
    assert tree.chain("optical") == ["optical", "camera_link", "base", "odom"]
