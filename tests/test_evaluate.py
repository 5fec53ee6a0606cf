"""The completion harness: every method on the same examples, scored, registered, reported."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import torch

from cadio.camera.render import CaptureConfig
from cadio.capture.examples import (
    ExampleConfig,
    observed_example,
    oracle_example,
    render_part_views,
    with_truth,
    write_example,
)
from cadio.records import Mesh
from models.checkpoint import save_checkpoint
from models.evaluate import (
    complete,
    learned_solids,
    load_models,
    part_inputs,
    register_completion,
    score_files,
    write_completion_report,
)
from models.synthetic import synthetic_examples
from models.train import config_for, train_completion
from reports.completion import read_completion_parts

CFG = ExampleConfig(n_in=16, n_out=32)
TINY = {"n_in": 16, "n_out": 32, "width": 4, "batch_size": 2, "eval_every": 5}


@pytest.fixture(scope="module")
def examples(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Four example files of a box: two single views and a pair, both protocols."""
    box = o3d.geometry.TriangleMesh.create_box(60, 40, 30)
    mesh = Mesh(np.asarray(box.vertices, np.float64), np.asarray(box.triangles, np.int64))
    pose = np.eye(4)
    pose[:3, 3] = [-30, -20, 0]
    views, to_world = render_part_views(mesh, pose, [0, 31], CaptureConfig())
    folder = tmp_path_factory.mktemp("inputs") / "capture" / "box-0"
    paths = []
    for seq in ([views[0]], [views[1]], views):
        for ex in (observed_example(seq, CFG), oracle_example(seq, mesh, to_world, CFG)):
            ex = with_truth(ex, mesh, to_world, CFG)
            path = folder / f"{ex.protocol}-{'-'.join(str(v.view) for v in seq)}.npz"
            write_example(path, ex, {"part_id": "box-0"})
            paths.append(path)
    return paths


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Tiny checkpoints of the three learned methods, observed protocol only."""
    torch.set_num_threads(1)
    folder = tmp_path_factory.mktemp("ckpt")
    data = synthetic_examples(4, n_in=16, n_out=32, n_views=2)
    for method in ("gan_lstm", "ae", "r2n2"):
        result = train_completion(config_for(method, **TINY), data, None, steps=5,
                                  data_info={"protocol": "observed", "train_parts": ["p-0"]})
        save_checkpoint(result.checkpoint, folder / f"completion-{method}-observed.pt")
    return folder


def test_every_method_completes_the_same_example(examples: list[Path],
                                                 checkpoints: Path) -> None:
    from cadio.capture.examples import read_example

    models = load_models(checkpoints)
    assert set(models.models) == {(m, "observed") for m in ("gan_lstm", "ae", "r2n2")}
    assert models.trained_on() == {"p-0"}
    observed = read_example(examples[4])  # the pair of views
    preds = complete(models, observed)
    assert set(preds) == {"visible", "carve", "gan_lstm", "ae", "r2n2"}
    assert all(p.shape == (32, 32, 32) and p.dtype == bool for p in preds.values())
    oracle = complete(models, read_example(examples[5]))
    assert set(oracle) == {"visible", "carve"}  # no oracle-box checkpoint in the folder


def test_a_forward_pass_of_many_examples_gives_each_its_own_solid(examples: list[Path],
                                                                  checkpoints: Path) -> None:
    """The stage completes a folder's examples several to a forward pass (single views and
    sequences of two, both protocols, mixed): each gets the solids it gets alone."""
    from cadio.capture.examples import read_example

    models = load_models(checkpoints)
    read = [read_example(p) for p in examples]
    together = learned_solids(models, read)
    for example, solids in zip(read, together, strict=True):
        [alone] = learned_solids(models, [example])
        assert set(solids) == set(alone) == ({"gan_lstm", "ae", "r2n2"}
                                             if example.protocol == "observed" else set())
        assert all(np.array_equal(solids[m], alone[m]) for m in alone)


def test_scores_cover_each_example_and_method_once(examples: list[Path], checkpoints: Path,
                                                   tmp_path: Path) -> None:
    models = load_models(checkpoints)
    scores = score_files([*examples, tmp_path / "missing.npz"], models, lambda pid: "test",
                         lambda pid: "fasteners")
    assert len(scores.failed) == 1 and "missing.npz" in scores.failed[0][0]
    keys = {(r["method"], r["protocol"], r["n_views"], r["view_deg"]) for r in scores.parts}
    assert len(keys) == len(scores.parts) == 3 * 5 + 3 * 2  # observed: 5 methods, oracle: 2
    carve = [r for r in scores.parts if r["method"] == "carve" and r["protocol"] == "observed"]
    assert all(0 < r["iou"] <= 1 for r in carve)
    assert len(scores.registration) == 3
    md = write_completion_report(tmp_path, [scores])
    parts = read_completion_parts(tmp_path)
    assert len(parts) == len(scores.parts)
    assert (tmp_path / "completion_registration.csv").exists()
    assert "missing.npz" in md.read_text()


def test_an_example_that_cannot_be_scored_fails_alone(examples: list[Path], checkpoints: Path,
                                                      tmp_path: Path) -> None:
    """An example whose truth grid is empty (a part the cube holds no voxel of) is a failure
    row naming its file; the examples beside it in the batch are scored."""
    from dataclasses import replace

    from cadio.capture.examples import read_example

    empty = read_example(examples[0])
    assert empty.target is not None
    bad = tmp_path / "box-0" / "observed-9.npz"
    write_example(bad, replace(empty, target=np.zeros_like(empty.target)), {"part_id": "box-0"})
    scores = score_files([bad, examples[0], examples[2]], load_models(checkpoints),
                         lambda pid: "test", lambda pid: "fasteners")
    assert [path for path, _ in scores.failed] == [str(bad)]
    assert "truth grid is empty" in scores.failed[0][1]
    assert len({r["view_deg"] for r in scores.parts}) == 2  # both of the other views
    assert len(scores.parts) == 2 * 5


def test_a_perfect_completion_registers_with_no_residual(examples: list[Path]) -> None:
    from cadio.capture.examples import read_example

    ex = read_example(examples[0])
    assert ex.target is not None
    row = register_completion(ex, ex.target, 32)
    # the surface voxels' centres lie within half a voxel of the true surface
    assert row.fitness > 0.9 and row.residual_mm < ex.voxel_mm
    assert math.isclose(row.view_deg, 0.0, abs_tol=1e-9)


def _instance(folder: Path, part: str, capture: str, **meta: object) -> None:
    folder.mkdir(parents=True)
    np.savez(folder / "observed-0.npz", meta=np.array(json.dumps(
        {"part_id": part, "capture": capture, **meta})))


def test_a_part_in_two_captures_is_scored_once_per_context(tmp_path: Path) -> None:
    """Folders are instances (1, 2, ...): two scenes' instance 1 are different parts, and one
    part shown by a pair scene and by an assembly is scored in each."""
    for capture, parts in (("s1", ("a", "b")), ("s2", ("b", "c"))):
        for i, part in enumerate(parts, 1):
            _instance(tmp_path / capture / str(i), part, capture)
    _instance(tmp_path / "assembly-x" / "1", "a", "assembly-x")
    (tmp_path / "s2" / "3").mkdir()  # an instance without examples is skipped
    # a part its capture does not score has only its views' inputs: passed over
    _instance(tmp_path / "alone-d" / "1", "d", "alone-d")
    _instance(tmp_path / "a0" / "1", "d", "a0", input_only=True)
    found = part_inputs([tmp_path / "s2", tmp_path / "s1", tmp_path / "assembly-x",
                         tmp_path / "gone", tmp_path / "a0", tmp_path / "alone-d"])
    assert sorted(str(p.relative_to(tmp_path)) for p in found) == [
        "alone-d/1", "assembly-x/1", "s1/1", "s1/2", "s2/2"]


def test_a_method_that_fails_on_an_example_leaves_the_others_standing(
        examples: list[Path], caplog: pytest.LogCaptureFixture) -> None:
    """A registration that raises on one example (its CAD method) is logged and left out of
    that example; every other method's solid stands."""
    from cadio.capture.examples import read_example
    from cadio.inspect.completion import CaptureCad
    from cadio.registry import Role
    from models.completions import COMPLETIONS, CompletionMethod

    failing = CompletionMethod("failing", "raises", Role.BASELINE, 9, __name__,
                               from_cad=_raises)

    class OneCapture:  # a capture's CAD for every example: no parts, no views
        def of(self, capture: str) -> CaptureCad:
            return CaptureCad((), {}, 1e-3, {}, {})

    with COMPLETIONS.registered(failing):
        preds = complete(load_models(Path("/nonexistent")), read_example(examples[0]),
                         OneCapture())  # type: ignore[arg-type]
    assert "failing" not in preds and {"visible", "carve"} <= set(preds)
    assert not preds["registered"].any()  # nothing to register it to: an empty solid
    assert "failing of box-0" in caplog.text and "no points to register" in caplog.text


def _raises(example: object, cad: object) -> object:
    raise ValueError("no points to register")
