"""The built-in sample library the product generates for itself (build123d, bd_warehouse).

``parts`` builds single parts of the paper's four categories, ``assemblies`` a few assemblies
with known mates, and ``library`` writes them as byte-reproducible STEP with a LIBRARY.json index.
For training, ``variants`` draws seeded variants of the single parts and ``assembly_variants``
of the assembly families (``shaft_assemblies``, ``joint_assemblies``, on ``assembly_kit``),
written as STEP assemblies with the face mates each layout is built to have.
"""
