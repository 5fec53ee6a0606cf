"""The simulated camera: what an RGB-D sensor would record of placed parts.

``render`` places meshes and ray-casts colour, depth and instance ids with open3d on the
paper's camera circle (its per-pixel loops, compiled, in ``raycast``); ``noise`` is the depth
sensor model. No CAD kernel here: meshes come from the workspace.
"""

# The paper's camera circle: 125 views 2.88 degrees apart cover 360 degrees (``render``'s
# default; here, where a command line can read it without loading open3d).
CIRCLE_VIEWS = 125
