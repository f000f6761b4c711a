"""Benchmarks share the tests' JAX settings: float64 and the persistent compile cache."""

import os
from pathlib import Path

from mjxdiff.engine.engines import configure_jax

os.environ.setdefault("MJXDIFF_CACHE", str(Path(__file__).resolve().parent.parent / ".jax_cache"))
configure_jax("float64")
