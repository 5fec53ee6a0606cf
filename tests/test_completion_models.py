"""Shape completion models on the CPU at small sizes (16^3 in, 32^3 out): shapes, learning,
seeding, the critic's penalty, checkpoints, exact resume, the data contract and bad inputs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from models.checkpoint import (
    FORMAT,
    build_model,
    load_checkpoint,
    model_card,
    model_from_checkpoint,
    save_checkpoint,
)
from models.completion import (
    CompletionConfig,
    Critic,
    Generator,
    gradient_penalty,
    union_views,
)
from models.completions import learned
from models.data import CompletionDataset, Example, read_shard, training_batch, write_shard
from models.errors import CheckpointError, ShardError
from models.synthetic import box, cylinder, example, synthetic_examples
from models.train import TrainEvent, config_for, predict, train_completion

METHODS = learned()  # every learned completion method of the registry
SMALL = {"n_in": 16, "n_out": 32, "width": 4, "batch_size": 2, "eval_every": 2}


@pytest.fixture(autouse=True)
def one_thread():  # type: ignore[no-untyped-def]
    """Models this small run fastest on one thread; on a busy machine two threads wait on
    each other for far longer than the work takes."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def small(method: str, **overrides: object) -> CompletionConfig:
    return config_for(method, **{**SMALL, **overrides})  # type: ignore[return-value]


@pytest.fixture(scope="module")
def two_parts() -> CompletionDataset:
    """A box and a cylinder, each seen from three views (view 0: its front-visible surface)."""
    solids = [box(32, (16, 16, 16), (9, 6, 5)), cylinder(32, (15, 17, 16), 7.0, 10.0)]
    return CompletionDataset([example(s, 16, 3, {"part_id": str(i)}) for i, s in enumerate(solids)])


@pytest.fixture(scope="module")
def parts() -> CompletionDataset:
    return CompletionDataset(synthetic_examples(6, 16, 32, n_views=3, seed=1))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("n_views", [1, 3])
def test_output_shapes(method: str, n_views: int, parts: CompletionDataset) -> None:
    torch.manual_seed(0)
    model = build_model(small(method))
    batch = parts.batch([0, 1], [list(range(n_views))] * 2)
    logits = model(batch.model_input(model.input_key))
    assert logits.shape == (2, 1, 32, 32, 32)
    probs = predict(model, parts, batch_size=4, n_views=n_views)
    assert probs.shape == (6, 32, 32, 32) and probs.dtype == np.float32
    assert 0 <= probs.min() and probs.max() <= 1


@pytest.mark.parametrize("method", METHODS)
def test_loss_falls_when_overfitting_two_parts(method: str, two_parts: CompletionDataset) -> None:
    cfg = small(method, width=8, lr=3e-3, eval_every=100, max_views=3)
    result = train_completion(cfg, two_parts, None, steps=40)
    ce = [s["ce"] for s in result.losses]
    assert np.mean(ce[-5:]) < 0.5 * np.mean(ce[:5])


@pytest.mark.parametrize("method", METHODS)
def test_same_seed_gives_the_same_losses(method: str, parts: CompletionDataset) -> None:
    runs = [train_completion(small(method), parts, None, steps=3).losses for _ in range(2)]
    assert runs[0] == runs[1]
    other = train_completion(small(method, seed=7), parts, None, steps=3).losses
    assert other != runs[0]


def test_gradient_penalty_is_finite_and_non_negative(parts: CompletionDataset) -> None:
    torch.manual_seed(0)
    cfg = small("gan_lstm")
    critic = Critic(cfg)
    batch = parts.batch([0, 1, 2], [[0]] * 3)
    observed = union_views(batch.inputs)[:, 0]
    fake = torch.rand_like(batch.target)
    gp = gradient_penalty(critic, observed, batch.target, fake, torch.rand(3))
    assert math.isfinite(gp.item()) and gp.item() >= 0
    gp.backward()  # the penalty trains the critic: it must reach every weight (not the biases)
    assert all(p.grad is not None for n, p in critic.named_parameters() if "weight" in n)


