"""The engines behind one interface: MuJoCo C and MJX, batched.

Both take the same :class:`~mjxdiff.input.inputs.BatchedInputs` and return a
:class:`Trajectory` with the same fields and shapes. Recording follows
``mj_step``: after step k, ``qpos``/``qvel``/``act``/``time`` are the new
state, while ``sensordata`` and ``ncon`` were computed from the state before
the step (both engines evaluate them in the forward pass that precedes
integration).

* :class:`CEngine` steps every member on all cores with :class:`mujoco.batch.Batch`
  (:mod:`mjxdiff.engine.c`).
* :class:`MJXEngine` runs ``jit(vmap(scan(mjx.step)))``. Each member's model is
  ``mjx.put_model`` of its own C model; model leaves that differ between
  members are batched inputs (``vmap`` axis 0), the rest are shared
  (:func:`put_models`, :mod:`mjxdiff.engine.models`). One
  compiled function therefore serves every randomized variant of a model
  structure: it is cached by JAX on (structure, which leaves vary, B, T), and
  across processes as a ``jax.export`` artifact (:mod:`mjxdiff.engine.export_cache`).
  Large batches are split across the host CPU devices (``shard_map``; XLA CPU
  runs one device per thread): one per core after :func:`configure_jax`, which
  the CLI calls (see :class:`MJXEngine`; XLA's configuration and compile counters are
  :mod:`mjxdiff.engine.xla`).

This module holds MJX's engines and the functions their rollouts trace, and re-exports the
public names of the others (:class:`CEngine`, :class:`UnsupportedError`, :func:`put_models`,
:func:`configure_jax`, :func:`compile_count`, ...).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import threading
from typing import Any, Iterator

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

with contextlib.redirect_stdout(io.StringIO()):  # mjx prints "Failed to import warp" to stdout
    from mujoco import mjx
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402
from mjxdiff.compat import (BALANCED_COMPILE, FAST_COMPILE, Batch, data_impl, disable_bit,  # noqa: E402,F401
                            full_inertia, jit_for_few_calls)

from mjxdiff.input.precision import Precision  # noqa: E402
from mjxdiff.engine import export_cache, pairs, stages, xla  # noqa: E402
from mjxdiff.engine.c import CEngine  # noqa: E402
from mjxdiff.engine.digest import untraced  # noqa: E402
from mjxdiff.engine.models import UnsupportedError, _unsupported, put_models  # noqa: E402
from mjxdiff.engine.xla import (CORES, COMPILE_MODES, _ensure_safe_backend, _traced, compile_count,  # noqa: E402,F401
                                compile_seconds, configure_jax, device_count, xla_compiles)
from mjxdiff.input import joints  # noqa: E402
from mjxdiff.engine.stages import Forward  # noqa: E402
from mjxdiff.input.inputs import BatchedInputs  # noqa: E402
# Trajectory and Engine live in mjxdiff.trajectory (no MJX there); kept importable from here
from mjxdiff.engine.trajectory import Engine, Trajectory, concat, first_true, resync_blocks, shifted  # noqa: E402

__all__ = [
    "CEngine",
    "Engine",
    "MJXEngine",
    "MJXWarpEngine",
    "Trajectory",
    "UnsupportedError",
    "compile_count",
    "compile_seconds",
    "concat",
    "configure_jax",
    "device_count",
    "overflow_names",
    "put_models",
    "warp_capacity",
]


def clear_compiled() -> None:
    """Forgets compiled MJX rollouts, so the next rollout re-traces MJX's (possibly patched) Python code."""
    export_cache.clear()
    # jax's JitWrapped protocol leaves out the clear_cache every jitted function has
    _rollout.clear_cache()  # pyright: ignore[reportAttributeAccessIssue]
    _resync_rollout.clear_cache()  # pyright: ignore[reportAttributeAccessIssue]
    forward.clear_cache()  # pyright: ignore[reportAttributeAccessIssue]


