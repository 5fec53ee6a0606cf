"""``completed``: the completion network's shape of each part from that single view.

The product's input (the paper's route): the night's completion network (the shipped method
of ``models.completions`` under the observed protocol) completes every part of a capture from
each of its single observed views, and the completion is read as points (``voxel_surface``:
the centres of its surface voxels). Its networks also read the view's observed points and
their evidence (``observed_by``): a completion gives the hidden side, but as voxel centres
where the camera saw finer points.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from cadio.records import FloatArray
from cadio.registry import Role
from models.relation_inputs import INPUTS, InputContext, RelationInput

if TYPE_CHECKING:  # torch and the evidence's modules load where a night completes and relates
    from cadio.capture.observe import CubeGrid
    from cadio.evidence.pairs import InputBuilder, InputClouds, ViewSources
    from cadio.workspace import Workspace
    from models.train import Model

THRESHOLD = 0.5  # a voxel of the completion is solid above this probability
_SINGLE = re.compile(r"^observed-(\d+)\.npz$")

Surface = Callable[[npt.NDArray[np.float32], "CubeGrid"], FloatArray]


def voxel_surface(probs: npt.NDArray[np.float32], grid: CubeGrid) -> FloatArray:
    """The centres of the surface voxels of the solid predicted (probabilities over ``grid``,
    (n, n, n)), world metres: how the night reads a completion."""
    from reports.metrics import surface_points

    n = probs.shape[-1]
    return surface_points(probs > THRESHOLD, grid.voxel_m(n), grid.grid_to_world(n))


def completed_clouds(folder: Path, model: Model, surface: Surface = voxel_surface
                     ) -> dict[int, FloatArray]:
    """The completion of each single observed view of one part: view -> (m, 3) world metres
    (``surface`` of the probabilities predicted in the view's observed grid; the scan's points
    where nothing is predicted)."""
    from cadio.capture.examples import read_example
    from models.train import predict

    files = sorted((int(m.group(1)), p) for p in Path(folder).glob("observed-*.npz")
                   if (m := _SINGLE.match(p.name)))
    if not files:
        return {}
    examples = [read_example(p) for _, p in files]
    probs = predict(model, [e.inputs for e in examples], batch_size=16)
    out = {}
    for (view, _), example, p in zip(files, examples, probs, strict=True):
        pts = surface(p, example.grid) if (p > THRESHOLD).any() else \
            example.points  # nothing predicted: the scan is all there is
        out[view] = np.asarray(pts, dtype=np.float64)
    return out


def capture_completions(capture: str, part_ids: Iterable[str], ws: Workspace,
                        model: Model | None, surface: Surface = voxel_surface
                        ) -> dict[tuple[str, int], FloatArray]:
    """(part id, view) -> completed points for the parts of one capture (none without model)."""
    if model is None:
        return {}
    return {(pid, view): pts for pid in part_ids
            for view, pts in completed_clouds(ws.inputs(capture, pid), model, surface).items()}


def completions_of(path: Path, ws: Workspace, completion: Model | None,
                   surface: Surface = voxel_surface) -> dict[tuple[str, int], FloatArray]:
    """(instance id as text, view) -> completed points of every instance with inputs under a
    capture; (m, 3) world metres, or (m, 6) with each point's outward unit normal after it
    (a completion that gives normals: the pair evidence reads them as it reads the CAD
    samples' exact ones)."""
    folder = ws.root / "inputs" / path.stem
    parts = [p.name for p in folder.iterdir() if p.is_dir()] if folder.is_dir() else []
    return capture_completions(path.stem, parts, ws, completion, surface)


def completion_builder(done: Mapping[tuple[str, int], FloatArray]) -> InputBuilder:
    """The clouds of a view of a pair from the capture's completions by (instance, view)."""
    def build(src: ViewSources) -> InputClouds | None:
        from cadio.evidence.pairs import InputClouds, evidence_cloud, k_points

        found = [done.get((str(instance), src.view)) for instance in src.instances]
        clouds = [c for c in found if c is not None]
        if len(clouds) < 2:
            return None
        points = np.stack([k_points(c[:, :3], src.cfg.n_points) for c in clouds])
        evidence = tuple(np.asarray(evidence_cloud(c, src.cfg.evidence_points),
                                    dtype=np.float32) for c in clouds)
        return InputClouds(points, (evidence[0], evidence[1]))

    return build


def builder(capture: Path, ws: Workspace, ctx: InputContext) -> InputBuilder | None:
    done: dict[tuple[str, int], Any] = completions_of(
        capture, ws, ctx.completion, ctx.surface or voxel_surface)
    return completion_builder(done) if done else None


COMPLETED = INPUTS.register(RelationInput(
    "completed", "the completion network's shape from the single view, beside its observed "
    "points", 2, __name__, builder, role=Role.OURS, observed_by="partial"))
