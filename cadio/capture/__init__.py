"""The capture room: RGB-D frames in and out.

``render`` simulates the paper's camera with open3d ray casting, ``noise`` is the depth sensor
model, ``mcap_io`` writes and reads Foxglove MCAP captures (ours and real recordings),
``pointcloud`` back-projects frames to per-part points and grids, ``segment`` separates parts
without instance ids, and ``scan`` is the stage: scenes to captures, captures to learning inputs.
``primitives`` is the geometric relation baseline: planes and cylinders fitted to a part's
points by ``ransac``, then the ground truth's relation function.
No CAD kernel is imported here.
"""