def _contacts(mx: mjx.Model, dx: mjx.Data, world: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
    """(C's ``d.ncon``, (2,) uint32 pair sums :mod:`mjxdiff.engine.pairs`) from MJX's contacts;
    no sums (None) where the model has no contact to sum: a constant output left out, so that
    the compiled step of a model without contacts is what it was without them (XLA fuses a
    loop with one more output otherwise, and pieces of different lengths then round apart).

    ``d.ncon`` counts those with ``dist < includemargin + gap`` (:func:`mjxdiff.engine.stages.contact_gap`;
    C keeps a gap's inactive contacts, MJX does not). Under MJX's warp implementation, MuJoCo
    Warp's active contacts of world ``world`` (the member's index in the batch): its contact
    buffer holds every world's, each tagged, with ``includemargin = margin - gap`` as C's."""
    impl = data_impl(dx)  # MJX's contacts
    if world is not None:
        dist = impl.contact__dist  # pyright: ignore[reportAttributeAccessIssue] - the warp implementation's Data
        active = jnp.arange(dist.shape[0]) < jnp.asarray(impl.nacon).reshape(-1)[0]
        active &= impl.contact__worldid == world  # pyright: ignore[reportAttributeAccessIssue]
        key = pairs.keys(impl.contact__geom, impl.contact__flex, jnp)  # pyright: ignore[reportAttributeAccessIssue]
        margin = impl.contact__includemargin  # pyright: ignore[reportAttributeAccessIssue]
        return jnp.sum(active).astype(jnp.int32), pairs.sums(mx, key, dist, margin, active, jnp)
    c = impl.contact  # pyright: ignore[reportAttributeAccessIssue] - the JAX implementation's Data
    if c.dist.shape[0] == 0:
        return jnp.zeros((), jnp.int32), None
    geom = jnp.stack([c.geom1, c.geom2], -1)
    gap = stages.contact_gap(mx, geom, jnp)
    sums = pairs.sums(mx, geom, c.dist, c.includemargin, xp=jnp)
    return jnp.sum(c.dist < c.includemargin + gap), sums


def energy(mx: mjx.Model, dx: mjx.Data, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
    """(2,) potential and kinetic energy, J, as C's ``mj_energyPos``/``mj_energyVel``.

    ``dx`` holds kinematics (``xipos``, ``qM``) of the state (``qpos``, ``qvel``):

      potential = -sum_b mass_b (gravity . xipos_b) + sum_j k_j |q_j - q_spring_j|^2 / 2
                  + sum_t k_t dist(len_t, [lower_t, upper_t])^2 / 2
      kinetic   = qvel^T M qvel / 2

    Quaternion springs use the rotation vector ``quat_sub(q, q_spring)``.
    """
    from mujoco.mjx._src import math as mjx_math
    from mujoco.mjx._src import support

    pot = jnp.zeros((), qpos.dtype)
    disabled = int(mx.opt.disableflags)
    if not disabled & int(mujoco.mjtDisableBit.mjDSBL_GRAVITY):
        pot -= jnp.sum(mx.body_mass * (dx.xipos @ mx.opt.gravity))
    if not disabled & disable_bit("spring"):
        for p in joints.parts(mx):
            if p.kind == "rotation":
                dif = mjx_math.quat_sub(mjx_math.normalize(qpos[p.qpos]), mx.qpos_spring[p.qpos])
            else:
                dif = qpos[p.qpos] - mx.qpos_spring[p.qpos]
            pot += 0.5 * mx.jnt_stiffness[p.joint] * dif @ dif
        if mx.ntendon:
            lower, upper = mx.tendon_lengthspring.T
            length = dx.ten_length
            stretch = jnp.where(length < lower, lower - length, jnp.where(length > upper, length - upper, 0.0))
            pot += 0.5 * jnp.sum(mx.tendon_stiffness * stretch ** 2)
    kin = 0.5 * qvel @ support.mul_m(mx, dx, qvel)
    return jnp.stack([pot, kin])


def _scan_steps(mx, dx, ctrl, with_energy, n=None, world=None):
    """One member: ``mjx.step`` over ``ctrl`` (T, nu) from ``dx``; returns (last dx, (T, ...) records).

    With ``n`` (a traced integer, at most T), only the first ``n`` steps are taken (a loop with
    a run-time trip count: ``mjx.step`` is traced once, and steps past ``n`` cost nothing; their
    records are zeros), so one compiled piece of T steps serves every horizon up to T: the
    one-step check runs the sweep's own rollout with ``n = 1``."""
    def record(dx, energy_):
        ncon, pair_sums = _contacts(mx, dx, world)
        rec = dict(qpos=dx.qpos, qvel=dx.qvel, act=dx.act, sensordata=dx.sensordata, time=dx.time, ncon=ncon)
        if pair_sums is not None:
            rec["pairs"] = pair_sums
        if with_energy:
            rec["energy"] = energy_
        if world is not None:  # MJX's warp implementation: the buffers it overflowed so far, a bitmask
            rec["overflow"] = jnp.asarray(data_impl(dx).overflow).reshape(-1)[0]  # pyright: ignore[reportAttributeAccessIssue]
        return rec

    def step(dx, u):
        qpos_before, qvel_before = dx.qpos, dx.qvel
        dx = mjx.step(mx, dx.replace(ctrl=u))
        # dx's kinematics are those of the state before the step
        return dx, record(dx, energy(mx, dx, qpos_before, qvel_before) if with_energy else None)

    if n is None:
        return jax.lax.scan(step, dx, ctrl)

    def body(i, carry):
        dx, records = carry
        dx, rec = step(dx, ctrl[i])
        return dx, jax.tree.map(lambda buffer, x: buffer.at[i].set(x), records, rec)

    empty = jax.tree.map(lambda x: jnp.zeros((ctrl.shape[0], *jnp.shape(x)), jnp.result_type(x)),
                         record(dx, jnp.zeros(2, dx.qpos.dtype)))
    return jax.lax.fori_loop(0, n, body, (dx, empty))


def _per_leaf(mx, varying, if_varying, if_shared):
    """A tree shaped like ``mx`` holding ``if_varying`` at stacked leaves, ``if_shared`` elsewhere."""
    return jax.tree.unflatten(jax.tree.structure(mx), [if_varying if v else if_shared for v in varying])


def _model_axes(mx, varying):
    return _per_leaf(mx, varying, 0, None)


def _split(fn, mesh: Mesh | None, mx, varying, batched: tuple[bool, ...]):
    """``fn(mx, *args)`` with its batch axis split over ``mesh``'s devices.

    Each device runs ``fn`` on its slice (``shard_map``): stacked model leaves
    and the arguments marked in ``batched`` are split, the rest replicated.
    """
    if mesh is None:
        return fn
    b, shared = PartitionSpec("batch"), PartitionSpec()
    return jax.shard_map(fn, mesh=mesh, in_specs=(_per_leaf(mx, varying, b, shared),) + tuple(
        b if split else shared for split in batched), out_specs=b, check_vma=False)


@functools.partial(jax.jit, static_argnames=("varying", "with_energy", "mesh", "shared"))
def _rollout(mx, dx, ctrl, n, varying, with_energy=False, mesh=None, shared=None):
    """B members stepped from their data ``dx`` (leaves (B, ...)) over ``ctrl`` (B, T, nu), the
    first ``n`` (an int32 scalar, at most T) steps of it (:func:`_scan_steps`):
    (last data, (B, T, ...) records). ``shared`` (MJX's warp implementation, :func:`_warp_shared`):
    per leaf of ``dx``, whether it is one for all members (MuJoCo Warp's buffers of every world)."""
    _traced()  # runs only while tracing
    if shared is not None:
        return _warp_rollout(mx, dx, ctrl, n, varying, with_energy, shared)

    def batch(mx, dx, ctrl, n):
        def member(mx, dx, ctrl, n):
            return _scan_steps(mx, dx, ctrl, with_energy, n)
        return jax.vmap(member, in_axes=(_model_axes(mx, varying), 0, 0, None))(mx, dx, ctrl, n)

    return _split(batch, mesh, mx, varying, (True, True, False))(mx, dx, ctrl, n)


def _warp_rollout(mx, dx, ctrl, n, varying, with_energy, shared):
    """:func:`_rollout` under MJX's warp implementation: buffers shared by the worlds go in
    unbatched and come out as one (the batched copies MJX's FFI returns are equal)."""
    leaves, treedef = jax.tree.flatten(dx)  # as a list: per-leaf axes of a Data tree are not a prefix vmap takes

    def member(mx, leaves, ctrl, world):
        return _scan_steps(mx, jax.tree.unflatten(treedef, leaves), ctrl, with_energy, n, world)
    out, rec = jax.vmap(member, in_axes=(_model_axes(mx, varying), [None if s else 0 for s in shared], 0, 0))(
        mx, leaves, ctrl, jnp.arange(ctrl.shape[0]))
    out = jax.tree.unflatten(jax.tree.structure(out), [
        x[0] if s and x.shape[1:] == leaf.shape else x for x, s, leaf in zip(jax.tree.leaves(out), shared, leaves)])
    return out, rec


def _warp_shared(dx: mjx.Data) -> tuple[bool, ...]:
    """Per leaf of a warp-implementation ``dx``: whether MJX's FFI takes it unbatched (a buffer
    of every world, or an index), from MJX's own tables (``mujoco.mjx.warp.types``)."""
    from mujoco.mjx.warp import ffi, types as warp_types

    out = []
    for path, _ in jax.tree_util.tree_flatten_with_path(dx)[0]:
        ndim = ffi._get_mapping_from_tree_path(path, warp_types._NDIM["Data"])  # noqa: SLF001
        batched = ffi._get_mapping_from_tree_path(path, warp_types._BATCH_DIM["Data"])  # pyright: ignore[reportArgumentType]  # noqa: SLF001, E501
        out.append(ndim is not None and ndim >= 0 and not batched)
    return tuple(out)


@functools.partial(jax.jit, static_argnames=("varying", "mesh"))
def _resync_rollout(mx, dx0, qpos, qvel, act, time, ctrl, varying, mesh=None):
    """(B, S, k, ...) records of B members restarted from S given states, k steps each."""
    _traced()

    warp = hasattr(data_impl(dx0), "nacon")  # MJX's warp implementation: contacts counted per world

    def batch(mx, dx0, qpos, qvel, act, time, ctrl):
        def member(mx, q, v, a, t, u, world=None):
            # restarts one after another (scan), members side by side (vmap): the shape of
            # _rollout, rather than a (B x S)-wide nested vmap, which hung XLA CPU here
            def restart(_, start):
                q, v, a, t, u = start
                return None, _scan_steps(mx, dx0.replace(qpos=q, qvel=v, act=a, time=t), u, False, world=world)[1]
            return jax.lax.scan(restart, None, (q, v, a, t, u))[1]

        if warp:
            return jax.vmap(member, in_axes=(_model_axes(mx, varying), 0, 0, 0, 0, 0, 0))(
                mx, qpos, qvel, act, time, ctrl, jnp.arange(qpos.shape[0]))
        return jax.vmap(member, in_axes=(_model_axes(mx, varying), 0, 0, 0, 0, 0))(mx, qpos, qvel, act, time, ctrl)

    return _split(batch, mesh, mx, varying, (False,) + (True,) * 5)(mx, dx0, qpos, qvel, act, time, ctrl)


def _canonical_ints(dx: mjx.Data) -> mjx.Data:
    # make_data gives some int32 leaves that mjx.step returns as int64 under x64;
    # scan needs the carry's dtypes fixed.
    int_t = jnp.asarray(0).dtype
    return jax.tree.map(lambda x: x.astype(int_t) if jnp.issubdtype(x.dtype, jnp.integer) else x, dx)


_LAST_CHOICE = untraced(threading.local())  # per thread: never part of a code digest
_HELD = untraced(threading.local())  # per thread: MJXEngine.holding's pieces


def last_choice() -> dict | None:
    """What :func:`~mjxdiff.engine.xla.xla_options` chose for the last stream this thread started (None if not
    compiled here)."""
    return getattr(_LAST_CHOICE, "value", None)


#: ``mjx.forward``, compiled to run once per state: every stage of one state, for the drill-down.
forward = jit_for_few_calls(mjx.forward)


def _pad(x: np.ndarray, n: int) -> np.ndarray:
    """``x`` with its last row repeated ``n`` more times along axis 0."""
    return np.concatenate([x, np.repeat(x[-1:], n, axis=0)]) if n else x


#: A batch is split automatically only if every device gets at least this many members
#: (measured, 2 cores, 200 steps: ant and humanoid 1.1-1.3x at 16 per device and 2.8-4.3x
#: at 32; below 16 per device the split's overhead can cost more than it brings).
SPLIT_MIN_MEMBERS = 16
#: Members per device a sweep steps at once (see :meth:`MJXEngine.batch_cap`): ant and
#: humanoid ran 2.5-4x more steps/s per device at 32 members than at 64.
MEMBERS_PER_DEVICE = 32


class MJXEngine:
    """MJX: ``jit(vmap(scan(mjx.step)))`` with per-member model parameters batched.

    Args:
      devices: host CPU devices to split the batch over. None (default):
        every device (:func:`device_count`, one per core unless
        ``MJXDIFF_DEVICES`` says otherwise) when each gets at least
        :data:`SPLIT_MIN_MEMBERS` members, else one. N: exactly N (at most
        the batch and the devices there are); 1: never split. A batch that
        does not divide evenly is padded with copies of its last member,
        whose records are dropped.
      compile: how hard XLA optimises a rollout (:func:`~mjxdiff.engine.xla.xla_options`): ``auto``
        chooses from the expected stepping work, ``fast`` always compiles quickly,
        ``optimized`` always uses XLA's defaults.
    """

    name = "mjx"
    capabilities: frozenset[str] = frozenset({"estimate", "transfer"})

    @property
    def precision(self) -> Precision:
        """MJX's precision follows JAX's: float64 under ``jax_enable_x64`` (:func:`configure_jax`)."""
        return "float64" if jax.config.read("jax_enable_x64") else "float32"

    def forward(self, m: mujoco.MjModel, d: mujoco.MjData, fields: tuple[str, ...]) -> Forward:
        """``mjx.forward`` from C's ``d`` (put with ``put_model``/``put_data``), read back.

        Compiled once per model structure and code, fast (:data:`FAST_COMPILE`), and cached like
        a rollout (:func:`export_cache.bind`: keyed on the code it traces, loaded by later runs),
        but not counted among the rollouts a run loaded or traced."""
        mx, dx = mjx.put_model(m), mjx.put_data(m, d)
        options = xla.xla_options("fast", 1)
        dx = export_cache.bind(mjx.forward, (mx, dx), {}, options, ("fast", 1), counted=False)(mx, dx)
        return Forward({f: np.asarray(getattr(dx, f)).ravel() for f in fields}, np.asarray(mjx.full_m(mx, dx)),
                       stages.contacts_mjx(m, dx))

    #: MJX's implementation (``mjx.put_model(m, impl=...)``): its JAX one.
    impl = "jax"

    def _shared(self, dx0) -> tuple[bool, ...] | None:
        """Per leaf of the data, whether the members share it (None: none do)."""
        return None

    def _make_data(self, inputs: BatchedInputs) -> mjx.Data:
        """One member's initial data, the scan carry's dtypes fixed."""
        return _canonical_ints(mjx.make_data(inputs.models[0]))

    def _bind(self, fn, args: tuple, static: dict[str, Any], steps: int):
        """``fn`` compiled for ``args`` (:func:`export_cache.bind`: keyed on the code it traces,
        saved for later runs), XLA's options chosen for ``steps`` steps of stepping."""
        return export_cache.bind(fn, args, static, xla.xla_options(self.compile, steps), (self.compile, steps))

    def __init__(self, devices: int | None = None, compile: str = "auto"):
        _ensure_safe_backend()
        if compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, not {compile!r}")
        self.devices, self.compile = devices, compile

    def _usable_devices(self) -> int:
        return device_count() if self.devices is None else max(1, min(self.devices, device_count()))

    def split(self, batch: int) -> int:
        """How many devices a batch of ``batch`` members is split over."""
        n = self._usable_devices()
        if self.devices is None:
            return n if batch >= n * SPLIT_MIN_MEMBERS else 1
        return min(n, batch)

    def batch_cap(self) -> int:
        """Members a sweep should give this engine at once: :data:`MEMBERS_PER_DEVICE` per device it can use."""
        return MEMBERS_PER_DEVICE * self._usable_devices()

    def _mesh(self, batch: int) -> Mesh | None:
        n = self.split(batch)
        return Mesh(np.array(jax.devices("cpu")[:n]), ("batch",)) if n > 1 else None

    def _prepare(self, inputs: BatchedInputs):
        """Model, initial data and a placer for batched arrays: (mx, varying, dx0, place, mesh).

        ``place(tree)`` pads every array of ``tree`` along its batch axis to the
        split and puts it on the devices (one transfer for the whole tree);
        ``mx`` is already placed, ``dx0`` (one member's data) is not: the
        stream batches it on the host, only resync needs it on the devices.
        """
        mesh = self._mesh(inputs.batch)
        pad = -inputs.batch % mesh.size if mesh else 0
        mx, varying = put_models(inputs.models + (inputs.models[-1],) * pad, self.impl)
        dx0 = self._make_data(inputs)
        if mesh is None:
            # committed, as _rollout's outputs are: the next piece's call then hits the same compiled function
            device = jax.devices("cpu")[0]
            return mx, varying, dx0, lambda tree: jax.device_put(jax.tree.map(np.asarray, tree), device), None
        split, shared = NamedSharding(mesh, PartitionSpec("batch")), NamedSharding(mesh, PartitionSpec())
        mx = jax.device_put(mx, _per_leaf(mx, varying, split, shared))

        def place(tree):
            leaves, treedef = jax.tree.flatten(jax.tree.map(
                lambda x: _pad(np.asarray(x), pad) if np.ndim(x) else np.asarray(x), tree))
            # empty arrays come back from shard_map replicated: give them that sharding from the start,
            # or the next piece's call would lower and compile _rollout again
            placed = jax.device_put(leaves, [split if x.size and x.ndim else shared for x in leaves])
            return jax.tree.unflatten(treedef, placed)

        return mx, varying, dx0, place, mesh

    def rollout(self, inputs: BatchedInputs) -> Trajectory:
        return concat(list(self.stream(inputs, inputs.steps)))

    @contextlib.contextmanager
    def holding(self):
        """Within the block, this thread's calls for the same models (the same objects), batch,
        horizon and piece length share one prepared, compiled piece: the models put on the devices
        once, the code digested and the function bound once (~0.5 s a call saved on a warm sweep).
        A sweep holds one per scenario, where nothing changes the code between its calls; a call
        outside any block binds afresh (:func:`~mjxdiff.engine.trace_deps.fresh_digest`)."""
        outer = getattr(_HELD, "pieces", None)
        _HELD.pieces = {}
        try:
            yield
        finally:
            _HELD.pieces = outer

    def _bound(self, inputs: BatchedInputs, chunk: int):
        """The compiled piece function of :meth:`stream`, its first arguments, the placer and the
        padded controls: (run, (mx, dx, ctrl piece, steps), place, ctrl)."""
        t = export_cache.clock()
        # every piece runs the compiled function: the work it will do, over the planned horizon (a
        # quick run's XLA options are the full run's: one executable serves both)
        T = -(-max(inputs.steps, inputs.horizon or 0) // chunk) * chunk
        held = getattr(_HELD, "pieces", None)
        # this thread's precision too: a float32 sweep's float64 ablation steps the same model objects
        key = (id(self), tuple(map(id, inputs.models)), inputs.batch, chunk, T, inputs.energy,
               jax.dtypes.canonicalize_dtype(np.float64))
        if held is not None and key in held:
            _, run, prepared = held[key]
            (_, args, _), place, ctrl = self.piece(inputs, chunk, prepared)
        else:
            prepared = self._prepare(inputs)
            (fn, args, static), place, ctrl = self.piece(inputs, chunk, prepared)
            run = self._bind(fn, args, static, T)
            if held is not None:
                held[key] = inputs.models, run, prepared  # the models kept: their ids stay theirs
        # the model and state put on the devices, the code and key digested: a compile phase, not stepping
        spent = export_cache.clock() - t
        export_cache.count("seconds", spent)
        export_cache.count("prepare", spent)
        return run, args, place, ctrl

    def piece(self, inputs: BatchedInputs, chunk: int, prepared: tuple | None = None):
        """What :meth:`stream` compiles, uncompiled: ((function, its first arguments, its static
        arguments), the placer, the padded controls); :func:`export_cache.audit` takes the first.
        ``prepared``: :meth:`_prepare` of these models, when already done."""
        B, T = inputs.batch, inputs.steps
        mx, varying, dx0, place, mesh = prepared or self._prepare(inputs)
        dtype = dx0.qpos.dtype
        state = dict(qpos=inputs.qpos, qvel=inputs.qvel, act=inputs.act)
        shared = self._shared(dx0)
        host = jax.device_get(dx0)
        dx = jax.tree.unflatten(jax.tree.structure(host), [
            np.asarray(x) if s else np.broadcast_to(np.asarray(x), (B, *np.shape(x)))
            for x, s in zip(jax.tree.leaves(host), shared or [False] * len(jax.tree.leaves(host)))])
        dx = place(dx.replace(**{k: np.asarray(v, dtype) for k, v in state.items()}))
        ctrl = np.zeros((B, -(-T // chunk) * chunk, inputs.ctrl.shape[2]), dtype)
        ctrl[:, :T] = inputs.ctrl
        args = (mx, dx, *place((ctrl[:, :chunk], np.int32(min(chunk, T)))))
        static = dict(varying=varying, with_energy=inputs.energy, mesh=mesh)
        if shared is not None:
            static["shared"] = shared
        return (_rollout, args, static), place, ctrl

    def compile_ahead(self, inputs: BatchedInputs, chunk: int) -> None:
        """Compiles what :meth:`stream` of ``inputs`` in pieces of ``chunk`` steps will run, so
        that the stream starts at once; safe from another thread. Best effort: any problem
        (an unsupported feature) is left for :meth:`stream` to raise and report."""
        with contextlib.suppress(Exception), _unsupported():
            self._bound(inputs, chunk)

    def first_piece(self, inputs: BatchedInputs, chunk: int, steps: int | None = None) -> Trajectory:
        """The first ``steps`` (default and at most ``min(chunk, inputs.steps)``) steps of
        :meth:`stream` of ``inputs``, and nothing after: the compiled function of a stream of the
        same batch, horizon and piece length (a sweep's own rollout), so it costs those steps'
        stepping, never a compile."""
        steps = min(chunk, inputs.steps, steps or chunk)
        with _unsupported():
            run, (mx, dx, ctrl, _), place, _ = self._bound(inputs, chunk)
            _, rec = run(mx, dx, ctrl, place(np.int32(steps)))
        return _host_piece(rec, inputs.batch, steps)

    def stream(self, inputs: BatchedInputs, chunk: int) -> Iterator[Trajectory]:
        """The rollout in consecutive pieces of ``chunk`` steps (the last may be shorter).

        Each piece continues from the full MJX data the previous one ended in
        (solver warm start included), so the pieces concatenate to
        :meth:`rollout`'s result bit for bit; only one piece of records is
        held at a time. Every piece runs the same compiled function: the last
        one is padded with zero controls, steps only up to the horizon
        (:func:`_scan_steps`' ``n``) and its extra records are dropped.

        This call prepares the model and data and dispatches the first piece
        (so errors of preparation, e.g. :class:`UnsupportedError`, are raised
        here); the iterator it returns dispatches piece k+1 before handing
        piece k over, so MJX keeps stepping while the caller works.
        """
        B, T = inputs.batch, inputs.steps
        with _unsupported():  # make_data and tracing mjx.step raise it for some features too
            run, args, place, ctrl = self._bound(inputs, chunk)
            mx = args[0]
            _LAST_CHOICE.value = run.choice if isinstance(run, export_cache.Bound) else None
            first = run(*args)

        def piece(rec, start):
            p = _host_piece(rec, B, min(chunk, T - start))
            return dataclasses.replace(p, diverged_at=shifted(p.diverged_at, start))

        def pieces(dx, rec):
            for start in range(chunk, T, chunk):
                with _unsupported():  # dispatched, not awaited: it runs while the caller handles the last piece
                    dx, following = run(mx, dx, *place((ctrl[:, start:start + chunk], np.int32(min(chunk, T - start)))))
                yield piece(rec, start - chunk)
                rec = following
            yield piece(rec, (T - 1) // chunk * chunk)

        return pieces(*first)

    def resync(self, inputs: BatchedInputs, reference: Trajectory, every: int = 1) -> Trajectory:
        """MJX re-synchronised to ``reference`` (C) every ``every`` steps.

        Record t is MJX's state after step t when restarted from the reference
        state after step ``every * floor(t / every) - 1`` (the initial state for
        the first block). Compared with the reference it gives the local error:
        at ``every=1`` the one-step error, which chaos cannot amplify.
        """
        B, T, k = inputs.batch, inputs.steps, every
        states, ctrl, starts = resync_blocks(inputs, reference, every)
        S = len(starts)
        batched = (states["qpos"], states["qvel"], states["act"], states["time"], ctrl)
        with _unsupported():
            mx, varying, dx0, place, mesh = self._prepare(inputs)
            arrays = place(tuple(np.asarray(x, dx0.qpos.dtype) for x in batched))
            if mesh is not None:
                dx0 = jax.device_put(dx0, NamedSharding(mesh, PartitionSpec()))
            rec = self._bind(_resync_rollout, (mx, dx0, *arrays), dict(varying=varying, mesh=mesh), S * k)(
                mx, dx0, *arrays)
        rec = {key: np.asarray(v)[:B].reshape(B, S * k, *v.shape[3:])[:, :T] for key, v in rec.items()}
        return _trajectory(rec, B, T)


class MJXWarpEngine(MJXEngine):
    """MJX's warp implementation: ``mjx.put_model(m, impl='warp')`` stepped by ``jit(vmap(scan(mjx.step)))``,
    the rollout :class:`MJXEngine` compiles, so the code an MJX user selects with ``impl='warp'``
    (MJX's vendored MuJoCo Warp, ``mujoco/mjx/third_party/mujoco_warp``, through JAX's FFI, float32
    whatever JAX's precision) is what is compared with C. Differs from :class:`MJXEngine` in:
    one device (Warp's kernels batch the members themselves), compiled with ``jax.jit`` alone (its
    kernels run through FFI handlers registered by this process, which no saved artifact may
    outlive: nothing is saved, and the vendored Warp code is read at run time), the buffers Warp
    keeps for all worlds passed unbatched (:func:`_warp_shared`), contacts counted per world from
    Warp's buffer (:func:`_contacts`), and the drill-down's mass matrix and contacts read
    from the implementation's buffers rather than ``mjx.get_data`` (see :meth:`forward`).
    Kernels compile on first use into Warp's cache (``~/.cache/warp``; pendulum 17 s cold here)."""

    name = "mjx.warp"
    impl = "warp"
    capabilities: frozenset[str] = frozenset()

    @property
    def precision(self) -> Precision:
        return "float32"

    def __init__(self, devices: int | None = None, compile: str = "auto"):
        super().__init__(devices=1, compile=compile)

    def _bind(self, fn, args: tuple, static: dict[str, Any], steps: int):
        return functools.partial(fn, **static)

    def _shared(self, dx0) -> tuple[bool, ...] | None:
        return _warp_shared(dx0)

    def _make_data(self, inputs: BatchedInputs) -> mjx.Data:
        """Warp's data, its int32 kept (its kernels take them so), its contact and constraint
        buffers sized from C's own run of the members (:func:`warp_capacity`: 2x C's
        most contacts + 8; MuJoCo Warp drops what does not fit), contacts for all the worlds."""
        from mujoco.mjx.third_party.mujoco_warp._src import io

        nconmax, njmax = warp_capacity(inputs, io)
        return mjx.make_data(inputs.models[0], impl="warp", naconmax=nconmax * inputs.batch, njmax=njmax)

    def forward(self, m: mujoco.MjModel, d: mujoco.MjData, fields: tuple[str, ...]) -> Forward:
        """``mjx.forward`` of the warp implementation from C's ``d``, read back with ``mjx.get_data``,
        but for the mass matrix and the contacts, which it gets wrong (:func:`stages.contacts_mjx_warp`)."""
        with _unsupported():
            mx, dx = mjx.put_model(m, impl="warp"), mjx.put_data(m, d, impl="warp")
            dx = _forward_once(mx, dx)
            read = mjx.get_data(m, dx)
            out = stages.read(m, read, fields)
        # get_data leaves the mass matrix at zero: the implementation's own M, in C's sparse layout
        # (mjx.full_m returns it as it is), made dense as C's is
        M = np.asarray(data_impl(dx).M).ravel()  # pyright: ignore[reportAttributeAccessIssue]
        if M.size == m.nv * m.nv:
            qM = M.reshape(m.nv, m.nv)
        else:
            read.M[:] = M  # pyright: ignore[reportAttributeAccessIssue] - one MjData: get_data of unbatched data
            qM = full_inertia(m, read)
        return dataclasses.replace(out, qM=qM, contacts=stages.contacts_mjx_warp(m, dx))


_forward_once = jax.jit(mjx.forward)


def warp_capacity(inputs: BatchedInputs, io) -> tuple[int, int]:
    """(nconmax, njmax) per world for these inputs: MJWarp's defaults, or more where C's own run
    of the same members needs it (most contacts of any member at any step, x 2, + 8, as MuJoCo's
    parity method sizes them; rows: that many contacts at the model's widest friction cone plus
    every other constraint row C had). MJWarp drops contacts and rows beyond its capacity, which
    would read as a divergence. ``io``: the MuJoCo Warp whose defaults are the least (the installed
    ``mujoco_warp._src.io``, or MJX's vendored copy)."""
    m, B = inputs.models[0], inputs.batch
    b = Batch(m, B)
    b.set_models(list(inputs.models))
    b.qpos[:], b.qvel[:] = inputs.qpos, inputs.qvel
    if m.na:
        b.act[:] = inputs.act
    try:
        out = b.rollout(inputs.steps, control=inputs.ctrl, record=("ncon", "nefc"))
        ncon, nefc = int(np.max(out["ncon"], initial=0)), int(np.max(out["nefc"], initial=0))
    except Exception:  # noqa: BLE001 - C unstable here: the defaults, checked at every step anyway
        ncon = nefc = 0
    dims = np.concatenate([m.geom_condim, m.pair_dim]) if m.npair else m.geom_condim
    condim = int(dims.max(initial=1))
    rows = condim if m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC else max(2 * (condim - 1), 1)
    nconmax = max(io._default_nconmax(m), 2 * ncon + 8)  # noqa: SLF001
    njmax = max(io._default_njmax(m), nefc + (nconmax - ncon) * rows + 8)  # noqa: SLF001
    return nconmax, njmax


def _host_piece(rec, batch: int, steps: int) -> Trajectory:
    """A piece's device records, waited for, on the host: the first ``batch`` members (the rest
    pad the batch to the devices) and ``steps`` steps (the rest pad the last piece)."""
    rec = jax.tree.map(lambda x: np.asarray(x)[:batch, :steps], jax.block_until_ready(rec))
    return _trajectory(rec, batch, steps)


def overflow_names(bits, overflow_type) -> str | None:
    """The buffers a MuJoCo Warp ``overflow`` bitmask (any shape, OR-ed) names, as
    ``overflow_type``'s member names (``"NEFC, NARROWPHASE"``; that enum's ``str`` is the bare
    number); the solver's iteration limits left out (those are the verdict's to see); None for none."""
    solver = int(overflow_type.ITERATIONS) | int(overflow_type.LS_ITERATIONS)
    found = int(np.bitwise_or.reduce(np.asarray(bits, np.int64).ravel(), initial=0)) & ~solver
    return ", ".join(str(t.name) for t in overflow_type if found & int(t)) if found else None


def _warp_overflow(bits: np.ndarray) -> str | None:
    """:func:`overflow_names` of MJX's warp implementation's recorded bitmasks (its vendored MuJoCo Warp)."""
    from mujoco.mjx.third_party.mujoco_warp import OverflowType

    return overflow_names(bits, OverflowType)


def _trajectory(rec: dict[str, np.ndarray], batch: int, steps: int) -> Trajectory:
    """A Trajectory from (batch, steps, ...) MJX records, with non-finite states located; raises
    where MJX's warp implementation overflowed its buffers (its results are then not the model's:
    an engine error, never a divergence)."""
    overflow = _warp_overflow(rec["overflow"]) if "overflow" in rec else None
    if overflow is not None:
        raise RuntimeError(f"MJX's warp implementation overflowed its buffers ({overflow}): its results are not "
                           "the model's; sized at 2x C's peak contacts and rows (MuJoCo's parity method), they "
                           "held too few here")
    nonfinite = ~np.isfinite(rec["qpos"]).all(-1) | ~np.isfinite(rec["qvel"]).all(-1)
    return Trajectory(qpos=rec["qpos"], qvel=rec["qvel"], act=rec["act"],
                      sensordata=rec["sensordata"], time=rec["time"], ncon=rec["ncon"].astype(np.int64),
                      pairs=rec.get("pairs", np.zeros((batch, steps, 2), np.uint32)),
                      energy=rec.get("energy", np.zeros((batch, steps, 0))),
                      # numpy's stubs type .all(axis) as maybe a scalar
                      diverged_at=first_true(nonfinite))  # pyright: ignore[reportArgumentType]
