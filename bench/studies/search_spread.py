"""How far the search route's figures move with its seed, beside a change of its knobs.

The search route (``cadio.inspect.routes.by_search``) registers each segment of the intact
capture without the design: RANSAC over feature matches and seeded draws of orientations and
points. Its figures (the registered relations' F1 against the CAD's mates, its pose errors)
turn on those draws, and on a machine's last floating-point bits. A change of the search must
be judged against that spread, not against one night. This runs the search route on the
intact captures a night already made (any ``mateqa nightly`` workspace that inspected its
assemblies) once per seed (``RegisterConfig.seed``) and per variant of its knobs (other
``RegisterConfig`` fields: by default ``stride`` 1 and 2, every stride-th pixel of a
hypothesis's visible surface), all views and the night's single view as the night does, and
relates the registered poses as the night does (``models.relate.relate_inspection`` with the
shipped relation networks). Each run's rows go
to ``inspect/study-spread/<variant>-<seed>/<assembly>/`` of the workspace (the night's own are
not touched); the script prints per run the search's time, its pose errors and ltn's F1 of
the ``registered`` input against the CAD's mates (every pair view, and those where both parts
show 20% of their surface), then per variant each figure's least, median and greatest over the
seeds.

Usage:
    .venv/bin/python bench/studies/search_spread.py --workspace WORKSPACE \\
        [--seeds 0 1 2] [--variants stride=1 stride=2,keep=2] [--jobs 2] [--method ltn]

Nothing is asserted: it prints the tables.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

STUDY = "study-spread"


def intact_captures(ws_root: Path) -> list[tuple[str, str]]:
    """(assembly, intact capture) of every assembly whose search route found segments in an
    inspection of the workspace."""
    out = set()
    for found in sorted((ws_root / "inspect").glob("*/found.parquet")):
        table = pd.read_parquet(found)
        if table.empty:  # an inspection without the search
            continue
        out |= {(str(a), str(c)) for a, c in
                table[["assembly", "capture"]].drop_duplicates().itertuples(index=False)}
    return sorted(out)


def knobs(variant: str) -> dict[str, int | float]:
    """``RegisterConfig`` fields of a variant: "stride=2,keep=2" (empty: the defaults)."""
    out: dict[str, int | float] = {}
    for item in filter(None, variant.split(",")):
        name, value = item.split("=")
        out[name.strip()] = float(value) if "." in value else int(value)
    return out


def run_one(ws_root: str, assembly: str, capture: str, seed: int, variant: str,
            relations: str) -> dict[str, object]:
    """The search route on one intact capture (all views, and the single view) at a seed and
    a variant of its knobs, its rows written as the night writes them, then its relations."""
    from cadio.inspect.defects import Variant
    from cadio.inspect.evaluate import TABLES, score_capture
    from cadio.inspect.routes import by_search
    from cadio.inspect.scan import scan_of
    from cadio.inspect.stage import ALL_VIEWS, InspectConfig, Inspected, assembly_model
    from cadio.recordings.mcap_io import read_capture
    from cadio.workspace import Workspace
    from models.relate import load_relation_models, relate_inspection

    ws = Workspace(Path(ws_root))
    base = InspectConfig()
    route = replace(base.route, register=replace(base.route.register, seed=seed,
                                                 **knobs(variant)))
    model = assembly_model(assembly, ws)
    path = ws.capture(capture)
    whole = scan_of(list(read_capture(path)))
    sets = [(ALL_VIEWS, whole)]
    if base.single_view is not None:
        sets.append((str(base.single_view), whole.of_views([base.single_view])))
    clock = time.perf_counter()
    inspected = [Inspected(capture, views, np.eye(4), {}, [], [], by_search(model, scan, route))
                 for views, scan in sets]
    seconds = time.perf_counter() - clock
    tables: dict[str, list[dict[str, object]]] = {t: [] for t in TABLES}
    score_capture(model, Variant(assembly, "intact"), path, inspected, ws, tables)
    folder = ws.root / "inspect" / STUDY / f"{variant or 'defaults'}-{seed}" / assembly
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("poses", "found", "shares"):
        pd.DataFrame(tables[name]).to_parquet(folder / f"{name}.parquet", index=False)
    rows = relate_inspection(folder, ws, load_relation_models(Path(relations)))
    rows.to_parquet(folder / "relations.parquet", index=False)
    return {"assembly": assembly, "seed": seed, "variant": variant, "search_s": seconds,
            "folder": str(folder)}


def figures(folders: list[Path], method: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The search's pose summary and ``method``'s F1 table over a run's assemblies."""
    from reports.asbuilt import pose_summary, registered_f1

    poses = pd.concat([pd.read_parquet(f / "poses.parquet") for f in folders])
    shares = pd.concat([pd.read_parquet(f / "shares.parquet") for f in folders])
    rel = pd.concat([pd.read_parquet(f / "relations.parquet") for f in folders])
    f1 = registered_f1(rel, shares)
    f1 = f1[(f1["method"] == method) & (f1["input"] == "registered")]
    return pose_summary(poses[poses["route"] == "search"]), f1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--variants", nargs="+", default=["stride=1", "stride=2"],
                        help="RegisterConfig fields per variant, e.g. stride=2,keep=2")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--method", default="ltn")
    parser.add_argument("--relations", type=Path,
                        default=Path(__file__).resolve().parents[2] / "models" / "checkpoints"
                        / "relations")
    args = parser.parse_args()
    root = args.workspace.resolve()
    captures = intact_captures(root)
    runs = [(variant, seed) for variant in args.variants for seed in args.seeds]
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = [pool.submit(run_one, str(root), a, c, seed, variant, str(args.relations))
                   for variant, seed in runs for a, c in captures]
        done = pd.DataFrame([f.result() for f in futures])
    rows = []
    for (variant, seed), group in done.groupby(["variant", "seed"], sort=False):
        poses, f1 = figures([Path(f) for f in group["folder"]], args.method)
        each = ", ".join(f"{a} {s:.0f}" for a, s in zip(group["assembly"], group["search_s"],
                                                          strict=True))
        print(f"\n## {variant or 'defaults'}, seed {seed}: search {group['search_s'].sum():.0f} s "
              f"({each})\n")
        print(poses.round(3).to_string(index=False), "\n")
        print(f1.pivot_table(index="relation", columns="visible", values="f1").round(3)
              .to_string(), "\n")
        rows += [{"variant": variant, "seed": seed, "figure": f"f1 {r.visible} {r.relation}",
                  "value": r.f1} for r in f1.itertuples()]
        rows += [{"variant": variant, "seed": seed, "figure": f"pose {r.views} {q}",
                  "value": getattr(r, q)} for r in poses.itertuples()
                 for q in ("median_mm", "p90_mm", "median_deg", "p90_deg")]
        rows.append({"variant": variant, "seed": seed, "figure": "search s",
                     "value": group["search_s"].sum()})
    table = pd.DataFrame(rows)
    table.to_csv(root / "inspect" / STUDY / "figures.csv", index=False)
    spread = table.groupby(["figure", "variant"], sort=False)["value"] \
        .agg(["min", "median", "max"]).unstack("variant")
    print("## Over the seeds: least, median, greatest\n")
    print(spread.round(3).to_string())


if __name__ == "__main__":
    main()