@pytest.mark.parametrize("method", METHODS)
def test_checkpoint_round_trip_reproduces_predictions(method: str, parts: CompletionDataset,
                                                      tmp_path: Path) -> None:
    result = train_completion(small(method), parts, parts, steps=2,
                              data_info={"source": "synthetic"})
    path = save_checkpoint(result.checkpoint, tmp_path / f"{method}.pt")
    raw = torch.load(path, weights_only=True)
    assert raw["format"] == FORMAT and raw["method"] == method
    assert raw["data"] == {"train": 6, "val": 6, "source": "synthetic"}
    assert raw["step"] == 2 and "val_iou" in raw["metrics"] and "+" in raw["code_version"]
    assert "train_state" not in raw  # the shipped checkpoint holds no optimiser
    assert f"# {method} completion model" in model_card(raw, "make train")
    loaded = model_from_checkpoint(load_checkpoint(path))
    same = predict(loaded, parts, n_views=2) == predict(result.model, parts, n_views=2)
    assert same.all()


@pytest.mark.parametrize("method", ["gan_lstm", "r2n2"])
def test_resume_repeats_the_uninterrupted_losses(method: str, parts: CompletionDataset,
                                                 tmp_path: Path) -> None:
    cfg = small(method, gp_every=2) if method == "gan_lstm" else small(method)
    whole = train_completion(cfg, parts, parts, steps=6)
    snapshots: list[TrainEvent] = []
    first = train_completion(cfg, parts, parts, steps=4, progress=snapshots.append)
    assert [e.step for e in snapshots if e.snapshot] == [2, 4]
    path = save_checkpoint(snapshots[1].snapshot or {}, tmp_path / "step4.pt")
    resumed = train_completion(cfg, parts, parts, steps=6, resume=path)
    assert first.losses == whole.losses[:4]
    assert resumed.losses == whole.losses
    assert resumed.history[-1]["val_iou"] == whole.history[-1]["val_iou"]
    assert np.array_equal(predict(resumed.model, parts), predict(whole.model, parts))


def test_resume_refuses_another_config_or_a_shipped_checkpoint(parts: CompletionDataset) -> None:
    examples = [parts.example(i) for i in range(3)]  # a plain list of examples works too
    result = train_completion(small("ae"), examples, None, steps=1)
    with pytest.raises(ValueError, match="another config"):
        train_completion(small("ae", lr=1e-3), examples, None, steps=2, resume=result.last)
    with pytest.raises(ValueError, match="train_state"):
        train_completion(small("ae"), examples, None, steps=2, resume=result.checkpoint)


def test_wrong_shapes_raise_value_errors_naming_the_shape(parts: CompletionDataset) -> None:
    gen = Generator(small("gan_lstm"))
    with pytest.raises(ValueError, match=r"\(2, 1, 2, 16, 16, 8\)"):
        gen(torch.zeros(2, 1, 2, 16, 16, 8))
    with pytest.raises(ValueError, match=r"\(1, 16, 16, 16\)"):
        gen(torch.zeros(1, 16, 16, 16))
    with pytest.raises(ValueError, match=r"\(1, 1, 16, 16, 16\)"):
        gen(torch.zeros(1, 1, 16, 16, 16))  # occupancy alone: the free channel is missing
    r2n2 = build_model(small("r2n2"))
    with pytest.raises(ValueError, match=r"\(1, 1, 2, 16, 16\)"):
        r2n2(torch.zeros(1, 1, 2, 16, 16))
    with pytest.raises(ValueError, match=r"\(1, 2, 32, 32\)"):
        predict(gen, [np.zeros((2, 32, 32), bool)])
    ex = parts.example(0)
    with pytest.raises(ValueError, match=r"\(3, 2, 16, 16\)"):
        Example(ex.inputs, ex.target, np.zeros((3, 2, 16, 16), np.float32))
    with pytest.raises(ValueError, match=r"\(9, 2, 16, 16, 16\)"):
        Example(np.zeros((9, 2, 16, 16, 16), bool), ex.target)
    with pytest.raises(ValueError, match=r"\(3, 16, 16, 16\)"):
        Example(np.zeros((3, 16, 16, 16), bool), ex.target)  # occupancy alone: no free space
    no_depth = CompletionDataset([Example(ex.inputs, ex.target)])
    with pytest.raises(ValueError, match="no 'depth' views"):
        predict(r2n2, no_depth)
    with pytest.raises(ValueError, match="no 'depth' views"):
        train_completion(small("r2n2"), no_depth, None, steps=1)
    with pytest.raises(ValueError, match="differ from the config"):
        train_completion(config_for("ae"), parts, None, steps=1)


