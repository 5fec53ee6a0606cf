"""Relation network: the paper's Logic Tensor Network over the ten relations of a part pair.

Each part's point cloud is grounded by a shared five-layer per-point MLP with max pooling
(PointNet's shape, so point order does not matter). Beside its coordinates each point carries
how near the other part is (in the parts' millimetres: the CAD mates are decided at 0.1 and
1 mm), so the grounding sees where and how the parts touch. The pair vector [e_a, e_b,
e_a - e_b, f] feeds one Neural Tensor Network predicate per relation, where f encodes the
pair's evidence from fitted planes and axes (``cadio.evidence.pair_features``: contact plane,
contact axis, part axes, dominant plane directions; symmetric in the two parts). Training
(``models.relations_train``) maximises the satisfaction of a knowledge base written in
product real logic (``models.relation_logic``): the labelled facts and, for the ``ltn``
method, the paper's rules (converse, asymmetry, symmetry, exclusion). The ``mlp`` method is
the same network trained on the facts alone.

The CAD's joint of a pair (revolute, cylindrical, planar, slider or none) is not a function of
its concentric and coincident answers: a concentric face mate may be a clearance that holds
nothing (a planar joint), two coincident faces may stop a rotation (a slider). A joint head
(``JOINTS``) reads it from the same pair vector, as a softmax averaged over both orders; its
facts are the CAD's joints, and for ``ltn`` its rules are what each joint says of the face
mates (``JOINT_IMPLIES``: a revolute joint is concentric and coincident, a planar one
coincident, a pair without a joint not coincident).

Inference decides a pair and its swap together (``models.relation_decision``: ``combine``
then ``decide``), so the answers obey the rules for any network output; ``violations`` says
where the raw outputs do not.

Points are (B, 2, P, 3) in the observer's frame (x right, y behind = the camera's forward
direction on the ground, z up), any length unit, with the millimetres per unit of each pair
(B,): each pair is centred on the mean of its two clouds' centroids and divided by its RMS
radius, which keeps the parts' relative position. No I/O here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from itertools import pairwise

import torch
from torch import Tensor, nn

from cadio.records import CONVERSE, DIRECTIONAL, SYMMETRIC, Relation

RELATIONS = tuple(Relation)
_INDEX = {r: i for i, r in enumerate(RELATIONS)}
# Column permutation taking the relations of (a, b) to those of (b, a): converse for the
# directional ones, identity for the symmetric ones.
CONVERSE_INDEX = tuple(_INDEX[CONVERSE.get(r, r)] for r in RELATIONS)
DIRECTIONAL_INDEX = tuple(_INDEX[r] for r in DIRECTIONAL)
SYMMETRIC_INDEX = tuple(_INDEX[r] for r in SYMMETRIC)
PARALLEL, PERPENDICULAR = _INDEX[Relation.PARALLEL], _INDEX[Relation.PERPENDICULAR]
OPPOSITES = ((0, 1), (2, 3), (4, 5))  # left/right, above/below, front/behind: never both
EXCLUSIVE = (*OPPOSITES, (PARALLEL, PERPENDICULAR))  # pairs of one pair's relations, at most one
N_DESCRIPTORS = 24  # per part: centroid 3, principal directions' d d^T 3 x 6, extents 3
N_CONTACT = 2  # per point: nearness of the other part at 1 mm and at 10 mm
# The joint head's classes: the CAD's kinematic joints of the training corpus's pairs
# (``cadio.truth.joints``; fastened and "other" never occur there), "none" without one.
JOINTS = ("none", "planar", "revolute", "cylindrical", "slider")
CONCENTRIC, COINCIDENT = _INDEX[Relation.CONCENTRIC], _INDEX[Relation.COINCIDENT]
# What each joint says of the pair's face mates (held by every labelled pair of the corpus): a
# shaft in a bore is a concentric mate, a planar contact a coincident one; a pair without a
# joint has no coincident mate (its concentric faces, if any, are a clearance).
JOINT_IMPLIES = {"revolute": ((CONCENTRIC, True), (COINCIDENT, True)),
                 "cylindrical": ((CONCENTRIC, True), (COINCIDENT, False)),
                 "planar": ((COINCIDENT, True),), "slider": ((COINCIDENT, True),),
                 "none": ((COINCIDENT, False),)}



@dataclass(frozen=True)
class RelationConfig:
    """The network, its logic and its training; ``method`` names the variant."""

    # a network of ``models.relation_methods``: "ltn" (facts and rules), "mlp" (facts only)
    method: str = "ltn"
    n_points: int = 600  # points per part the data layer delivers (inference takes any count)
    # Points per part per training step (a random subset, its nearness to the other part
    # measured against that part's every point beforehand): the per-point MLP over 2 x 600
    # points x 64 pairs cost 2.7 s a CPU step.
    train_points: int = 256
    contact: bool = True  # each point also carries the other part's nearness (N_CONTACT)
    pair_features: int = 0  # width of the pair evidence vector (0: none)
    # The columns of ``models.geometric.ALL_EVIDENCE`` read, by name, ``pair_features`` of
    # them (those of the observed points only where it names them: ``reads_observed``);
    # empty: the first ``pair_features`` columns (checkpoints from before the names).
    evidence: tuple[str, ...] = ()
    # Evidence columns scaled before the network reads them, as (name, gain) pairs; the rest
    # read at gain 1. A 0/1 test answer among features of the same scale is one vote of
    # many: the ``truth`` ltn outvoted the exact coincident test on a stacked pair whose
    # faces lie 0.42 mm apart (dominant planes perpendicular, a combination training holds
    # three times), where the test agrees with the labels on 99.6% of training's clear pairs.
    evidence_gains: tuple[tuple[str, float], ...] = ()
    feature_width: int = 16  # its encoding in the pair vector
    # Hidden widths of the per-point MLP; the pair evidence carries the mates, the points the
    # directions and shapes, and a quarter of (32, 64, 64, 128)'s cost held the same accuracy.
    widths: tuple[int, ...] = (16, 32, 32, 64)
    # Part embedding: the MLP's fifth layer, max- and mean-pooled (2 x 32). Each predicate's
    # bilinear tensor grows with its square: 64 made 24 MB float32 checkpoints for 0.7 points
    # of held-out mean accuracy on truth inputs (89.0% against 88.3%, 1,500 steps).
    embed: int = 32
    pair_diff: bool = True  # pair vector [e_a, e_b, e_a - e_b] (False: [e_a, e_b])
    ntn_k: int = 4  # slices of each predicate's bilinear tensor
    descriptors: bool = False  # append centroid, PCA directions and extents to each embedding
    # Pool by max and mean: the mean counts how many points share a feature (the principal
    # plane is the direction carrying the most planar area), which max cannot.
    mean_pool: bool = True
    p_forall: float = 2.0  # p of the p-mean-error Forall (LTN's default)
    p_sat: float = 2.0  # p of the aggregation of the axioms into the KB's satisfaction
    # Weight of each rule axiom relative to one fact axiom. At 1.0 the rules cost accuracy (held
    # out on CAD surface points: mean 88.3% against the facts-only mlp's 89.6%); at 0.25 ltn
    # beats mlp (89.9%) and still breaks fewer axioms (5.2% of raw answers against 7.2%).
    rule_weight: float = 0.25
    lr: float = 1e-3  # Adam
    steps: int = 1000
    batch_size: int = 64
    eval_every: int = 100  # steps between validations (the best one is kept)
    # Gaussian noise on training points, millimetres: under the 0.1 mm of the mates' tolerances,
    # which noise of a pair's size (0.3-0.5 mm) washed out.
    jitter_mm: float = 0.02
    # Present each training pair as (b, a) with probability 1/2 (labels by the rules), so both
    # methods see both orders in their facts and differ by the rules alone.
    swap_augment: bool = True
    # A joint head beside the predicates: the pair's kinematic joint (``JOINTS``), a softmax
    # over the pair vector of both orders; trained on its facts (and, for ``ltn``, on
    # ``JOINT_IMPLIES`` as rules). Off in checkpoints trained before it existed.
    joints: bool = False
    joint_weight: float = 1.0  # weight of the joint's knowledge base in the loss
    # The joint head reads the pair vector without training it, and its rules read the
    # relations without training them: so the relations learn exactly what they learn without
    # a head (bit-identical weights). Sharing them cost ltn on completed inputs 0.04 of
    # validation mean F1 (0.773 to 0.731) and 0.02-0.05 of held-out mean F1 against the CAD
    # mates (two seeds).
    joint_detach: bool = True
    seed: int = 0  # torch, numpy and python seeds; also keys batches and augmentation

    def __post_init__(self) -> None:
        object.__setattr__(self, "widths", tuple(int(w) for w in self.widths))
        object.__setattr__(self, "evidence", tuple(str(n) for n in self.evidence))
        object.__setattr__(self, "evidence_gains",
                           tuple((str(n), float(g)) for n, g in self.evidence_gains))
        ungained = sorted({n for n, _ in self.evidence_gains} - set(self.evidence))
        if ungained or not all(math.isfinite(g) and g > 0 for _, g in self.evidence_gains):
            raise ValueError(f"evidence_gains must scale columns of evidence by positive "
                             f"gains; not read: {ungained}")
        if self.evidence:
            from models.geometric import ALL_EVIDENCE

            unknown = sorted(set(self.evidence) - set(ALL_EVIDENCE))
            if unknown or len(self.evidence) != self.pair_features:
                raise ValueError(f"evidence must name pair_features ({self.pair_features}) "
                                 f"columns of ALL_EVIDENCE; unknown {unknown}")
        from models.relation_methods import learned

        if self.method not in learned():
            raise ValueError(f"method must be one of {learned()}, got {self.method!r}")
        if min(self.widths, default=0) < 1 or min(self.embed, self.ntn_k, self.n_points) < 1:
            raise ValueError("widths, embed, ntn_k and n_points must be positive")
        if self.pair_features < 0 or self.feature_width < 1 or self.jitter_mm < 0:
            raise ValueError("pair_features >= 0, feature_width >= 1, jitter_mm >= 0 required")
        if min(self.train_points, self.steps, self.batch_size, self.eval_every) < 1:
            raise ValueError("train_points, steps, batch_size and eval_every must be >= 1")
        if min(self.p_forall, self.p_sat) < 1 or min(self.lr, self.rule_weight,
                                                     self.joint_weight) <= 0:
            raise ValueError("p must be >= 1; lr, rule_weight and joint_weight must be "
                             "positive")

    @classmethod
    def from_dict(cls, config: dict[str, object]) -> RelationConfig:
        """The config from its plain dict (a checkpoint's ``config``).

        Raises:
            ValueError: unknown fields or bad values.
        """
        unknown = set(config) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown relation config fields {sorted(unknown)}")
        return cls(**config)  # type: ignore[arg-type]


def normalise_pair(points: Tensor) -> Tensor:
    """Centre each pair on the mean of its two centroids, divide by the pair's RMS radius.

    Computed in float64 (finite float32 coordinates of any size stay finite) with operations
    symmetric in the two parts, so the swapped pair normalises to exactly the swapped result.

    Args:
        points: (B, 2, P, 3) any float dtype, any length unit.

    Returns:
        (B, 2, P, 3) float32, unit-free.
    """
    x = points.double()
    a, b = x[:, 0], x[:, 1]  # (B, P, 3) each
    centre = (a.mean(1) + b.mean(1)) / 2  # (B, 3)
    ms_a = (a - centre[:, None]).square().sum(-1).mean(1)  # (B,)
    ms_b = (b - centre[:, None]).square().sum(-1).mean(1)
    radius = ((ms_a + ms_b) / 2).sqrt().clamp_min(1e-300)  # (B,)
    return ((x - centre[:, None, None]) / radius[:, None, None, None]).float()


@torch.no_grad()
def part_descriptors(points: Tensor) -> Tensor:
    """Centroid, principal directions (sign-free) and extents of normalised parts.

    Args:
        points: (B, P, 3) one part of each normalised pair.

    Returns:
        (B, 24) float32: centroid (3), the six distinct entries of d d^T for each of the three
        principal directions by falling variance (18: a direction's sign is arbitrary, and a
        canonical sign flips discontinuously), extents along them, max - min (3).
    """
    x = points.double()
    centroid = x.mean(1)  # (B, 3)
    centred = x - centroid[:, None]  # (B, P, 3)
    cov = centred.transpose(1, 2) @ centred / x.shape[1]  # (B, 3, 3)
    _, vecs = torch.linalg.eigh(cov)  # ascending eigenvalues; directions are columns
    dirs = vecs.flip(-1).transpose(1, 2)  # (B, 3, 3) rows, by falling variance
    i, j = torch.triu_indices(3, 3)
    outer = (dirs[..., :, None] * dirs[..., None, :])[..., i, j]  # (B, 3, 6)
    proj = centred @ dirs.transpose(1, 2)  # (B, P, 3)
    extents = proj.amax(1) - proj.amin(1)  # (B, 3)
    return torch.cat([centroid, outer.flatten(1), extents], 1).float()


def nearest_mm(points: Tensor, mm: Tensor) -> Tensor:
    """(B, 2, P) for each point, the distance to the other part's nearest point, millimetres
    (computed in float64: a tenth of a millimetre in a metre-sized scene needs it). The data
    layer hands these in precomputed; this is the fallback."""
    a, b = points[:, 0].double(), points[:, 1].double()
    d = torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist") * mm.double()[:, None, None]
    return torch.stack([d.amin(2), d.amin(1)], 1).float()


def contact_channels(near_mm: Tensor) -> Tensor:
    """Per point, how near the other part of its pair is: exp(-d / 1 mm) and exp(-d / 10 mm).

    Args:
        near_mm: (B, 2, P) distances to the other part's nearest point, millimetres.

    Returns:
        (B, 2, P, 2) float32.
    """
    d = near_mm.float()
    return torch.stack([torch.exp(-d / 1.0), torch.exp(-d / 10.0)], -1)


class PointEncoder(nn.Module):
    """Shared per-point MLP (len(widths) + 1 linear layers), max (and mean) pool, tanh: a
    part's embedding."""

    def __init__(self, widths: tuple[int, ...], embed: int, in_dim: int = 3,
                 mean_pool: bool = False) -> None:
        super().__init__()
        dims = [in_dim, *widths, embed]
        layers: list[nn.Module] = []
        for a, b in pairwise(dims):
            layers += [nn.Linear(a, b), nn.ReLU()]
        self.mlp = nn.Sequential(*layers[:-1])  # no ReLU before the pooling
        self.mean_pool = mean_pool

    def forward(self, points: Tensor) -> Tensor:
        """points (B, P, F) -> (B, E) (or (B, 2E) with mean pooling) in (-1, 1)."""
        # Bounded embeddings keep each predicate's quadratic form x^T W x in tanh's working
        # range; unbounded max-pooled features grew until training stalled or diverged.
        h = self.mlp(points)  # (B, P, E)
        pooled = torch.cat([h.amax(1), h.mean(1)], 1) if self.mean_pool else h.amax(1)
        return torch.tanh(pooled)


class NTNPredicate(nn.Module):
    """One relation: sigmoid(u^T tanh(x^T W[1:k] x + V x + b)); ``forward`` gives the logit."""

    def __init__(self, dim: int, k: int) -> None:
        super().__init__()
        self.W = nn.Parameter(torch.randn(k, dim, dim) / dim)  # x^T W x ~ O(1) at init
        self.V = nn.Linear(dim, k)  # V x + b
        self.u = nn.Linear(k, 1, bias=False)
        # The logit is bounded by |u|_1: torch's default init (|u_i| < 1/sqrt(k)) caps the first
        # truth values near [0.2, 0.8] and Adam then needs ~1000 steps to grow u; N(0, 1) lets a
        # predicate approach 0 or 1 within a few hundred steps without saturating at the start.
        nn.init.normal_(self.u.weight, 0.0, 1.0)

    def forward(self, x: Tensor) -> Tensor:
        """x (B, D) pair vectors -> (B,) logits."""
        xw = torch.einsum("bi,kij->bkj", x, self.W)  # (B, k, D)
        bilinear = (xw * x[:, None]).sum(-1)  # (B, k)
        return self.u(torch.tanh(bilinear + self.V(x)))[:, 0]  # (B,)


class RelationNet(nn.Module):
    """Points of a pair -> logits of the ten relations for (a, b) and for (b, a)."""

    def __init__(self, cfg: RelationConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = PointEncoder(cfg.widths, cfg.embed, 3 + (N_CONTACT if cfg.contact else 0),
                                    mean_pool=cfg.mean_pool)
        part = cfg.embed * (2 if cfg.mean_pool else 1) + (N_DESCRIPTORS if cfg.descriptors
                                                          else 0)
        dim = part * (3 if cfg.pair_diff else 2)
        self.features: nn.Module | None = None
        if cfg.pair_features:
            self.features = nn.Sequential(nn.Linear(cfg.pair_features, 32), nn.ReLU(),
                                          nn.Linear(32, cfg.feature_width), nn.Tanh())
            dim += cfg.feature_width
        self.predicates = nn.ModuleList(NTNPredicate(dim, cfg.ntn_k) for _ in RELATIONS)
        self.joint_head: nn.Module | None = None
        if cfg.joints:
            self.joint_head = nn.Sequential(nn.Linear(dim, 32), nn.ReLU(),
                                            nn.Linear(32, len(JOINTS)))

    def embed(self, points: Tensor, mm: Tensor | None = None,
              near: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """points (B, 2, P, 3), mm (B,) millimetres per unit -> part embeddings e_a, e_b,
        (B, E') each. ``near``: (B, 2, P) each point's distance to the other part in mm
        (``nearest_mm``, computed when None).

        The parts go through the encoder in two calls of the same shape, so the swapped pair
        gets bit-identical embeddings (and outputs) whatever the kernels' row blocking.

        Raises:
            ValueError: not (B, 2, P, 3) with B, P >= 1, or non-finite coordinates.
        """
        if points.dim() != 4 or points.shape[1] != 2 or points.shape[3] != 3 or 0 in points.shape:
            raise ValueError(f"points must have shape (B, 2, P, 3); got {tuple(points.shape)}")
        if not bool(torch.isfinite(points).all()):
            raise ValueError("points must be finite")
        device = next(self.parameters()).device
        points = points.to(device)
        x = normalise_pair(points)  # (B, 2, P, 3)
        if self.cfg.contact:
            scale = torch.ones(len(points), device=device) if mm is None else mm.to(device)
            dist = nearest_mm(points, scale) if near is None else near.to(device)
            x = torch.cat([x, contact_channels(dist)], -1)  # (B, 2, P, 3 + 2)
        parts = []
        for j in (0, 1):
            e = self.encoder(x[:, j])  # (B, E)
            if self.cfg.descriptors:
                e = torch.cat([e, part_descriptors(x[:, j, :, :3])], 1)  # (B, E + 24)
            parts.append(e)
        return parts[0], parts[1]

    def pair_vector(self, e_a: Tensor, e_b: Tensor, f: Tensor | None = None) -> Tensor:
        """Part embeddings (B, E') each and the encoded pair evidence (B, W) -> the vector of
        the ordered pair (a, b): (B, D)."""
        terms = [e_a, e_b, e_a - e_b] if self.cfg.pair_diff else [e_a, e_b]
        if f is not None:
            terms.append(f)
        return torch.cat(terms, 1)

    def head(self, e_a: Tensor, e_b: Tensor, f: Tensor | None = None) -> Tensor:
        """Part embeddings (B, E') each and the encoded pair evidence (B, W) -> logits of the
        ordered pair (a, b): (B, 10)."""
        x = self.pair_vector(e_a, e_b, f)  # (B, D)
        return torch.stack([pred(x) for pred in self.predicates], 1)  # (B, 10)

    def forward(self, points: Tensor, mm: Tensor | None = None,
                features: Tensor | None = None,
                near: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """points (B, 2, P, 3), mm (B,), features (B, F), near (B, 2, P) or None -> logits
        for (a, b) and for (b, a), (B, 10) each.

        Raises:
            ValueError: points as ``embed`` refuses them, or pair features missing or of
                another width than the config's.
        """
        ab, ba, _ = self.forward_all(points, mm, features, near)
        return ab, ba

    def forward_all(self, points: Tensor, mm: Tensor | None = None,
                    features: Tensor | None = None, near: Tensor | None = None
                    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """``forward``'s two logits and the joint head's log-probabilities (B, ``JOINTS``),
        the same for the pair and its swap (the mean of both orders' softmax); None without
        a joint head."""
        e_a, e_b = self.embed(points, mm, near)
        f_ab = f_ba = None
        if self.features is not None:
            ab, ba = self._evidence(features, len(points))
            f_ab = self.features(ab.to(e_a.device).float())
            f_ba = self.features(ba.to(e_a.device).float())
        joints = None
        if self.joint_head is not None:
            x_ab, x_ba = self.pair_vector(e_a, e_b, f_ab), self.pair_vector(e_b, e_a, f_ba)
            if self.cfg.joint_detach:
                x_ab, x_ba = x_ab.detach(), x_ba.detach()
            probs = (torch.softmax(self.joint_head(x_ab), 1)
                     + torch.softmax(self.joint_head(x_ba), 1)) / 2
            joints = torch.log(probs.clamp_min(1e-12))
        return self.head(e_a, e_b, f_ab), self.head(e_b, e_a, f_ba), joints

    def _evidence(self, features: Tensor | None, n: int) -> tuple[Tensor, Tensor]:
        """The evidence columns the network reads for (a, b) and for (b, a), (B, W) each: the
        columns its config names of ``models.geometric.network_evidence`` (and, where it names
        the observed points', of ``with_observed``), the swapped pair's with the ordered columns
        negated (as ``models.geometric.swap_evidence``), each times its ``evidence_gains``
        gain; or, named none, the first W columns (symmetric).

        Raises:
            ValueError: features missing, of another row count, or too narrow.
        """
        from models.geometric import ALL_EVIDENCE, EVIDENCE, ORDERED_COLUMNS, reads_observed

        width = ((len(ALL_EVIDENCE) if reads_observed(self.cfg.evidence) else len(EVIDENCE))
                 if self.cfg.evidence else self.cfg.pair_features)
        if features is None or features.ndim != 2 or len(features) != n \
                or features.shape[1] < width:
            got = None if features is None else tuple(features.shape)
            raise ValueError(f"pair features must have shape (B, >= {width}); got {got}")
        if not self.cfg.evidence:
            return features[:, :width], features[:, :width]
        cols = [ALL_EVIDENCE.index(name) for name in self.cfg.evidence]
        ordered = [c for c in ORDERED_COLUMNS if c < width]
        own = features[:, :width]
        swapped = own.clone()
        swapped[:, ordered] = -own[:, ordered]
        if not self.cfg.evidence_gains:
            return own[:, cols], swapped[:, cols]
        gains = dict(self.cfg.evidence_gains)
        scale = own.new_tensor([gains.get(name, 1.0) for name in self.cfg.evidence])
        return own[:, cols] * scale, swapped[:, cols] * scale
