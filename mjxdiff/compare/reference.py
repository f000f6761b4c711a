"""The reference itself: where the installed MuJoCo C is known to be wrong.

mjxdiff judges MJX against MuJoCo C, but C has bugs too. ``mujoco`` 4.0.0 pins
``mujoco-core==4.0.0`` and ``mujoco-mjx`` 3.17.0 needs ``mujoco``, so pip gives every MJX user
4.0.0's C, whose sparse Cholesky factorization "merged rows with different descendants into one
supernode and gave the Newton solver a wrong Hessian factor when the constraint Jacobian is
sparse" (mujoco-core 4.0.1's changelog, google-deepmind/mujoco issue 3767).

Measured here (2026-11-28; ``tests/data/sparse_cholesky_401.json``): a free-floating binary tree
of 15 hinged capsules on a plane (nv 21, ``jacobian="sparse"``, Newton, 1 iteration), stepped by
C 4.0.0, from the state of its step 6 (in contact with the plane): 4.0.0's qacc is 7,978 from 4.0.1's (on a
scale of 15,261); the rollouts agree bit for bit before it. A ternary tree (nv 46, 100
iterations) parts at step 13 by 2.5e-3 and grows to 1.8e5. Chains, separate free trees, and five
bundled scenarios (humanoid, ant, box_stack, equality, combinations) forced to the sparse Jacobian
stayed bit-identical over 200-300 steps at 1, 3 and 100 iterations.
"""

from __future__ import annotations

from typing import Any

import mujoco

__all__ = ["PAIRS", "SPARSE_CHOLESKY", "c_outlier", "caveat", "outlier_clause", "suspect"]

#: The known C bug a model can meet: the release it is in, the fix, and what to run to rule it out.
SPARSE_CHOLESKY = dict(
    release="4.0.0", fixed_in="4.0.1", issue="google-deepmind/mujoco#3767",
    what="sparse Cholesky gives Newton a wrong Hessian factor on branching trees with a sparse Jacobian",
    check="pip install --no-deps mujoco-core==4.0.1, then sweep again: a verdict that changes was C's")


def _branching(m: mujoco.MjModel) -> bool:
    """Whether some body (not the world) has two or more child bodies with degrees of freedom
    beneath it: the tree shape whose rows the 4.0.0 factorization merged wrongly (separate trees
    and chains stayed bit-identical to 4.0.1 here)."""
    moving = [False] * m.nbody
    for b in range(m.nbody - 1, 0, -1):  # children come after their parents
        moving[b] = moving[b] or m.body_dofnum[b] > 0
        moving[m.body_parentid[b]] = moving[m.body_parentid[b]] or moving[b]
    children = [0] * m.nbody
    for b in range(1, m.nbody):
        if moving[b]:
            children[m.body_parentid[b]] += 1
    return any(n >= 2 for n in children[1:])


def suspect(m: mujoco.MjModel, version: str | None = None) -> dict[str, Any] | None:
    """:data:`SPARSE_CHOLESKY` when the installed C (``version``, default ``mujoco.__version__``)
    is its release and ``m`` meets its conditions (Newton, a sparse constraint Jacobian,
    a branching tree), else None."""
    if (version or mujoco.__version__) != SPARSE_CHOLESKY["release"]:
        return None
    if m.opt.solver != mujoco.mjtSolver.mjSOL_NEWTON or not mujoco.mj_isSparse(m) or not _branching(m):
        return None
    return dict(SPARSE_CHOLESKY)


def caveat(found: dict[str, Any]) -> str:
    """The clause a failing verdict gains from :func:`suspect`'s finding."""
    return (f"the reference may be wrong here: MuJoCo C {found['release']}'s {found['what']}, "
            f"and this model is one ({found['issue']}, fixed in {found['fixed_in']}); to rule C out: {found['check']}")


#: ``impl="both"``'s three pairs of one scenario, by their name's suffix (``mjxdiff.runner.pipeline``).
PAIRS = ("", "@warp", "@mjx-warp")


def c_outlier(statuses: dict[str, str]) -> bool:
    """Whether C is the odd one out of ``impl="both"``'s three verdicts of one scenario, ``suffix ->
    status`` (:data:`PAIRS`): MJX against C and MuJoCo Warp against C both ``fail``, while MuJoCo
    Warp against MJX (C's own rounding envelope as the floor, float32 tolerances) ``pass``es.

    >>> c_outlier({"": "fail", "@warp": "fail", "@mjx-warp": "pass"})
    True
    >>> c_outlier({"": "fail", "@warp": "pass", "@mjx-warp": "pass"})  # MJWarp within float32 of C
    False
    """
    return (statuses.get("") == "fail" and statuses.get("@warp") == "fail"
            and statuses.get("@mjx-warp") == "pass")


def outlier_clause(name: str) -> str:
    """What a failing verdict of scenario ``name`` gains where :func:`c_outlier` holds."""
    return (f"C is the outlier: MJX and MuJoCo Warp agree with each other ({name}@mjx-warp passes) and both part "
            "from C beyond their bounds, so C is wrong here or both share this difference from it; "
            "check it on another MuJoCo C (`mjxdiff versions`, or pip install --no-deps mujoco-core==NEWER)")
