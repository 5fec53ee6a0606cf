"""The ground-truth room: what the exact B-rep says about pairs of parts.

``labels`` is the one truth function: the ten relations of every ordered pair of a set of placed
parts, for scenes, assemblies and training corpora alike. ``relations`` holds the definition
(ten relations from two parts' features and what their face mates say; the geometric baseline
uses it with fitted features); ``facemates`` finds the face-level mates, on the part geometry of
``contact`` pruned by ``proximity``; ``mates`` writes an assembly's face mates, part relations
and joints (``joints`` names the joint the mates allow); ``scenes`` places pairs of parts so that
each relation holds (``placement``).
"""