def test_configs_reject_impossible_grids() -> None:
    with pytest.raises(ValueError, match="n_out"):
        CompletionConfig(n_in=32, n_out=48)
    with pytest.raises(ValueError, match="n_in"):
        CompletionConfig(n_in=24)
    with pytest.raises(ValueError, match="unknown completion method"):
        config_for("voxnet")


def test_union_of_views_makes_ae_blind_to_repeats(parts: CompletionDataset) -> None:
    torch.manual_seed(0)
    ae = build_model(small("ae"))
    once, twice = parts.batch([0], [[0, 1]]), parts.batch([0], [[0, 1, 1, 0]])
    assert torch.equal(ae(once.inputs), ae(twice.inputs))


def test_shards_round_trip_and_refuse_missing_keys(parts: CompletionDataset,
                                                    tmp_path: Path) -> None:
    paths = []
    for i in range(3):
        write_shard(tmp_path / f"{i}.npz", parts.example(i))
        paths.append(tmp_path / f"{i}.npz")
    lazy = CompletionDataset.from_shards(paths)
    assert (len(lazy), lazy.n_in, lazy.n_out) == (3, 16, 32)
    back = lazy.example(1)
    assert np.array_equal(back.inputs, parts.example(1).inputs) and back.meta["part_id"]
    assert lazy[1]["depth"].shape == (3, 2, 32, 32)
    np.savez(tmp_path / "bad.npz", inputs=back.inputs, target=back.target)
    with pytest.raises(ShardError, match="keys"):
        read_shard(tmp_path / "bad.npz")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "0.npz")


def test_training_batches_are_a_function_of_seed_and_step(parts: CompletionDataset) -> None:
    counts = parts.view_counts()
    a, b = (training_batch(parts, counts, 5, 4, 3, seed=0) for _ in range(2))
    assert torch.equal(a.inputs, b.inputs) and torch.equal(a.target, b.target)
    seen = {training_batch(parts, counts, s, 2, 3, seed=0).inputs.shape[1] for s in range(20)}
    assert seen == {1, 2, 3}
    views = parts.batch([0], [[0]]).inputs
    assert torch.equal(training_batch(parts, counts, 0, 1, 1, seed=0).inputs.amax(), views.amax())


def test_batches_take_recorded_sequences_whole() -> None:
    """An example recorded with k views had its grid placed from those k views: a batch of k
    views takes such examples whole rather than cutting longer ones down."""
    singles = synthetic_examples(4, n_in=16, n_out=32, n_views=1, seed=1)
    pairs = synthetic_examples(4, n_in=16, n_out=32, n_views=2, seed=2)
    data = CompletionDataset(singles + pairs)
    counts = data.view_counts()
    ks = [training_batch(data, counts, s, 3, 2, seed=0).inputs.shape[1] for s in range(40)]
    assert set(ks) == {1, 2} and 10 <= ks.count(1) <= 30  # one view half of the time
    pair_inputs = {tuple(np.flatnonzero(ex.inputs[1])[:20]) for ex in pairs}
    for s in range(40):
        batch = training_batch(data, counts, s, 3, 2, seed=0)
        if batch.inputs.shape[1] == 2:
            for second in batch.inputs[:, 1].numpy().astype(bool):
                assert tuple(np.flatnonzero(second)[:20]) in pair_inputs


