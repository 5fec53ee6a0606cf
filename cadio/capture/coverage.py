"""Every part of the library scored once: where each part is scored, and the parts captured alone.

A night's pair scenes and assembly captures show only some of the library's parts (a part alone
in its split has no partner for a scene; a part of an assembly whose mates failed is placed
nowhere). The completion stage scores a part once in each context it is seen in
(``capture_context``: in a pair scene, inside an assembly, alone), in the first capture of that
context, by name, that places it; that capture is chosen before any is rendered
(``scoring_plan``), and only there are the part's learning examples built
(``cadio.capture.scan.scan_inputs``; elsewhere it gets only what the relation stage reads).
Every ingested part that no capture scored (placed nowhere, its capture failed, or hidden in
every view) is then captured alone (``capture_alone``): on the support plane in a seeded pose,
from the same cameras as the scenes, and scored there.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence

import pandas as pd

from cadio.camera.render import PlacedPart
from cadio.capture.examples import part_pose
from cadio.capture.scan import ASSEMBLY_PREFIX, ScanConfig, with_inputs, write_views
from cadio.catalog import read_catalog
from cadio.contracts import CaptureSummary
from cadio.errors import CaptureError
from cadio.truth.assemblies import AssemblyJob
from cadio.workspace import Workspace, read_mesh

log = logging.getLogger(__name__)

ALONE_PREFIX = "alone-"

# What a capture scores: capture id (the MCAP file's stem) -> part ids.
Plan = dict[str, tuple[str, ...]]


def placements(scenes: pd.DataFrame, assemblies: Iterable[AssemblyJob]) -> dict[str, list[str]]:
    """Capture id -> the part ids it places: each scene row's two parts, each assembly's
    solids (captured as ``assembly-<name>``)."""
    placed = {str(r["scene_id"]): [str(r["part_a"]), str(r["part_b"])]
              for r in scenes.to_dict("records")}
    for job in assemblies:
        placed[f"{ASSEMBLY_PREFIX}{job.assembly}"] = list(job.part_ids.values())
    return placed


def capture_context(capture_id: str) -> str:
    """Where a capture shows its parts, from its name: ``assembly`` (``assembly-<name>``),
    ``alone`` (``alone-<part_id>``), else ``pair`` (a scene, or a recording)."""
    return next((c for c in ("assembly", "alone") if capture_id.startswith(f"{c}-")), "pair")


def scoring_plan(placed: Mapping[str, Sequence[str]]) -> Plan:
    """Capture id -> the parts scored in it: each part, in each context it is placed in, in
    the first capture (by id) of that context that places it; a capture that scores none is
    left out."""
    first: dict[tuple[str, str], str] = {}
    for capture in sorted(placed):
        for part in placed[capture]:
            first.setdefault((str(part), capture_context(capture)), capture)
    plan: dict[str, list[str]] = {}
    for (part, _), capture in sorted(first.items()):
        plan.setdefault(capture, []).append(part)
    return {capture: tuple(parts) for capture, parts in sorted(plan.items())}


def ingested_parts(catalog: pd.DataFrame) -> pd.DataFrame:
    """The parts the library gave: the catalog's ``ok`` rows, columns part_id and category."""
    ok = catalog[catalog["status"] == "ok"]
    return ok[["part_id", "category"]].astype("str").drop_duplicates("part_id").reset_index(
        drop=True)


def unscored_parts(catalog: pd.DataFrame, captured: Iterable[CaptureSummary]) -> list[str]:
    """Ingested part ids that no capture scored (``CaptureSummary.scored``), sorted."""
    scored = {pid for c in captured if not c.error for pid in c.scored}
    return sorted(set(ingested_parts(catalog)["part_id"]) - scored)


def alone_id(part_id: str) -> str:
    """The capture id of a part captured alone."""
    return f"{ALONE_PREFIX}{part_id}"


def is_alone(capture_id: str) -> bool:
    """Whether a capture shows one part alone (it has no pair to relate)."""
    return capture_context(capture_id) == "alone"


def capture_alone(part_id: str, category: str, ws: Workspace, cfg: ScanConfig,
                  colour: str = "#b4b4b4") -> CaptureSummary:
    """Render one part alone on the support plane (``examples.part_pose``: a seeded turn,
    on its side for about a third of the parts) into ``captures/alone-<part_id>.mcap`` from
    the views of ``cfg``, and build its learning examples to be scored. A failure comes back
    as the summary's error."""
    scene_id = alone_id(part_id)
    try:
        mesh = read_mesh(ws.mesh(part_id))
        part = PlacedPart(instance_id=1, mesh=mesh, pose=part_pose(part_id, mesh),
                          colour=colour, part_id=part_id, label=part_id)
        path = ws.capture(scene_id)
        frames = write_views(path, [part], cfg, {"alone": part_id, "category": category})
    except (OSError, ValueError, CaptureError) as exc:
        log.warning("part %s alone: %s", part_id, exc)
        return CaptureSummary(scene_id=scene_id, path="", error=str(exc))
    summary = CaptureSummary(scene_id=scene_id, path=str(path), frames=frames, parts=1,
                             bytes=path.stat().st_size)
    return with_inputs(summary, ws, cfg, scored=(part_id,))


def capture_parts_alone(part_ids: Sequence[str], ws: Workspace,
                        cfg: ScanConfig) -> list[CaptureSummary]:
    """``capture_alone`` for each part id, with its category and colour from the catalog."""
    catalog = read_catalog(ws.catalog).drop_duplicates("part_id").set_index("part_id")
    return [capture_alone(pid, str(catalog.at[pid, "category"]), ws, cfg,
                          _colour(catalog.at[pid, "colour"])) for pid in part_ids]


def _colour(value: object) -> str:
    return value if isinstance(value, str) and value else "#b4b4b4"
