"""What a second, nearer ring of inspection views buys and costs (``InspectConfig.near_m``).

A D435's noise grows with the square of the distance: 1.4 mm rms at 0.6 m, 0.34 mm at 0.3 m.
This inspects every assembly of a night's workspace (its catalog and mates written: any
``mateqa nightly`` workspace) twice with the night's inspection otherwise at its defaults, the
design route only: without near views, and with as many again at ``--near-m``. Each run works
in a scratch workspace of its own under ``inspect/study-near/`` of the workspace (the
catalog, meshes and mates copied there: the captures it renders carry the night's names, and
the night's own are not touched). It prints per run the stage's time, the pose errors of the
intact captures (the design route, all views and one), the planted defects caught per kind and
size (the product's method) and the false alarms on the intact parts.

Usage:
    .venv/bin/python bench/studies/near_views.py --workspace WORKSPACE [--near-m 0.3]

Nothing is asserted: it prints the tables.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import pandas as pd

from cadio.catalog import read_catalog
from cadio.inspect.evaluate import REGISTERED, inspect_assembly, read_tables
from cadio.inspect.stage import InspectConfig
from cadio.workspace import Workspace


def assemblies(ws: Workspace) -> list[str]:
    """The workspace's assemblies whose mates the night wrote."""
    catalog = read_catalog(ws.catalog)
    names = sorted({Path(str(s)).stem for s in catalog[catalog["n_solids"] > 1]["source"]})
    return [n for n in names if ws.mates(n).is_file()]


def scratch(ws: Workspace, name: str) -> Workspace:
    """A workspace under ``inspect/study-near/<name>`` holding the night's catalog, meshes
    and mates (the study's captures and rows go there)."""
    root = ws.root / "inspect" / "study-near" / name
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    shutil.copy2(ws.catalog, root / ws.catalog.name)
    for folder in ("meshes", "mates"):
        shutil.copytree(ws.root / folder, root / folder)
    return Workspace(root)


def study(night: Workspace, near_m: float | None) -> None:
    ws = scratch(night, f"{near_m or 0}")
    cfg = InspectConfig(near_m=near_m, search=False)
    tables: dict[str, list[pd.DataFrame]] = {"poses": [], "defects": [], "parts": []}
    clock = time.perf_counter()
    for assembly in assemblies(ws):
        done = inspect_assembly(assembly, ws, cfg, assembly)
        if done.error:
            print(f"{assembly}: {done.error}")
            continue
        for name, frame in read_tables(Path(done.folder)).items():
            if name in tables:
                tables[name].append(frame)
    print(f"\n## near views: {near_m or 'none'} ({time.perf_counter() - clock:.0f} s)\n")
    poses, defects, parts = (pd.concat(tables[n]) for n in ("poses", "defects", "parts"))
    design = poses[(poses["variant"] == "intact") & (poses["route"] == "design")]
    print(design.groupby("views")[["error_mm", "error_deg"]].quantile([0.5, 0.9]).round(3)
          .to_string(), "\n")
    mine = defects[(defects["method"] == REGISTERED) & defects["inspectable"]]
    print(mine.groupby(["kind", "size", "views"])["caught"].agg(["sum", "count"]).unstack()
          .to_string(), "\n")
    intact = parts[(parts["method"] == REGISTERED) & (parts["variant"] == "intact")
                   & parts["inspectable"] & ~parts["defective"]]
    print("false alarms (intact parts flagged):")
    print(intact.groupby("views")["flagged"].agg(["sum", "count"]).to_string())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workspace", type=Path, required=True)
    parser.add_argument("--near-m", type=float, default=0.3)
    args = parser.parse_args()
    ws = Workspace(args.workspace)
    for near in (None, args.near_m):
        study(ws, near)


if __name__ == "__main__":
    main()
