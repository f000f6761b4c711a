"""mjxdiff's pytest plugin (registered through the ``pytest11`` entry point).

Offers the ``mjx_matches_c`` fixture (the :func:`mjxdiff.testing.assert_mjx_matches_c`
helper) and registers Hypothesis profiles ``mjxdiff-dev`` and ``mjxdiff-ci``
with ``deadline=None``, since JIT compiles break any per-example deadline.

pytest loads this plugin in every run of every project installed beside
mjxdiff, so it imports nothing heavy itself (Hypothesis only): JAX, MuJoCo and MJX are imported
when a test first uses the fixture.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, settings


# Hypothesis itself is light (no JAX); registering at import keeps the profiles usable
# from a conftest's module level, which runs before any pytest_configure hook.
settings.register_profile("mjxdiff-dev", deadline=None, max_examples=20,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("mjxdiff-ci", deadline=None, max_examples=10, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture
def mjx_matches_c():
    """``mjx_matches_c(model, qpos=..., ctrl=...)`` asserts MJX follows MuJoCo C, with a diagnosis on failure."""
    from mjxdiff.testing import assert_mjx_matches_c

    return assert_mjx_matches_c
