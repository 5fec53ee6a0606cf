"""The simulated camera: what an RGB-D sensor would record of placed parts.

``render`` places meshes and ray-casts colour, depth and instance ids with open3d on the
paper's camera circle (its per-pixel loops, compiled, in ``raycast``); ``noise`` is the depth
sensor model. No CAD kernel here: meshes come from the workspace.
"""
