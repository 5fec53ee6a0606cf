"""The CAD room: everything that reads B-rep geometry through OpenCascade (OCP).

``step`` reads STEP parts and assemblies (names, colours, placements) and writes reproducible
STEP; ``tessellate`` meshes solids; ``faces`` recognises planes, cylinders and cones (freeform
ones too); ``features`` groups them into the features the relations are decided on; ``voxels``
builds solid occupancy grids; ``ingest`` turns a library folder into the workspace catalog,
meshes, features and voxels, each file in a crash-isolated worker.
"""
