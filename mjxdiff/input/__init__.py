"""Stage 1, input: a scenario file -> a model, a sweep's settings and the batched initial states,
controls and per-member models both engines step (``scenario``, ``config``, ``precision``,
``inputs``, ``joints``, ``adjust``, ``cost``)."""
