"""The relation network (models.relations, models.relations_train) on the CPU at small sizes:
truth values in range, the knowledge base learned, decisions obeying the rules for any input,
seeding, checkpoints, overfitting, violations and calibration error."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from cadio.records import CONVERSE, DIRECTIONAL, SYMMETRIC, Relation
from models.checkpoint import build_model, make_checkpoint, save_checkpoint
from models.completion import CompletionConfig
from models.errors import CheckpointError
from models.relation_decision import combine, decide, swap_decision, violations
from models.relation_logic import and_, exists, forall, implies, knowledge_base, or_
from models.relations import (
    PARALLEL,
    PERPENDICULAR,
    RELATIONS,
    RelationConfig,
    RelationNet,
    normalise_pair,
)
from models.relations_train import (
    Decision,
    RelationData,
    RelationResult,
    evaluate,
    fit_thresholds,
    load_relation_model,
    make_relation_checkpoint,
    predict_relations,
    save_relation_checkpoint,
    train_relations,
    training_batch,
)
from models.synthetic import relation_pairs
from reports.relations import expected_calibration_error

TINY = {"n_points": 64, "train_points": 48, "widths": (8, 16, 16, 32), "embed": 16,
        "ntn_k": 2, "batch_size": 16, "eval_every": 10, "steps": 10, "lr": 3e-3}
IDX = {r: i for i, r in enumerate(RELATIONS)}


@pytest.fixture(autouse=True)
def one_thread():  # type: ignore[no-untyped-def]
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def tiny(**overrides: object) -> RelationConfig:
    return RelationConfig(**{**TINY, **overrides})  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def pairs() -> RelationData:
    return relation_pairs(64, n_points=128, seed=1)


# The network the knowledge-base test trains (max pooling only: its thresholds were set on
# it), once for the module: the joint-head test trains it again with a joint head beside it.
KB_NET = {"descriptors": True, "steps": 300, "batch_size": 32, "eval_every": 100,
          "mean_pool": False, "train_points": 96, "widths": (16, 32, 32, 64), "embed": 32}


@pytest.fixture(scope="module")
def kb_ltn(pairs: RelationData) -> RelationResult:
    before = torch.get_num_threads()
    torch.set_num_threads(1)  # as the tests' own (``one_thread`` is set up after this)
    try:
        return train_relations(tiny(method="ltn", **KB_NET), pairs, pairs)
    finally:
        torch.set_num_threads(before)


def random_net(seed: int, **overrides: object) -> RelationNet:
    torch.manual_seed(seed)
    return RelationNet(tiny(**overrides)).eval()


def test_synthetic_labels_follow_the_rules(pairs: RelationData) -> None:
    labels = pairs.labels
    assert labels.shape == (64, 10) and pairs.points.shape == (64, 2, 128, 3)
    assert labels[:, IDX[Relation.CONCENTRIC]].any() and labels[:, IDX[Relation.LEFT]].any()
    assert not (labels[:, PARALLEL] & labels[:, PERPENDICULAR]).any()
    for r in DIRECTIONAL:  # the cones of opposite directions never overlap
        assert not (labels[:, IDX[r]] & labels[:, IDX[CONVERSE[r]]]).any()


def test_operators_match_product_real_logic() -> None:
    a, b = torch.tensor([0.0, 0.3, 1.0]), torch.tensor([1.0, 0.6, 0.0])
    assert torch.allclose(and_(a, b), a * b, atol=3e-4)
    assert torch.allclose(or_(a, b), a + b - a * b, atol=3e-4)
    assert torch.allclose(implies(a, b), 1 - a + a * b, atol=3e-4)
    x = torch.tensor([1.0, 1.0, 0.0, 0.5])
    assert forall(x, 2).item() == pytest.approx(1 - np.sqrt((1 + 0.25) / 4), abs=1e-3)
    assert exists(x, 2).item() == pytest.approx(np.sqrt((1 + 1 + 0.25) / 4), abs=1e-3)
    assert forall(torch.ones(5), 2).item() < 1  # the stable forms never reach 1 or 0 ...
    one = torch.ones(3, requires_grad=True)
    forall(one, 2).backward()  # ... so the gradient at full truth stays finite
    assert one.grad is not None and torch.isfinite(one.grad).all()


@pytest.mark.parametrize("scale", [1e-30, 1.0, 1e30])
def test_predicates_in_unit_interval(scale: float) -> None:
    net = random_net(0, descriptors=True)
    points = torch.randn(8, 2, 64, 3) * scale
    points[0, 0] = 0.0  # a part collapsed to one point
    points[1] = 5.0  # both parts at one point: zero radius
    logits_ab, logits_ba = net(points)
    for t in (torch.sigmoid(logits_ab), torch.sigmoid(logits_ba)):
        assert t.shape == (8, 10) and torch.isfinite(t).all()
        assert (t >= 0).all() and (t <= 1).all()
    with pytest.raises(ValueError, match="finite"):
        net(torch.full((1, 2, 4, 3), float("nan")))
    with pytest.raises(ValueError, match=r"\(B, 2, P, 3\)"):
        net(torch.zeros(1, 3, 4, 3))


def test_normalisation_is_unit_free_and_keeps_relative_position() -> None:
    pts = torch.randn(4, 2, 32, 3, dtype=torch.float64)
    pts[:, 0] += torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64)
    moved = normalise_pair(pts * 1e3 + 7.0)
    assert torch.allclose(normalise_pair(pts), moved, atol=1e-5)
    assert (moved[:, 0, :, 0].mean(1) > moved[:, 1, :, 0].mean(1)).all()  # a stays right of b
    net = random_net(1)
    with torch.no_grad():  # the same parts in metres instead of millimetres, moved
        mm, m = torch.ones(4), torch.full((4,), 1e3)
        assert torch.allclose(net(pts.float(), mm)[0], net((pts * 1e-3 - 2).float(), m)[0],
                              atol=1e-4)


def test_training_satisfies_the_knowledge_base(pairs: RelationData,
                                               kb_ltn: RelationResult) -> None:
    results = {}
    for method in ("ltn", "mlp"):
        cfg = tiny(method=method, **KB_NET)
        res = kb_ltn if method == "ltn" else train_relations(cfg, pairs, pairs)
        pred = predict_relations(res.checkpoint, pairs)
        kb = knowledge_base(torch.from_numpy(pred.raw_ab), torch.from_numpy(pred.raw_ba),
                            torch.from_numpy(pairs.labels).float(), cfg)
        acc = (pred.decided == pairs.labels).mean()
        results[method] = (kb, acc, res)
    kb, acc, res = results["ltn"]
    # Untrained, the KB sits near 0.6; a broken axiom or operator keeps it well below 0.85.
    assert kb["sat"].item() > 0.85 and kb["rules"].item() > 0.9
    assert acc > 0.95
    assert res.history[-1]["train_sat"] > res.history[0]["train_sat"] + 0.05
    assert res.checkpoint["method"] == "ltn" and len(res.checkpoint["temperatures"]) == 10
    assert len(res.checkpoint["thresholds"]) == 10
    kb, acc, res = results["mlp"]
    assert kb["rules"].item() == 1.0 and kb["facts"].item() > 0.8 and acc > 0.9
    assert res.history[-1]["train_facts"] > res.history[0]["train_facts"]


@pytest.mark.parametrize("seed", range(5))
def test_decisions_obey_the_rules_for_any_input(seed: int) -> None:
    gen = torch.Generator().manual_seed(seed)
    net = random_net(seed, descriptors=bool(seed % 2))
    scale = 10.0 ** torch.randint(-3, 4, (24, 1, 1, 1), generator=gen)
    points = torch.randn(24, 2, 40, 3, generator=gen) * scale
    points[:, 0] += torch.randn(24, 1, 3, generator=gen) * scale[:, 0]
    converse = [IDX[CONVERSE.get(r, r)] for r in RELATIONS]
    temps = np.linspace(0.5, 2.0, 10)
    cut = np.linspace(0.3, 0.7, 10)
    decision = Decision((temps + temps[converse]) / 2, (cut + cut[converse]) / 2)
    labels = np.zeros((24, 10), bool)
    mm = torch.rand(24, generator=gen).double().numpy() * 10
    ab = predict_relations(net, RelationData(points.numpy(), labels, mm), 7, decision)
    ba = predict_relations(net, RelationData(points[:, [1, 0]].numpy(), labels, mm), 7, decision)
    np.testing.assert_array_equal(ba.raw_ab, ab.raw_ba)
    np.testing.assert_array_equal(ba.decided, swap_decision(ab.decided))
    for d in (ab.decided, ba.decided):
        for r in DIRECTIONAL:  # converse pairs of one pair never both hold (asymmetry)
            assert not (d[:, IDX[r]] & d[:, IDX[CONVERSE[r]]]).any()
        assert not (d[:, PARALLEL] & d[:, PERPENDICULAR]).any()
    for r in SYMMETRIC:
        np.testing.assert_array_equal(ab.decided[:, IDX[r]], ba.decided[:, IDX[r]])
    assert ((ab.confidence >= 0) & (ab.confidence <= 1)).all()
    assert (ab.confidence[ab.decided] >= 0.5).all()
    # Hand-made raw outputs hitting every tie and threshold: still consistent.
    raw = np.random.default_rng(seed).choice([0.0, 0.5, 0.7, 1.0], (50, 10))
    raw_ba = np.random.default_rng(seed + 9).choice([0.0, 0.5, 0.7, 1.0], (50, 10))
    d_ab, d_ba = decide(combine(raw, raw_ba)), decide(combine(raw_ba, raw))
    np.testing.assert_array_equal(d_ba, swap_decision(d_ab))
    d_ab = decide(combine(raw, raw_ba), decision.thresholds)
    d_ba = decide(combine(raw_ba, raw), decision.thresholds)
    np.testing.assert_array_equal(d_ba, swap_decision(d_ab))


def test_same_seed_same_losses(pairs: RelationData) -> None:
    def losses(seed: int) -> list[float]:
        return [s["loss"] for s in train_relations(tiny(seed=seed), pairs).losses]

    first = losses(3)
    assert first == losses(3)
    assert first != losses(4)
    b1, b2 = training_batch(pairs, tiny(seed=3), 5), training_batch(pairs, tiny(seed=3), 5)
    assert torch.equal(b1[0], b2[0]) and torch.equal(b1[1], b2[1])


def test_checkpoint_round_trip(pairs: RelationData, tmp_path: Path) -> None:
    res = train_relations(tiny(method="mlp", descriptors=True), pairs, pairs)
    path = save_relation_checkpoint(tmp_path / "rel.pt", res.checkpoint)
    _, decision, ckpt = load_relation_model(path)
    assert ckpt["method"] == "mlp" and ckpt["config"]["descriptors"] is True
    assert ckpt["code_version"] and ckpt["step"] == 10 and "val_f1" in ckpt["metrics"]
    np.testing.assert_array_equal(decision.temperatures, res.decision.temperatures)
    np.testing.assert_array_equal(decision.thresholds, res.decision.thresholds)
    before = predict_relations(res.model, pairs, decision=res.decision)
    after = predict_relations(path, pairs)
    for field in ("raw_ab", "raw_ba", "decided", "confidence"):
        np.testing.assert_array_equal(getattr(before, field), getattr(after, field))
    assert torch.load(path, weights_only=True)["temperatures"] == ckpt["temperatures"]


def test_bad_checkpoints_fail_clearly(pairs: RelationData, tmp_path: Path) -> None:
    ckpt = make_relation_checkpoint(random_net(0), Decision.default(), 0, {})
    with pytest.raises(CheckpointError, match="'mlp'"):
        load_relation_model(save_checkpoint(ckpt, tmp_path / "ltn.pt"), method="mlp")
    broken = {k: v for k, v in ckpt.items() if k != "temperatures"}
    with pytest.raises(CheckpointError, match="temperatures"):
        load_relation_model(save_checkpoint(broken, tmp_path / "broken.pt"))
    with pytest.raises(CheckpointError, match="temperatures"):
        save_relation_checkpoint(tmp_path / "never.pt", broken)
    assert not (tmp_path / "never.pt").exists()
    no_step = {k: v for k, v in ckpt.items() if k != "step"}
    with pytest.raises(CheckpointError, match="missing keys"):
        load_relation_model(save_checkpoint(no_step, tmp_path / "no_step.pt"))
    cfg = CompletionConfig(n_in=16, n_out=32, width=4, gan=False, lstm=False, max_views=1)
    other = save_checkpoint(make_checkpoint(build_model(cfg), 0, {}), tmp_path / "ae.pt")
    with pytest.raises(CheckpointError, match="method 'ae'"):
        load_relation_model(other)
    wrong = {**ckpt, "config": {**ckpt["config"], "embed": 7}}
    with pytest.raises(CheckpointError, match="does not rebuild"):
        load_relation_model(save_checkpoint(wrong, tmp_path / "wrong.pt"))


def test_loss_falls_on_two_samples_and_shapes() -> None:
    data = relation_pairs(2, n_points=64, seed=5)
    # The toy pairs never touch: without contact channels the fit is quicker (0.34 -> 0.12 in
    # 120 steps against 0.37 -> 0.24), and both fall.
    res = train_relations(tiny(steps=120, batch_size=2, eval_every=120, descriptors=True,
                               contact=False), data)
    losses = [s["loss"] for s in res.losses]
    assert np.mean(losses[-5:]) < 0.6 * np.mean(losses[:5])
    touching = train_relations(tiny(steps=120, batch_size=2, eval_every=120, descriptors=True),
                               data)
    losses = [s["loss"] for s in touching.losses]
    assert np.mean(losses[-5:]) < 0.75 * np.mean(losses[:5])
    pred = predict_relations(res.model, data)
    for field in ("raw_ab", "raw_ba", "decided", "confidence", "probability"):
        assert getattr(pred, field).shape == (2, 10)
    assert pred.decided.dtype == bool
    logits_ab, logits_ba = res.model(torch.from_numpy(data.points[:, :, :17]))  # any P
    assert logits_ab.shape == logits_ba.shape == (2, 10)
    empty = RelationData(np.zeros((0, 2, 5, 3), np.float32), np.zeros((0, 10), bool))
    assert predict_relations(res.model, empty).decided.shape == (0, 10)


def test_thresholds_fitted_on_validation_stop_over_predicting_a_rare_relation() -> None:
    """Scores of a relation true in 10% of pairs, positives around 0.8 and negatives spread
    up to 0.7: at 0.5 it is over-predicted; the fitted threshold keeps F1 at its best."""
    rng = np.random.default_rng(0)
    truth = np.zeros((1000, 10), bool)
    truth[:100, IDX[Relation.CONCENTRIC]] = True
    score = np.where(truth, rng.uniform(0.65, 0.95, truth.shape), rng.uniform(0.0, 0.7,
                                                                              truth.shape))
    t = fit_thresholds(score, truth)
    k = IDX[Relation.CONCENTRIC]
    assert 0.6 <= t[k] <= 0.7
    at_half, fitted = decide(score), decide(score, t)
    assert at_half[:, k].sum() > 2 * truth[:, k].sum()
    assert fitted[:, k].sum() < 1.3 * truth[:, k].sum()
    assert t[IDX[Relation.LEFT]] == t[IDX[Relation.RIGHT]]  # converse relations share one


def test_pair_features_and_contact_reach_the_predicates() -> None:
    """With pair evidence configured, the network needs it and uses it; contact channels make
    the outputs depend on the millimetres a unit of the points is (mates are decided in mm)."""
    net = random_net(2, pair_features=5)
    points = torch.randn(4, 2, 30, 3)
    with pytest.raises(ValueError, match=r"\(B, >= 5\)"):
        net(points, torch.ones(4))
    with pytest.raises(ValueError, match=r"\(B, >= 5\); got \(4, 4\)"):
        net(points, torch.ones(4), torch.zeros(4, 4))
    f = torch.zeros(4, 5)
    base = net(points, torch.ones(4), f)[0]
    assert not torch.allclose(base, net(points, torch.ones(4), f + 1)[0])
    # columns after its own width (the geometric answers a network without them leaves) are
    # not read
    assert torch.equal(base, net(points, torch.ones(4), torch.cat([f, torch.ones(4, 4)], 1))[0])
    assert not torch.allclose(base, net(points, torch.full((4,), 50.0), f)[0])
    swapped = net(points[:, [1, 0]], torch.ones(4), f)
    assert torch.allclose(swapped[0], net(points, torch.ones(4), f)[1], atol=1e-6)


def test_a_network_reads_its_named_evidence_and_the_swap_reads_the_direction_negated() -> None:
    """The pair's direction is the one ordered column of the evidence: the network reads the
    columns its config names, and answers the swapped pair, handed the swapped evidence,
    exactly as it answers the pair's second order."""
    from models.geometric import EVIDENCE, evidence_names, swap_evidence

    names = evidence_names("partial")
    with pytest.raises(ValueError, match="evidence must name"):
        tiny(pair_features=2, evidence=("gap_mm", "no_such_column"))
    net = random_net(4, pair_features=len(names), evidence=tuple(names), joints=True)
    gen = np.random.default_rng(4)
    points = gen.normal(size=(6, 2, 30, 3)).astype(np.float32)
    evidence = gen.normal(size=(6, len(EVIDENCE))).astype(np.float32)
    with pytest.raises(ValueError, match=rf"\(B, >= {len(EVIDENCE)}\)"):
        net(torch.from_numpy(points), torch.ones(6), torch.from_numpy(evidence[:, :-1]))
    labels = np.zeros((6, 10), bool)
    data = RelationData(points, labels, np.ones(6), evidence)
    ab, ba = predict_relations(net, data), predict_relations(net, data.swapped())
    np.testing.assert_array_equal(ba.raw_ab, ab.raw_ba)
    np.testing.assert_array_equal(ba.decided, swap_decision(ab.decided))
    assert ab.joint() == ba.joint()
    # the direction reaches the predicates; a column the config does not name does not
    turned = evidence.copy()
    turned[:, -3:] = -turned[:, -3:]
    assert not np.allclose(predict_relations(net, RelationData(points, labels, np.ones(6),
                                                               turned)).raw_ab, ab.raw_ab)
    answers = evidence.copy()
    answers[:, EVIDENCE.index("geometric_coincident")] += 1
    np.testing.assert_array_equal(
        predict_relations(net, RelationData(points, labels, np.ones(6), answers)).raw_ab,
        ab.raw_ab)
    np.testing.assert_array_equal(swap_evidence(swap_evidence(evidence)), evidence)


