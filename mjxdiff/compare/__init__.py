"""Stage 3, comparison: two trajectories -> a verdict per scenario, and the checks behind a failure
(``noise``: C's own rounding envelope; ``verdict`` and ``result``; ``statistics``: the behaviour
statistics :mod:`mjxdiff.metrics` exports; ``onestep``; ``transfer``:
MJX's host interface; ``diagnose``: drill-down and causes; ``known``, ``support``, ``segments``,
``reference``: what MJX, and C, are known to get wrong)."""
