"""Shrink injected MJX bugs on a bundled scenario's model into bug bundles (issue 37).

    python benchmarks/scripts/shrink_injected.py [--scenario humanoid] [--out DIR] [BUG_ID ...]

Per bug of tests/injected_bugs.py (default: contact_distance and armature): the bug patched into
MJX, C's rollout of the scenario's model from its keyframe (else qpos0) with smooth random
controls searched for the first state where one step or mj_forward differs, the model shrunk
(``mjxdiff.tools.shrink.shrink``) and bundled under OUT/BUG_ID; then the minimal model checked with the
bug (the same signature: shrinking turned it into no other divergence) and without it (no
divergence: the bug's own). One line per bug: sizes before and after (bodies, geoms, joints,
actuators, sensors, options, steps), candidates, XLA compiles, seconds.
"""

import argparse
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

import injected_bugs  # noqa: E402

from mjxdiff.tools import bundle, shrink  # noqa: E402
from mjxdiff.engine import engines  # noqa: E402
from mjxdiff.input.scenario import load_scenario  # noqa: E402


def _size(c: shrink.Counts) -> str:
    return f"{c.bodies}/{c.geoms}/{c.joints}/{c.actuators}/{c.sensors}/{c.options}/{c.steps}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bugs", nargs="*", default=["contact_distance", "armature"], metavar="BUG_ID")
    parser.add_argument("--scenario", default="humanoid")
    parser.add_argument("--out", default="mjxdiff-out/shrink-injected")
    parser.add_argument("--budget", type=float, default=600.0)
    args = parser.parse_args()
    engines.configure_jax("float64")
    sc = load_scenario(args.scenario)
    path = sc.model_path
    spec = shrink.named(mujoco.MjSpec.from_file(str(path)))
    m = spec.compile()
    rng = np.random.default_rng(0)
    controls = rng.uniform(-1, 1, (200, m.nu)) * 0.3
    print("bug, signature, before b/g/j/a/s/o/steps -> after, candidates, compiles, s, with bug, without")
    for bug_id in args.bugs:
        bug = injected_bugs.by_id(bug_id)
        with pytest.MonkeyPatch.context() as mp:
            bug.patch(mp)
            engines.clear_compiled()
            found = shrink.find_state(m, 200, 0 if m.nkey else None, lambda k: controls[k])
            if found is None:
                print(f"{bug_id}: no divergence in 200 states")
                continue
            state, signature, step = found
            shrunk = shrink.shrink(spec, state, signature, args.budget, lambda s: print("  " + s, file=sys.stderr),
                                   steps_before=step + 1)
            bundle.write(shrunk, Path(args.out) / bug_id, path.parent, origin=f"{args.scenario} with {bug_id}")
            minimal = shrunk.spec.compile()
            with_bug = shrink.probe(minimal, shrunk.state)
        engines.clear_compiled()
        without = shrink.probe(minimal, shrunk.state)
        print(f"{bug_id}, {signature.describe()}, {_size(shrunk.before)} -> {_size(shrunk.after)}, "
              f"{shrunk.candidates}, {shrunk.compiles}, {shrunk.seconds:.0f}, "
              f"{'same' if with_bug == signature else with_bug}, {'passes' if without is None else without}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