def test_a_gained_evidence_column_reads_as_the_column_times_its_gain() -> None:
    """A network whose config scales a column reads that column times the gain, and the
    swapped pair's likewise; a gain on a column it does not read is refused."""
    from models.geometric import ANSWER_GAINS, EVIDENCE, evidence_gains, evidence_names

    names = tuple(evidence_names("truth"))
    assert evidence_gains("truth") == ANSWER_GAINS and evidence_gains("completed") == ()
    with pytest.raises(ValueError, match="evidence_gains"):
        tiny(pair_features=len(names) - 4, evidence=evidence_names("partial"),
             evidence_gains=(("geometric_coincident", 10.0),))
    with pytest.raises(ValueError, match="evidence_gains"):
        tiny(pair_features=len(names), evidence=names,
             evidence_gains=(("geometric_coincident", 0.0),))
    plain = random_net(5, pair_features=len(names), evidence=names)
    gained = random_net(5, pair_features=len(names), evidence=names,
                        evidence_gains=(("geometric_coincident", 10.0),))
    assert gained.cfg == RelationConfig.from_dict(dataclasses.asdict(gained.cfg))
    gen = np.random.default_rng(5)
    points = torch.from_numpy(gen.normal(size=(4, 2, 30, 3)).astype(np.float32))
    evidence = torch.from_numpy(gen.normal(size=(4, len(EVIDENCE))).astype(np.float32))
    scaled = evidence.clone()
    scaled[:, EVIDENCE.index("geometric_coincident")] *= 10
    with torch.no_grad():
        for got, want in zip(gained(points, torch.ones(4), evidence),
                             plain(points, torch.ones(4), scaled), strict=True):
            torch.testing.assert_close(got, want)
        assert not torch.allclose(gained(points, torch.ones(4), evidence)[0],
                                  plain(points, torch.ones(4), evidence)[0])


