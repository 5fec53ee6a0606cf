"""Whether the inspection's pose sigmas are honest: each intact mate's residual over its sigma.

A mate as built holds while its residuals stay within max(the CAD's tolerance, 3 sigma of the
two parts' relative pose) (``cadio.inspect.asbuilt``); the sigma comes from the fit's Hessian
(``cadio.inspect.uncertainty``). On an intact assembly every residual is the registration's
error, so residual / sigma is a normal error's absolute value where the sigma is right: median
0.674, 90th percentile 1.645, 95th 1.960. This reads the inspection rows of workspaces
(``inspect/*/mates.parquet``: the intact captures, the product's method), takes the residuals
whose threshold the sigma set (3 sigma above the tolerance, so sigma = threshold / 3), and
prints per set of views the quantiles of |residual| / sigma and the factor k by which the
sigmas would have to grow for each quantile to match: k near 1 is calibrated, above 1 the
sigmas are too small (false alarms), below 1 too large (defects missed). The
``RouteConfig.several_views_sigma`` of the inspection is set from development workspaces
this way; a workspace inspected with it should read k near 1.

Usage:
    .venv/bin/python bench/studies/pose_sigma.py WORKSPACE [WORKSPACE ...]

Nothing is asserted: it prints the table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

RESIDUALS = ("plane_offset_mm", "normal_angle_deg", "axis_distance_mm", "axis_angle_deg")
NORMAL = {"median": 0.6745, "p90": 1.6449, "p95": 1.9600}


def ratios(mates: pd.DataFrame) -> pd.DataFrame:
    """|residual| / sigma of the intact captures' product rows whose threshold the sigma set
    (columns: views, residual, z)."""
    intact = mates[(mates["variant"] == "intact") & (mates["method"] == "registered")]
    frames = []
    for name in RESIDUALS:
        if name not in intact:
            continue
        rows = intact[["views", name, f"{name}_threshold"]].dropna()
        rows = rows[np.isfinite(rows[f"{name}_threshold"]) & (rows[f"{name}_threshold"] > 0)]
        frames.append(pd.DataFrame({"views": rows["views"].astype(str), "residual": name,
                                    "z": rows[name].abs() / (rows[f"{name}_threshold"] / 3)}))
    return pd.concat(frames) if frames else pd.DataFrame(columns=["views", "residual", "z"])


def table(z: pd.DataFrame) -> pd.DataFrame:
    """Per set of views (and all together): n, the quantiles of z and the factor k of each."""
    rows = []
    for views, group in [*z.groupby("views"), ("pooled", z)]:
        row: dict[str, object] = {"views": views, "n": len(group)}
        for name, q in (("median", 0.5), ("p90", 0.9), ("p95", 0.95)):
            value = float(group["z"].quantile(q)) if len(group) else float("nan")
            row[f"z {name}"] = round(value, 2)
            row[f"k {name}"] = round(value / NORMAL[name], 2)
        rows.append(row)
    return pd.DataFrame(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspaces", nargs="+", type=Path)
    args = parser.parse_args()
    files = [f for ws in args.workspaces for f in sorted((ws / "inspect").glob("*/mates.parquet"))]
    if not files:
        raise SystemExit("no inspect/*/mates.parquet under the workspaces given")
    z = ratios(pd.concat([pd.read_parquet(f) for f in files]))
    print(f"{len(files)} inspections, {len(z)} residuals set by their sigma")
    print(table(z).to_string(index=False))


if __name__ == "__main__":
    main()