def test_surface_dropout_thins_the_seen_surface_only(parts: CompletionDataset) -> None:
    counts = parts.view_counts()
    plain = training_batch(parts, counts, 3, 4, 3, seed=0)
    thinned = training_batch(parts, counts, 3, 4, 3, seed=0, surface_dropout=0.9)
    assert torch.equal(plain.inputs[:, :, 1], thinned.inputs[:, :, 1])  # free space kept
    assert 0 < thinned.inputs[:, :, 0].sum() < plain.inputs[:, :, 0].sum()
    assert (thinned.inputs[:, :, 0] <= plain.inputs[:, :, 0]).all()
    with pytest.raises(ValueError, match="surface_dropout"):
        small("gan_lstm", surface_dropout=1.0)


def test_mirror_flips_views_and_truth_of_the_same_examples_across_x(
        parts: CompletionDataset) -> None:
    counts = parts.view_counts()
    plain = training_batch(parts, counts, 5, 8, 3, seed=0)
    mirrored = training_batch(parts, counts, 5, 8, 3, seed=0, mirror=0.5)
    flipped = [not torch.equal(a, b) for a, b in zip(plain.target, mirrored.target, strict=True)]
    assert any(flipped) and not all(flipped)  # about half, drawn per example
    for i, f in enumerate(flipped):
        source = plain.inputs[i].flip(-3) if f else plain.inputs[i]
        assert torch.equal(mirrored.inputs[i], source)
        assert torch.equal(mirrored.target[i], plain.target[i].flip(-3) if f else plain.target[i])
        if plain.depth is not None:
            assert mirrored.depth is not None
            depth = plain.depth[i].flip(-2) if f else plain.depth[i]
            assert torch.equal(mirrored.depth[i], depth)
    with pytest.raises(ValueError, match="mirror"):
        small("ae", mirror=1.5)


def test_a_run_started_from_a_checkpoint_starts_from_its_weights(
        two_parts: CompletionDataset) -> None:
    first = train_completion(small("ae"), two_parts, None, steps=2,
                             data_info={"train_parts": ["a", "b"]})
    tuned = train_completion(small("ae", mirror=0.5), two_parts, None, steps=0,
                             init=first.checkpoint, data_info={"train_parts": ["c", "a"]})
    for k, v in first.model.state_dict().items():
        assert torch.equal(tuned.model.state_dict()[k], v), k
    assert tuned.checkpoint["data"]["init"]["step"] == first.checkpoint["step"]
    # the tuned weights learned from the first run's parts too: they are never held out for it
    assert tuned.checkpoint["data"]["train_parts"] == ["a", "b", "c"]
    # with a validation split, the checkpoint says how good its start was there
    scored = train_completion(small("ae"), two_parts, two_parts, steps=0, init=first.checkpoint)
    start = scored.checkpoint["data"]["init"]
    assert 0.0 <= start["val_iou"] <= 1.0 and start["val_ce"] > 0
    with pytest.raises(ValueError, match="does not fit"):
        train_completion(small("ae", width=6), two_parts, None, steps=0, init=first.checkpoint)
    with pytest.raises(ValueError, match="one of them"):
        train_completion(small("ae"), two_parts, None, steps=0, init=first.checkpoint,
                         resume=first.last)


def test_a_checkpoint_made_from_an_uninstalled_tree_names_the_trees_version(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A copy of the tree on a GPU machine has no installed package: the version comes from its
    pyproject.toml, not ``unknown``."""
    import tomllib
    from importlib import metadata

    import models.checkpoint as checkpoint

    root = Path(checkpoint.__file__).resolve().parents[1]
    version = tomllib.loads((root / "pyproject.toml").read_text())["project"]["version"]
    installed = checkpoint.code_version()

    def absent(name: str) -> str:
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(checkpoint.metadata, "version", absent)
    assert checkpoint.code_version() == f"{version}+{installed.split('+')[1]}"
    (tmp_path / "pyproject.toml").write_text("[project]\nname = 'x'\n")
    assert checkpoint._tree_version(tmp_path / "pyproject.toml") == "unknown"
    assert checkpoint._tree_version(tmp_path / "absent.toml") == "unknown"