def test_violations_and_calibration_error() -> None:
    raw_ab, raw_ba = np.full((3, 10), 0.1), np.full((3, 10), 0.1)
    raw_ab[0, IDX[Relation.LEFT]] = raw_ba[0, IDX[Relation.RIGHT]] = 0.9  # consistent
    raw_ab[1, IDX[Relation.LEFT]] = 0.9  # converse missing: (b, a) is not right
    raw_ab[2, IDX[Relation.CONCENTRIC]] = 0.9  # symmetric relation in one order only
    raw_ab[2, PARALLEL] = raw_ab[2, PERPENDICULAR] = raw_ba[2, PARALLEL] = 0.8
    raw_ba[2, PERPENDICULAR] = 0.8
    v = violations(raw_ab, raw_ba)
    assert not v[0].any()
    assert v[1, IDX[Relation.LEFT]] and v[1].sum() == 1
    assert v[2, IDX[Relation.CONCENTRIC]] and v[2, PARALLEL] and v[2, PERPENDICULAR]
    assert not violations(np.full((1, 10), 0.1), np.full((1, 10), 0.1)).any()
    both = np.full((1, 10), 0.1)
    both[0, IDX[Relation.ABOVE]] = both[0, IDX[Relation.BELOW]] = 0.9  # above both ways
    assert violations(both, both)[0, IDX[Relation.ABOVE]]

    conf = np.repeat([0.55, 0.7, 0.9, 1.0], 20)
    correct = np.concatenate([np.arange(20) < k for k in (11, 14, 18, 20)])
    assert expected_calibration_error(conf, correct) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(0)
    c = rng.uniform(0.5, 1.0, 200_000)
    assert expected_calibration_error(c, rng.random(c.size) < c) < 0.01
    assert expected_calibration_error(c, np.zeros(c.size, bool)) == pytest.approx(c.mean(), 1e-9)


