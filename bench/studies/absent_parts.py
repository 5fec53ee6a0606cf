"""How much of a part's designed place the depth agrees with, left in place, moved, or missing.

The design route calls a part missing where the camera sees through its designed place (the
depth agrees with less than ``RouteConfig.absent_below`` of what the cameras would see of it
there) and its refinement found it nowhere the depth agrees with; of a part the design shows
fewer than ``missing_min_points`` of, only where the depth agrees with less than
``absent_sure`` of its place (``cadio.inspect.routes``). This reads every capture of a night's
inspection (each assembly's intact capture and planted variants, captured again where the
workspace lacks them), with all its views and with the single view, runs the design route, and
prints per planted kind the share of each part's place the depth agrees with (parts the design
shows at least ``min_visible`` points of) and how the route called the parts: the constants
should part the missing from the rest.

Usage:
    .venv/bin/python bench/studies/absent_parts.py --workspace WORKSPACE

Nothing is asserted: it prints the tables.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from near_views import assemblies  # the study beside this one: the night's assemblies

from cadio.inspect.routes import by_design, expected_points
from cadio.inspect.scan import consistency, scan_of
from cadio.inspect.stage import (
    InspectConfig,
    assembly_model,
    capture_name,
    capture_variant,
    variants_of,
)
from cadio.inspect.surface import occluders, visible
from cadio.recordings.mcap_io import read_capture
from cadio.workspace import Workspace


def agreements(ws: Workspace, assembly: str, cfg: InspectConfig) -> list[dict[str, object]]:
    """Per variant, set of views and part: what was planted on it, the points the design shows
    of it, the depth's agreement with its designed place, and the route's problem."""
    model = assembly_model(assembly, ws)
    rows: list[dict[str, object]] = []
    for variant in variants_of(model, pd.read_parquet(ws.mates(assembly)), cfg):
        path = ws.capture(capture_name(variant))
        if not path.is_file():
            path = capture_variant(model, variant, ws, cfg)
        whole = scan_of(list(read_capture(path)))
        planted = {d.index: d.kind for d in variant.defects}
        sets = [("all", whole.of_views(list(range(cfg.views))))]
        if cfg.single_view is not None:
            sets.append((str(cfg.single_view), whole.of_views([cfg.single_view])))
        for views, scan in sets:
            nominal, parts, _ = by_design(model, scan, cfg.route, np.eye(4))
            shown = expected_points(model, nominal, scan, cfg.route)
            others = occluders([(i, p.mesh, nominal @ d) for i, (p, d) in
                                enumerate(zip(model.parts, model.design, strict=True))])
            for i, part in enumerate(model.parts):
                seen, _ = visible(part, nominal @ model.design[i], scan.cameras,
                                  cfg.route.register.stride, (others, i))
                rows.append({"assembly": assembly, "variant": variant.name, "views": views,
                             "index": i, "planted": planted.get(i, "none"),
                             "shown": shown[i], "agreement": consistency(seen, scan),
                             "problem": parts[i].problem or "placed"})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True)
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    cfg = InspectConfig()
    table = pd.DataFrame([r for a in assemblies(ws) for r in agreements(ws, a, cfg)])
    seen = table[table["shown"] >= cfg.route.min_visible]
    print("\n## agreement of the depth with each part's designed place\n")
    print(seen.groupby(["planted", "views"])["agreement"]
          .describe(percentiles=[0.05]).round(3).to_string(), "\n")
    print("## the route's calls\n")
    print(table.groupby(["planted", "views", "problem"]).size().unstack(fill_value=0)
          .to_string())


if __name__ == "__main__":
    main()
