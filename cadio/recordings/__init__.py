"""Recordings: RGB-D in MCAP, read and written.

``mcap_io`` reads a recording in either dialect that carries RGB-D (Foxglove's protobuf
schemas, ``foxglove_mcap``, whose writer makes our captures; ROS 2 CDR, ``ros2_mcap``) as
frames, through one form of their messages (``recording``), a channel sorter (``channels``),
the transform tree (``tf_tree``) and the rules that pair images and place cameras
(``pairing``). Records and readers are kept apart, as the mcap library keeps them. No CAD
kernel and no rendering here.
"""