def test_the_joint_head_learns_the_joint_and_answers_a_pair_and_its_swap_alike(
        pairs: RelationData, kb_ltn: RelationResult, tmp_path: Path) -> None:
    from models.relations import JOINTS

    conc, coin = IDX[Relation.CONCENTRIC], IDX[Relation.COINCIDENT]
    named = np.where(pairs.labels[:, coin], "planar",
                     np.where(pairs.labels[:, conc], "cylindrical", "none"))
    assert {"planar", "cylindrical", "none"} <= set(named.tolist())
    joints = np.array([JOINTS.index(j) for j in named])
    data = RelationData(pairs.points, pairs.labels, pairs.mm, near=pairs.near, joints=joints)
    cfg = tiny(method="ltn", joints=True, **KB_NET)
    res = train_relations(cfg, data, data)
    assert res.history[-1]["val_joint_balanced"] > 0.9
    torch.manual_seed(0)
    assert evaluate(RelationNet(cfg), data)["joint_balanced"] < 0.7  # untrained
    pred = predict_relations(res.checkpoint, data)
    assert pred.joint_probability is not None
    np.testing.assert_allclose(pred.joint_probability.sum(1), 1.0, atol=1e-6)
    assert np.mean(np.array(pred.joint()) == named) > 0.9
    swapped = predict_relations(res.checkpoint, data.swapped())
    assert swapped.joint() == pred.joint()
    # its knowledge base, facts and rules tying each joint to the mates it implies, holds
    from models.relation_logic import joint_knowledge_base

    sat = joint_knowledge_base(torch.from_numpy(pred.joint_probability).float(),
                               torch.from_numpy(joints), torch.from_numpy(pred.raw_ab), cfg)
    assert sat.item() > 0.9
    # the head learns beside the relations without changing them: bit-identical predicates
    # to the same network trained without it (the knowledge-base test's)
    for name, weights in kb_ltn.model.state_dict().items():
        assert torch.equal(weights, res.model.state_dict()[name]), name
    path = save_relation_checkpoint(tmp_path / "joint.pt", res.checkpoint)
    again = predict_relations(path, data)
    assert again.joint_probability is not None
    np.testing.assert_array_equal(again.joint_probability, pred.joint_probability)
    # a network trained without a joint head has no joint of its own
    plain = train_relations(tiny(method="mlp"), pairs, pairs)
    assert predict_relations(plain.checkpoint, pairs).joint() is None


