"""The capture stage: from scenes and recordings to what the learned stages see.

``scan`` is the stage (scenes to captures, captures to learning inputs), ``coverage`` decides
where each part is scored; what a camera knows of a part: ``pointcloud`` back-projects frames
to points, ``segment`` separates parts without instance ids, ``observe`` builds the three-state
input grid from the observed points and the cameras, ``examples`` cuts a part's views into
completion examples, and ``register`` lays a completion back onto its scan. The camera itself
is ``cadio.camera``, the MCAP files ``cadio.recordings``.
"""
