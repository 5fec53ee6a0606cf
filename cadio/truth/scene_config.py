"""The scene generator's knobs (``SceneConfig``) and a night's scenes.

Its own module so that the generator (``cadio.truth.scenes``) and the poses it draws
(``cadio.truth.scene_poses``) both read it without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from cadio.tolerances import DEFAULT_TOLERANCES, Tolerances
from cadio.truth.relations import CAD_VIEW_AXIS, DEFAULT_MARGINS, BoundaryMargins


@dataclass(frozen=True)
class SceneConfig:
    """Knobs of the scene generator. Lengths mm, angles degrees."""

    seed: int = 0
    pairs_per_relation: int = 100  # over all splits, shared in proportion to the split fractions
    near_boundary_fraction: float = 0.1  # of each relation's pairs; half inside, half outside
    gap_mm: tuple[float, float] = (5.0, 50.0)  # clearance between the parts' bounding boxes
    val_fraction: float = 0.1
    test_fraction: float = 0.2
    view_axis: tuple[float, float, float] = CAD_VIEW_AXIS
    # "Large flat surfaces" (paper): the dominant plane direction carries this share of the area.
    min_plane_area_fraction: float = 0.1
    near_directional_deg: float = 1.0  # 14 vs 16 degrees for the 15 degree cone
    near_plane_deg: float = 0.1  # 0.9 vs 1.1 degrees for parallel, 89.1 vs 88.9 perpendicular
    near_inside_factor: float = 0.5  # lifts and axis shifts of 0.05 mm (tolerances 0.1 mm)
    near_outside_factor: float = 2.0  # ... against 0.2 mm
    # Concentric pairs: ends stacked with radii this share of ``concentric_gap_mm`` apart at
    # most, shafts this share thinner than their bore at most, and stacked faces this share of
    # it apart at most: clear of the near-boundary margin (0.8 to 1.2 mm).
    stack_fraction: float = 0.5
    nest_fraction: float = 0.7
    gap_fraction: float = 0.7
    # Pairs placed touching at random orientations (``placement.touch``), over all splits like
    # ``pairs_per_relation``: contact that is seldom a face mate, as most touching pairs of an
    # assembly are (a pin against a race, a ball in a groove). Every other pair of this
    # generator is apart unless it is a mate; without these, touching reads as a mate.
    contact_pairs: int = 0
    # Coaxial pairs apart (``clearance_pairs``, over all splits like ``contact_pairs``): a
    # shaft in a bore or two ends on one axis with their faces this many times
    # ``concentric_gap_mm`` apart, clear of the near-boundary margin (1.2 mm): a nut standing
    # off a flange's hole, a cage segment inside a bearing's ring. Every other coaxial pair of
    # this generator is a concentric mate; without these, coaxial reads as concentric.
    clearance_pairs: int = 0
    clearance_factors: tuple[float, float] = (1.5, 4.0)
    tolerances: Tolerances = field(default=DEFAULT_TOLERANCES)
    margins: BoundaryMargins = field(default=DEFAULT_MARGINS)

    def split_fractions(self) -> dict[str, float]:
        return {"train": 1.0 - self.val_fraction - self.test_fraction,
                "val": self.val_fraction, "test": self.test_fraction}


def night_scene_config(seed: int, pairs_per_relation: int,
                       tolerances: Tolerances = DEFAULT_TOLERANCES) -> SceneConfig:
    """The scenes of a night: every part in one pool ("test"), so any two parts of the library
    may pair. A night scores what the checkpoints never trained on (``models.evaluate``), not a
    split of its own; drawing pairs within 70/10/20 splits left a small library without scenes."""
    return SceneConfig(seed=seed, pairs_per_relation=pairs_per_relation, val_fraction=0.0,
                       test_fraction=1.0, tolerances=tolerances)
