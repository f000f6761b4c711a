"""fuzz() from scratch with one injected MJX bug from tests/test_detection.py.

python benchmarks/scripts/fuzz_injected_bug.py extra_damping (from the repo root).
"""
import sys
import tempfile
import time

import pytest

sys.path.insert(0, "tests")
import test_detection as td

from mjxdiff.engine import engines
from mjxdiff.tools.fuzz import DEFAULT_BUDGET, fuzz

engines.configure_jax("float64", ".jax_cache")
name = sys.argv[1]
mp = pytest.MonkeyPatch()
getattr(td, name)(mp)
engines.clear_compiled()
t = time.perf_counter()
r = fuzz(budget=DEFAULT_BUDGET, out=tempfile.mkdtemp(), seed=0, shrink_budget=60)
f = r.failure
print(f"{name}: examples {r.examples} in {r.seconds:.0f} s ({r.examples / r.seconds * 60:.1f}/min),"
      f" total {time.perf_counter()-t:.0f} s;",
      "NOT FOUND" if f is None
      else f"found: {f['nbody']} bodies, {f['ngeom']} geoms, features {f['features']}; {f['message'][:200]}")
