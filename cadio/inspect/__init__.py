"""The as-built inspection: the library's CAD registered in a real-size scan, each CAD mate read
from the registered B-reps, planted defects to judge it by.

``surface`` (a part's CAD surface and what a camera sees of it) and ``scan`` (a capture's
points) feed ``register`` (ICP from a seed, global search from nothing), read by ``routes``
(by design, by search); ``symmetry`` and ``uncertainty`` say what a pose error and a fit's
points mean; ``asbuilt`` reads each mate's residuals and status; ``defects`` plants the
variants; ``stage`` and ``evaluate`` are the night's stage, ``recording`` one recording
checked against its design (``mateqa inspect``).
"""
