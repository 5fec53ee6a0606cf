"""The ground-truth room: what the exact B-rep says about pairs of parts.

``relations`` is the one relation function (ten relations from two parts' features), used by
the truth and by the geometric baseline; ``contact`` decides which solids touch; ``mates``
extracts face-level mates, part-level relations and joints of assemblies (``joints`` names the
joint the mates allow); ``scenes`` places pairs of parts so that each relation holds.
"""
