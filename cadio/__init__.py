"""CAD and capture I/O for mateqa, one room per stage.

The shared core lives here: typed records (``records``), the one home of every tolerance
(``tolerances``), errors, the workspace layout with atomic writes, the part catalog and the
crash-isolated worker pool (``sandbox``). The stages live in sub-packages:

- ``cadio.cad``: STEP reading, tessellation, face recognition, features, voxels, ingest (OCP).
- ``cadio.truth``: relations, contact, mates, joints and scenes: the ground truth (OCP).
- ``cadio.capture``: rendering, the sensor model, MCAP I/O, point clouds and segmentation.
- ``cadio.samples``: the built-in sample library (build123d / bd_warehouse).
"""