def test_a_completed_network_reads_the_observed_points_evidence_beside_its_own() -> None:
    """A network of ``completed`` reads the observed points' evidence after its own: it needs
    both (``with_observed``), the observed direction reads negated for the swapped pair, and
    the observed columns reach its answers."""
    from models.geometric import (
        ALL_EVIDENCE,
        EVIDENCE,
        OBSERVED_PREFIX,
        evidence_names,
        swap_evidence,
        with_observed,
    )

    names = tuple(evidence_names("completed"))
    assert names == (*evidence_names("partial"),
                     *(OBSERVED_PREFIX + n for n in evidence_names("partial")))
    net = random_net(6, pair_features=len(names), evidence=names)
    gen = np.random.default_rng(6)
    points = gen.normal(size=(5, 2, 30, 3)).astype(np.float32)
    own, observed = (gen.normal(size=(5, len(EVIDENCE))).astype(np.float32) for _ in range(2))
    with pytest.raises(ValueError, match="both"):
        with_observed(own, observed[:, :-1])
    with pytest.raises(ValueError, match=rf"\(B, >= {len(ALL_EVIDENCE)}\)"):
        net(torch.from_numpy(points), torch.ones(5), torch.from_numpy(own))
    both = with_observed(own, observed)
    labels = np.zeros((5, 10), bool)
    data = RelationData(points, labels, np.ones(5), both)
    ab, ba = predict_relations(net, data), predict_relations(net, data.swapped())
    np.testing.assert_array_equal(ba.raw_ab, ab.raw_ba)
    np.testing.assert_array_equal(swap_evidence(both)[:, len(EVIDENCE):], swap_evidence(observed))
    moved = with_observed(own, observed + 1)
    assert not np.allclose(predict_relations(net, RelationData(points, labels, np.ones(5),
                                                               moved)).raw_ab, ab.raw_ab)
    # a network of its own evidence alone reads the first columns, whatever follows them
    alone = random_net(6, pair_features=len(evidence_names("partial")),
                       evidence=tuple(evidence_names("partial")))
    np.testing.assert_array_equal(
        predict_relations(alone, RelationData(points, labels, np.ones(5), both)).raw_ab,
        predict_relations(alone, RelationData(points, labels, np.ones(5), moved)).raw_ab)


