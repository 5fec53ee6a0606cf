"""CAD and capture I/O for mateqa: STEP ingest, geometry, ground truth and RGB-D captures.

Everything that touches a CAD kernel (OpenCascade through OCP) or a capture file lives here.
"""
