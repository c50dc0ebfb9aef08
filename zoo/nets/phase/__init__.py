"""The phase-feature family: nets that read the pairs' GCC-PHAT (the ``audio_phase`` recipes).

``steering`` (the geometry: which lag each point reads), ``search`` (SRP-PHAT's coarse-to-fine search),
``null`` (white-noise correlations for the null statistic) and ``gate`` (per-sequence confirmation, hold
and fallback) are the pieces; ``srp_phat`` (non-learned) and ``phase_student`` (a learned heat map over
the steered response) compose them. Importing this package registers both nets.
"""

from zoo.nets.phase import (
    phase_student,  # noqa: F401
    srp_phat,  # noqa: F401
)
