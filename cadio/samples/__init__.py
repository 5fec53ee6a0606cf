"""The built-in sample library the product generates for itself (build123d, bd_warehouse).

``parts`` builds single parts of the paper's four categories, ``assemblies`` a few assemblies
with known mates, and ``library`` writes them as byte-reproducible STEP with a LIBRARY.json index.
"""