def test_deciding_a_completed_pair_hands_its_network_the_observed_points() -> None:
    """``decide`` gives a network that reads the observed evidence the observed points and
    both evidence vectors; the baseline and a network of its own evidence keep the
    completion's points; without the observed points that network has no answer."""
    from cadio.evidence.pair_features import pair_features_many
    from models.geometric import evidence_names, network_evidence, tests_for, with_observed
    from models.relate import PairBatch, decide
    from models.relation_decision import Decision

    names = tuple(evidence_names("completed"))
    net = random_net(7, pair_features=len(names), evidence=names)
    gen = np.random.default_rng(7)
    completed, seen = (gen.normal(size=(3, 2, 40, 3)).astype(np.float32) for _ in range(2))
    mm = np.ones(3)
    raw, raw_seen = pair_features_many(completed, mm), pair_features_many(seen, mm)
    own = network_evidence(raw, completed, None, tests_for("completed"))
    observed = network_evidence(raw_seen, seen, None, tests_for("partial"))
    both = PairBatch(completed, mm, None, raw, None, tests_for("completed"), (seen, observed))
    alone = PairBatch(completed, mm, None, raw, None, tests_for("completed"))
    got = decide(both, "ltn", (net, Decision.default()))
    want = predict_relations(net, RelationData(seen, np.zeros((3, 10), bool), mm,
                                               with_observed(own, observed)))
    assert got is not None
    np.testing.assert_array_equal(got[0], want.decided)
    np.testing.assert_allclose(got[1], want.confidence)
    assert decide(alone, "ltn", (net, Decision.default())) is None
    geometric, by_itself = decide(both, "geometric", None), decide(alone, "geometric", None)
    assert geometric is not None and by_itself is not None
    np.testing.assert_array_equal(geometric[0], by_itself[0])


