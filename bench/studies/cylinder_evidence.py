"""How close the pair evidence's cylinder fits come to a concentric mate's exact coaxiality.

The truth calls a pair concentric when a cylinder or cone face of each part lies on one axis
(0.5 degree, 0.1 mm) within 1 mm of the other's. The evidence fits up to three cylinders to
each part's curved contact points and keeps the most coaxial pair (``cadio.evidence.fits``). For
every concentric pair view of a night's assembly captures, on the exact CAD samples (input
``truth``, 3,000 per part), this prints the angle and the offset between the pair's two fitted
axes, with each cylinder refitted to its points by least squares (the evidence) and with the
axis its points' normals give (``refine_cylinders=False``, the evidence before the refit), and
the share of the views whose pair lies within the truth's own tolerances.
Any workspace whose night captured assemblies with their mates will do (a held-out night's).

Usage:
    .venv/bin/python bench/studies/cylinder_evidence.py --workspace heldout/ws

Nothing is asserted: it prints the quartiles and the seconds each variant took.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from cadio.catalog import read_catalog
from cadio.evidence.fits import DEFAULT_FEATURES
from cadio.evidence.pair_features import PAIR_FEATURES, pair_features, part_cloud
from cadio.evidence.pairs import DEFAULT_PAIRS, capture_pairs
from cadio.workspace import Workspace
from models.relate import RELATIONS
from models.relation_inputs.partial import observed_clouds
from models.relation_inputs.truth import truth_clouds

CONCENTRIC = RELATIONS.index("concentric")
ANGLE, OFFSET = PAIR_FEATURES.index("cyl_angle_deg"), PAIR_FEATURES.index("cyl_offset_mm")

STOCK = {"truth": truth_clouds, "partial": observed_clouds}  # the inputs read here


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, default=Path("heldout/ws"))
    args = parser.parse_args()
    ws = Workspace(args.workspace.resolve())
    catalog = read_catalog(ws.catalog)
    categories = dict(zip(catalog["part_id"].astype(str), catalog["category"].astype(str),
                          strict=True))
    clouds = []
    for path in sorted((ws.root / "captures").glob("assembly-*.mcap")):
        for view in capture_pairs(path, ws, categories, DEFAULT_PAIRS, STOCK):
            if "truth" in view.points and view.labels[CONCENTRIC]:
                a, b = view.evidence_clouds("truth")
                mm = 1.0 / view.scale_m_per_mm
                clouds.append((part_cloud(np.asarray(a, np.float64) * mm),
                               part_cloud(np.asarray(b, np.float64) * mm)))
    print(f"{len(clouds)} concentric pair views of {args.workspace}, CAD samples")
    for name, cfg in (("refitted to the points", DEFAULT_FEATURES),
                      ("axis of the normals", replace(DEFAULT_FEATURES, refine_cylinders=False))):
        clock = time.perf_counter()
        f = np.array([pair_features(a, b, cfg) for a, b in clouds])
        angle = np.percentile(f[:, ANGLE], [25, 50, 75]).round(2).tolist()
        offset = np.percentile(f[:, OFFSET], [25, 50, 75]).round(2).tolist()
        within = np.mean((f[:, ANGLE] <= 0.5) & (f[:, OFFSET] <= 0.1))
        print(f"{name}: axes apart (deg, quartiles) {angle}, offset (mm) {offset}, "
              f"{within:.3f} within the truth's 0.5 deg and 0.1 mm, "
              f"{time.perf_counter() - clock:.1f} s")


if __name__ == "__main__":
    main()
