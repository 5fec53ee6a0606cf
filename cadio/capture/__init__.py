"""The capture room: RGB-D frames in and out.

``render`` simulates the paper's camera with open3d ray casting, ``noise`` is the depth sensor
model, ``mcap_io`` reads MCAP recordings in both dialects (Foxglove protobuf, ``foxglove_mcap``,
whose writer makes our captures; ROS 2 CDR, ``ros2_mcap``) as frames, through one form of their
messages (``recording``), a channel sorter (``channels``), the transform tree (``tf_tree``) and
the rules that pair images and place cameras (``pairing``),
``pointcloud`` back-projects frames to per-part points and grids, ``segment`` separates parts
without instance ids, and ``scan`` is the stage: scenes to captures, captures to learning inputs.
``primitives`` is the geometric relation baseline: planes and cylinders fitted to a part's
points by ``ransac``, then the ground truth's relation function.
No CAD kernel is imported here.
"""