def test_the_networks_of_a_batch_measure_its_nearest_distances_once(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Every network of a batch reads each point's distance to the other part: measured once
    per set of points (the batch's, or the observed ones a network reads instead), and each
    network's answer is the one it gives measuring them itself."""
    import models.relate as relate
    from cadio.evidence.pair_features import pair_features_many
    from models.geometric import evidence_names, network_evidence, tests_for, with_observed
    from models.relate import PairBatch, decide
    from models.relation_decision import Decision
    from models.relations_train import nearest_of_pairs

    names = tuple(evidence_names("completed"))
    nets = [random_net(seed, pair_features=len(names), evidence=names) for seed in (3, 4)]
    gen = np.random.default_rng(3)
    completed, seen = (gen.normal(size=(3, 2, 40, 3)).astype(np.float32) for _ in range(2))
    mm = np.array([1.0, 2.0, 0.5])
    raw, raw_seen = pair_features_many(completed, mm), pair_features_many(seen, mm)
    observed = network_evidence(raw_seen, seen, None, tests_for("partial"))
    batch = PairBatch(completed, mm, None, raw, None, tests_for("completed"), (seen, observed))
    measured: list[int] = []

    def counted(points, scale):  # type: ignore[no-untyped-def]
        measured.append(id(points))
        return nearest_of_pairs(points, scale)

    monkeypatch.setattr(relate, "nearest_of_pairs", counted)
    for net in nets:
        got = decide(batch, "ltn", (net, Decision.default()))
        want = predict_relations(net, RelationData(
            seen, np.zeros((3, 10), bool), mm,
            with_observed(network_evidence(raw, completed, None, tests_for("completed")),
                          observed)))
        assert got is not None
        np.testing.assert_array_equal(got[0], want.decided)
        np.testing.assert_allclose(got[1], want.confidence)
    assert len(measured) == 1
    np.testing.assert_array_equal(batch.nearest(completed), nearest_of_pairs(completed, mm))
    assert len(measured) == 2 and batch.nearest(completed) is batch.nearest(completed)
