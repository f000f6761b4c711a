"""MJX models of a batch's members: ``mjx.put_model`` of each member, the leaves that differ
between members stacked along a batch axis (:func:`put_models`), and MJX's refusal of a model
as :class:`UnsupportedError` (both re-exported by :mod:`mjxdiff.engine.engines`)."""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from mjxdiff import compat
from mjxdiff.engine.digest import untraced

if TYPE_CHECKING:
    from mujoco import mjx

__all__ = ["UnsupportedError", "put_models"]


class UnsupportedError(Exception):
    """MJX refused the model (``NotImplementedError`` in ``put_model``, ``make_data`` or
    while tracing ``mjx.step``); ``feature`` names what."""

    def __init__(self, feature: str):
        super().__init__(feature)
        self.feature = feature


@contextlib.contextmanager
def _unsupported():
    """Turns MJX's ``NotImplementedError`` into :class:`UnsupportedError`, naming the feature."""
    try:
        yield
    except NotImplementedError as e:
        raise UnsupportedError(" ".join(str(e).split()) or type(e).__name__) from None


_NUMERIC_NAMES: dict[tuple[type, tuple[type, ...]], tuple[str, ...]] = untraced({})


def _numeric_names(example, kinds: tuple[type, ...]) -> tuple[str, ...]:
    """The public attributes of ``example``'s type holding ``kinds`` (the same for every instance)."""
    key = (type(example), kinds)
    if key not in _NUMERIC_NAMES:
        _NUMERIC_NAMES[key] = tuple(name for name in dir(example) if not name.startswith("_")
                                    and isinstance(getattr(example, name), kinds))
    return _NUMERIC_NAMES[key]


def _c_fields(m: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Every numeric field of a C model, keyed like the MJX leaf it becomes (``body_mass``, ``opt.gravity``)."""
    out = {name: getattr(m, name) for name in _numeric_names(m, (np.ndarray,))}
    for struct in ("opt", "stat"):
        sub = getattr(m, struct)
        out.update({f"{struct}.{name}": np.asarray(getattr(sub, name))
                    for name in _numeric_names(sub, (np.ndarray, float, int))})
    return out


def _patched_columns(models: list[mujoco.MjModel], mx0: mjx.Model, impl: str = "jax"
                     ) -> dict[int, list[np.ndarray]] | None:
    """Per-member values of the MJX leaves that differ, read from the C models, without
    ``put_model`` per member; None when that is not safe.

    Safe when every C field that differs between the members becomes one MJX
    leaf unchanged (same values as member 0's leaf), and ``put_model`` of the
    last member differs from member 0's exactly in those leaves, holding the
    C values (no derived leaf depends on them).
    """
    paths = {jax.tree_util.keystr(path).lstrip("."): k
             for k, (path, _) in enumerate(jax.tree_util.tree_flatten_with_path(mx0)[0])}
    leaves0 = [np.asarray(x) for x in jax.tree.leaves(mx0)]
    fields = [_c_fields(mi) for mi in models]
    first = {name: value.tobytes() for name, value in fields[0].items()}  # bytes: 0.2 s -> 0.01 s for 64 humanoids
    differ = {name for f in fields[1:] for name, value in f.items() if value.tobytes() != first[name]}
    columns = {}
    for name in differ:
        k = paths.get(name)
        if k is None or fields[0][name].size != leaves0[k].size or not np.array_equal(
                fields[0][name].reshape(leaves0[k].shape), leaves0[k]):
            return None
        columns[k] = [f[name].reshape(leaves0[k].shape).astype(leaves0[k].dtype) for f in fields]
    probe = [np.asarray(x) for x in jax.tree.leaves(compat.put_model(models[-1], impl))]
    if len(probe) != len(leaves0) or any(not np.array_equal(p, columns[k][-1] if k in columns else leaves0[k])
                                         for k, p in enumerate(probe)):
        return None
    return columns


def put_models(models: tuple[mujoco.MjModel, ...], impl: str = "jax") -> tuple[mjx.Model, tuple[bool, ...]]:
    """``mjx.put_model`` of every member (MJX's ``impl``), with varying leaves stacked.

    Members usually differ only in randomized parameters that MJX copies
    straight from the C model; those leaves are read from the C models and
    ``put_model`` runs twice, not once per member (it costs about 15 ms on
    the ant; see :func:`_patched_columns` for when this falls back).

    Returns:
      (mx, varying): an ``mjx.Model`` whose leaves are either shared (as in
      member 0) or stacked along a new leading batch axis, and a per-leaf
      tuple saying which were stacked.

    Raises:
      UnsupportedError: MJX does not implement a feature the model uses.
      ValueError: members differ in a field MJX treats as static structure.
    """
    if models[0].nv == 0:  # MJX's scans over the kinematic tree raise ValueError on it while tracing
        raise UnsupportedError("a model without degrees of freedom (nv = 0): MJX cannot step it "
                               "('Scan across Model with zero DoFs unsupported')")
    with _unsupported():
        mx0 = compat.put_model(models[0], impl)
    leaves0, treedef = jax.tree.flatten(mx0)
    distinct = list({id(mi): mi for mi in models}.values())
    index = {id(mi): i for i, mi in enumerate(distinct)}
    columns = _patched_columns(distinct, mx0, impl) if len(distinct) > 1 else {}
    if columns is None:  # put_model per distinct member, and compare every leaf
        per_member = [leaves0]
        for mi in distinct[1:]:
            leaves, td = jax.tree.flatten(compat.put_model(mi, impl))
            if td != treedef:
                first, this = _c_fields(distinct[0]), _c_fields(mi)
                leaves = {jax.tree_util.keystr(p).lstrip(".") for p, _ in jax.tree_util.tree_flatten_with_path(mx0)[0]}
                names = sorted(k for k, v in first.items() if v.tobytes() != this[k].tobytes() and k not in leaves)
                raise ValueError(f"batch members differ in {', '.join(names)}, which MJX compiles into the rollout "
                                 "(static): draw it once per scenario (in the model), not per member")
            per_member.append([np.asarray(x) for x in leaves])
        columns = {k: [np.asarray(col[k]) for col in per_member] for k in range(len(leaves0))
                   if any(not np.array_equal(col[k], per_member[0][k]) for col in per_member[1:])}
    varying = tuple(k in columns for k in range(len(leaves0)))
    stacked = [jnp.asarray(np.stack([columns[k][index[id(mi)]] for mi in models])) if k in columns else leaf
               for k, leaf in enumerate(leaves0)]  # numpy: jnp.stack compiles once per leaf shape
    return jax.tree.unflatten(treedef, stacked), varying
