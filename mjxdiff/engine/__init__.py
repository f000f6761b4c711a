"""Stage 2, engines: the batched inputs stepped by MuJoCo C, MJX and MuJoCo Warp into
:class:`~mjxdiff.engine.trajectory.Trajectory` records (``trajectory``, ``engines``,
``mjwarp``), MJX's compiled rollouts cached across processes (``export_cache``), and one forward
pass read back stage by stage (``stages``)."""
