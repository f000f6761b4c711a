"""Contacts C itself cannot decide (MuJoCo's parity method's ``contacts_ambiguous``): at a step
where the engines' contacts differ by geom pair, C's own contacts at the state before the step
are computed again under the method's perturbations: the state rounded to float32, ``qpos``
moved at random by up to ``ccd_tolerance`` (:data:`MOVES` draws), and ``ccd_tolerance`` times
10 and times 0.1. Where any of them changes C's firm contact pairs (:mod:`mjxdiff.engine.pairs`),
the step is ambiguous (convex collision on near-parallel faces is defined only up to
``ccd_tolerance``; a stack of aligned boxes shares its load among corners C picks by rounding),
and its mismatch is not judged.

Before that, a mismatch may be explained by the state alone: once a rollout's states part by
rounding (chaos, or float32 against float64), a foot lands a step earlier in one engine than in
the other and no collision code is at fault. So at each mismatching step C's contacts are also
computed at the *tested engine's* state before it: where they are the tested engine's own pairs,
C's collision agrees with it there, and the mismatch is counted as explained by the state
(:attr:`CcdAmbiguity.explained`), not judged; the state fields judge the states. A collision bug
(a contact C would not make at that state, or made in the wrong pair) is not explained: C at the
same state makes other pairs.

Only mismatching steps are checked: the state check at each (one position pass), the
perturbations at most :data:`CHECKS_PER_MEMBER` per member (later ones count as mismatches). A
passing scenario pays nothing, and a failing one a few position passes.
"""

from __future__ import annotations

import copy
from typing import Any

import mujoco
import numpy as np

from mjxdiff.engine import pairs

__all__ = ["CHECKS_PER_MEMBER", "MOVES", "CcdAmbiguity"]

#: Mismatching steps per member whose ambiguity is checked.
CHECKS_PER_MEMBER = 32
#: Random ``qpos`` moves of up to ``ccd_tolerance`` tried per check.
MOVES = 4
#: The method's scalings of ``ccd_tolerance``.
_CCD_SCALES = (10.0, 0.1)


class CcdAmbiguity:
    """Tells, per member and step, whether C's firm contact pairs move under the parity method's
    perturbations. Fed C's pieces in order (:meth:`before`), it keeps each member's last state.

    Args:
      models: (B,) C models, one per member.
      qpos0: (B, nq) initial positions.
      seed: the sweep's seed (the ``qpos`` moves are drawn from it).
    """

    def __init__(self, models: tuple[mujoco.MjModel, ...], qpos0: np.ndarray, seed: int = 0):
        self.models = models
        self.last = {engine: np.array(qpos0, float, copy=True) for engine in ("c", "mjx")}
        self.checked = np.zeros(len(models), int)
        #: (B,) mismatching steps found ambiguous under the perturbations
        self.found = np.zeros(len(models), int)
        #: (B,) mismatching steps where C at the tested engine's state makes the tested engine's pairs
        self.explained = np.zeros(len(models), int)
        self.seed = seed
        self._scaled: dict[int, list[mujoco.MjModel]] = {}
        self._data: dict[int, mujoco.MjData] = {}

    def before(self, qpos: Any, members: np.ndarray, engine: str = "c") -> np.ndarray:
        """(b, K, nq) positions before each step of ``engine``'s (``c`` or ``mjx``: the one under
        test) piece whose positions after them are ``qpos`` (b, K, nq), for ``members``;
        remembers the piece's last ones."""
        qpos = np.asarray(qpos, float)
        last = self.last[engine]
        out = np.concatenate([last[members, None], qpos[:, :-1]], axis=1)
        last[members] = qpos[:, -1]
        return out

    def _data_of(self, member: int) -> mujoco.MjData:
        """``member``'s scratch MjData, made on first use."""
        if member not in self._data:
            self._data[member] = mujoco.MjData(self.models[member])
        return self._data[member]

    def _sums(self, m: mujoco.MjModel, d: mujoco.MjData, qpos: np.ndarray) -> np.ndarray:
        d.qpos[:] = qpos
        mujoco.mj_fwdPosition(m, d)  # pyright: ignore[reportAttributeAccessIssue]
        return pairs.of_data(m, d)

    def ambiguous(self, member: int, qpos: np.ndarray, step: int = 0) -> bool:
        """Whether C's firm contact pairs at ``qpos``, the state before ``step``, change under a
        perturbation (counted); the ``qpos`` move is drawn from (seed, member, step)."""
        m = self.models[member]
        d = self._data_of(member)
        base = self._sums(m, d, qpos)
        tol = float(m.opt.ccd_tolerance)
        if member not in self._scaled:
            self._scaled[member] = []
            for scale in _CCD_SCALES:
                mi = copy.copy(m)
                mi.opt.ccd_tolerance = tol * scale
                self._scaled[member].append(mi)
        moves = np.random.default_rng([self.seed, member, step]).uniform(-tol, tol, (MOVES, *qpos.shape))
        states = [qpos.astype(np.float32).astype(float), *(qpos + moves)]
        moved = any(not np.array_equal(self._sums(m, d, q), base) for q in states) or any(
            not np.array_equal(self._sums(mi, d, qpos), base) for mi in self._scaled[member])
        self.found[member] += moved
        return moved

    def state_explains(self, member: int, qpos: np.ndarray, sums: np.ndarray) -> bool:
        """Whether C's firm contact pairs at ``qpos``, the tested engine's state before a step,
        are the tested engine's pair ``sums`` (2,) of that step (counted)."""
        if not np.isfinite(qpos).all():
            return False
        m = self.models[member]
        same = bool(np.array_equal(self._sums(m, self._data_of(member), qpos), np.asarray(sums, np.uint32)))
        self.explained[member] += same
        return same

    def filter(self, differ: np.ndarray, before: np.ndarray, members: np.ndarray, start: int = 0,
               tested: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``differ`` (b, K) of the steps from ``start`` with the ones explained by the state or
        found ambiguous cleared; ``before`` (b, K, nq) C's states before them, ``tested`` the
        tested engine's (b, K, nq) states before them and its (b, K, 2) pair sums. The
        perturbations are tried at most :data:`CHECKS_PER_MEMBER` times per member."""
        differ = differ.copy()
        for row, k in zip(*np.nonzero(differ)):
            i = int(members[row])
            if tested is not None and self.state_explains(i, tested[0][row, k], tested[1][row, k]):
                differ[row, k] = False
                continue
            if self.checked[i] >= CHECKS_PER_MEMBER:
                continue
            self.checked[i] += 1
            if self.ambiguous(i, before[row, k], start + int(k)):
                differ[row, k] = False
        return differ
