"""Every difference between the MuJoCo / MJX / JAX releases mjxdiff supports, in one place.

mjxdiff runs on MuJoCo and MJX 3.3.0 through 4.0.0 (MJX always the release of its MuJoCo) and
the JAX those releases accept (:data:`SUPPORTED`). Where a release lacks something mjxdiff
uses, or names it differently, this module gives one name for it; nothing else in the package
branches on versions:

* :func:`mjx_lacks`: the public MJX functions of a list that this MJX does not have
  (``get_state``, ``set_state`` and ``state_size`` arrived after 3.3).
* :func:`full_inertia`: ``mj_fullM`` takes ``(m, d, dst)`` from MuJoCo 3.4 (or so), ``(m, dst,
  d.qM)`` before.
* :func:`disable_bit`: MuJoCo 3.3 disables springs and dampers together (``mjDSBL_PASSIVE``);
  later releases apart (``mjDSBL_SPRING``, ``mjDSBL_DAMPER``).
* :func:`sensor_types`: the sensor types of a list this MuJoCo has (``mjSENS_CONTACT``,
  ``mjSENS_INSIDESITE`` arrived in 3.3.x).
* :func:`enable_x64`: the thread-local ``jax_enable_x64`` context is ``jax.enable_x64`` from
  JAX 0.8 (or so), ``jax.experimental.enable_x64`` before.
* :func:`data_impl`, :func:`with_impl`, :func:`impl_fields`: from MJX 3.3.x (3.3.5 has it,
  3.3.0 not) the JAX implementation's fields of ``Data`` (contacts, constraint rows, ``qM``)
  live in ``Data._impl`` (``types.DataJAX``); before, on ``Data`` itself.
* :func:`put_model`: ``mjx.put_model(m, impl=...)`` takes ``impl`` from MJX 3.3.x (or so);
  3.3.0 has only the JAX implementation and no such argument.
* :func:`later_feature`: a model that an older MuJoCo cannot compile because its XML uses
  something a later release added (``<flag spring=...>`` before 3.4) is ``unsupported`` there,
  not bad input: ``scenario.load_model`` raises ``LaterFeatureError`` with this text, so every
  command says so, and a sweep reports the scenario ``unsupported``.
* :func:`jaxlib_validated`, :func:`fast_compile_validated`: two things mjxdiff does for speed
  are used only where they were validated: the persistent caches on the jaxlib releases of
  :data:`VALIDATED_JAXLIB`, the fast compile only there and with the MJX releases of
  :data:`VALIDATED_FAST_MJX`; elsewhere it compiles at XLA's level 1 and (other jaxlib) keeps
  no persistent caches. XLA's LLVM level 0 with classic emitters (the sweep's fast compile,
  :data:`FAST_COMPILE`, also :func:`jit_for_few_calls`) miscompiles MJX on jaxlib 0.7.2 (results that depend on
  which members share the batch) and MJX 3.10-3.15 on jaxlib 0.10.2 (contact rollouts leave
  their envelope with every forward stage agreeing), and a rollout loaded from the persistent
  caches on jaxlib 0.7.2 crashes the process (SIGSEGV in ``aot_cache_miss``).
* ``Batch``, ``SimulationError``: :class:`mujoco.batch.Batch` (MuJoCo 4.0) or, before it,
  :class:`LoopBatch`, the part of its interface mjxdiff uses as a loop over one ``MjData``
  per simulation (the same arithmetic: ``Batch`` is documented bit-identical to that loop).

:func:`check_versions` tells whether the installed set lies in the supported range.
"""

from __future__ import annotations

import copy
import functools
import re
from importlib import metadata
from typing import Any, Sequence

import mujoco
import numpy as np

__all__ = ["jaxlib_validated", "fast_compile_validated", "jit_for_few_calls", "FAST_COMPILE", "BALANCED_COMPILE",
           "later_feature", "enable_x64", "disable_bit", "sensor_types",
           "full_inertia", "put_model", "mjx_lacks", "data_impl", "with_impl", "impl_fields", "Batch", "LoopBatch",
           "SimulationError", "SUPPORTED", "JAX_CEILING", "REFERENCE", "VALIDATED_JAXLIB", "VALIDATED_FAST_MJX",
           "installed", "check_versions", "gate", "UntestedVersions", "HAS_BATCH", "matching_mujoco"]

#: The supported range, inclusive: distribution -> (oldest, newest).
SUPPORTED: dict[str, tuple[str, str]] = {
    "mujoco": ("3.3.0", "4.0.0"),
    "mujoco-mjx": ("3.3.0", "3.17.0"),
    "jax": ("0.6.0", "0.10.2"),
}
#: The newest JAX an MJX release runs on, where it is older than the range's: MJX 3.3 calls
#: ``jnp.clip(a_min=...)``, which JAX 0.10.0 removed (deprecated, still accepted, through 0.9.2:
#: read in each release's lax_numpy.py; "clip() got an unexpected keyword argument 'a_min'" under
#: 0.10.2). Measured: MJX 3.3.7 with JAX 0.9.2 sweeps pendulum, primitives_on_plane,
#: primitive_pairs and box_stack as with 0.7.0 (the same verdicts and catalogued divergences).
JAX_CEILING: dict[tuple[int, ...], str] = {(3, 3): "0.9.2"}
#: The reference set mjxdiff is developed on (constraints.txt pins it).
REFERENCE = {"mujoco": "4.0.0", "mujoco-mjx": "3.17.0", "jax": "0.10.2"}


def _release(version: str) -> tuple[int, ...]:
    """``3.3.5`` -> (3, 3, 5); pre-release and local parts dropped (``3.17.0.dev0`` -> (3, 17, 0))."""
    return tuple(int(p) for p in re.findall(r"\d+", version.split("+")[0])[:3])


@functools.cache
def _version(dist: str) -> str:
    """The installed version of ``dist``, or "not installed" (read once per process: the
    catalogue asks for MJX's at every match)."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def installed() -> dict[str, str]:
    """The installed versions of the distributions in :data:`SUPPORTED` ("not installed" where absent)."""
    return {dist: _version(dist) for dist in SUPPORTED}


class UntestedVersions(RuntimeError):
    """The installed MuJoCo, MJX or JAX lies outside :data:`SUPPORTED`."""


def check_versions(versions: dict[str, str] | None = None) -> None:
    """Raises :class:`UntestedVersions` naming every installed version outside :data:`SUPPORTED`,
    and an MJX that is not its MuJoCo's release (MJX 3.x.y goes with MuJoCo 3.x.y; MJX 3.17
    with MuJoCo 4.0)."""
    versions = versions or installed()
    problems = []
    for dist, (lo, hi) in SUPPORTED.items():
        v = versions.get(dist, "not installed")
        if v == "not installed" or not _release(lo) <= _release(v) <= _release(hi):
            problems.append(f"{dist} {v} (supported {lo} to {hi})")
    mj, mjx = versions.get("mujoco", ""), versions.get("mujoco-mjx", "")
    if not problems and _matching_mjx(mj) != _release(mjx)[:2]:
        problems.append(f"mujoco-mjx {mjx} is not the release of mujoco {mj}")
    ceiling = JAX_CEILING.get(_release(mjx)[:2]) if not problems else None
    if ceiling and _release(versions["jax"]) > _release(ceiling):
        problems.append(f"jax {versions['jax']} is newer than mujoco-mjx {mjx} runs on (at most {ceiling})")
    if problems:
        raise UntestedVersions("; ".join(problems))


def gate(allowed: bool = False) -> str | None:
    """Why the installed set may not run (None: it may): outside :data:`SUPPORTED` unless
    ``allowed`` (``--allow-untested-versions``) or ``$MJXDIFF_ALLOW_UNTESTED_VERSIONS`` is set;
    one line saying what to do."""
    import os

    if allowed or os.environ.get("MJXDIFF_ALLOW_UNTESTED_VERSIONS"):
        return None
    try:
        check_versions()
    except UntestedVersions as e:
        return (f"untested versions: {e}; install a supported set (pip install -c constraints.txt mjxdiff) or "
                "pass --allow-untested-versions to run anyway")
    return None


def matching_mujoco(mjx_release: tuple[int, ...]) -> tuple[int, ...]:
    """The MuJoCo release an MJX release ships with: the same up to 3.16; 4.0.x for 3.17.x."""
    return (4, 0, *mjx_release[2:]) if mjx_release[:2] == (3, 17) else mjx_release


def _matching_mjx(mujoco_version: str) -> tuple[int, ...]:
    """The MJX (major, minor) released with a MuJoCo: the same up to 3.x; 3.17 for 4.0."""
    r = _release(mujoco_version)[:2]
    return (3, 17) if r == (4, 0) else r


_SCHEMA = re.compile(r"Schema violation: unrecognized (attribute|element)|unrecognized (sensor|geom) type|"
                     r"invalid keyword|unknown (attribute|element)", re.IGNORECASE)


def later_feature(message: str, versions: dict[str, str] | None = None) -> str | None:
    """Why a compile error ``message`` of MuJoCo C is this MuJoCo being older than the reference
    (:data:`REFERENCE`), or None (the model is malformed): an XML schema violation (an
    unrecognized attribute, element or type) on a MuJoCo before the reference's."""
    v = (versions or installed())["mujoco"]
    if v == "not installed" or _release(v) >= _release(REFERENCE["mujoco"]) or not _SCHEMA.search(message):
        return None
    return f"MuJoCo {v} cannot compile this model, which uses something a later MuJoCo added: {message}"


#: jaxlib releases (major, minor) on which the fast compile was checked against XLA's defaults
#: and the persistent caches round-trip (tests/test_compile_options.py, tests/test_export_cache.py
#: and the suite on the reference set). Measured on jaxlib 0.7.2 with MJX 3.9.0: joint_parameters
#: (seed 0) member 3 comes out 7.5e-3 from C in qpos after one step when vmapped with members 0-7
#: or 2-3, 3e-17 alone, with 0-3 or 3-7, or at level 1; the second run of a sweep, loading the
#: first's rollout, dies of SIGSEGV (the first, and any run with --cache-dir "", pass).
VALIDATED_JAXLIB = ((0, 10),)
#: MJX releases (major, minor) the fast compile was validated with, on a :data:`VALIDATED_JAXLIB`
#: (the whole suite and the default sweep). Measured on jaxlib 0.10.2 with MJX 3.15.0: box_stack
#: (quick, seed 0) leaves its envelope at step 12 with "every forward stage agrees, the one-step
#: error does not: integration", primitives_on_plane at step 18 the same way; at XLA's default
#: level both pass (3.2e-8 and 2.5e-14 of their tolerances). MJX 3.10.0 to 3.14.0 showed the same
#: box_stack failure under the fast compile. Fail closed: any other MJX compiles at level 1.
VALIDATED_FAST_MJX = ((3, 17),)


def jaxlib_validated() -> bool:
    """Whether the installed jaxlib is one mjxdiff's fast compile and caches were validated on."""
    v = _version("jaxlib")
    return v != "not installed" and _release(v)[:2] in VALIDATED_JAXLIB


def fast_compile_validated() -> bool:
    """Whether the fast compile was validated with the installed jaxlib *and* MJX
    (:data:`VALIDATED_JAXLIB`, :data:`VALIDATED_FAST_MJX`)."""
    return jaxlib_validated() and _release(_version("mujoco-mjx"))[:2] in VALIDATED_FAST_MJX


#: XLA options of a rollout compiled for stepping: LLVM level 1 and XLA CPU's classic emitters
#: instead of its fusion emitters. Measured (2 cores, 8 members x 200 steps, against XLA's
#: defaults): compile 36-40% shorter (ant 5.7 -> 3.5 s, humanoid 10.0 -> 6.3, box_stack
#: 8.4 -> 5.9, primitive_pairs 11.6 -> 7.0), stepping within -12%..+9%.
BALANCED_COMPILE = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}
#: XLA options of a rollout compiled quickly: LLVM level 0, classic emitters: compile 55-62%
#: shorter than XLA's defaults (ant 2.2 s, humanoid 4.5, box_stack 3.7, primitive_pairs 4.9),
#: stepping 2.7-3.7x slower than :data:`BALANCED_COMPILE`.
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}


def jit_for_few_calls(fn, **jit_kwargs):
    """``jax.jit(fn, **jit_kwargs)`` compiled for a function called a few times per compile (a
    drill-down's ``forward``, a fuzz check, the verdict's per-piece metrics), not stepped: with
    :data:`FAST_COMPILE` (:data:`BALANCED_COMPILE` where LLVM level 0 is not validated,
    :func:`fast_compile_validated`). Measured (2 cores): the sensing scenario's ``mjx.forward``
    compiles in 11.5 s against 21.1 s with XLA's defaults (its accelerations agree with C's to
    1e-14 either way); a sweep of pendulum, box_stack and ant compiles the verdict's
    ``error_series`` 9 times in 0.5-0.7 s against 2.7-3.0 s."""
    import jax

    options = FAST_COMPILE if fast_compile_validated() else BALANCED_COMPILE
    return jax.jit(fn, compiler_options=dict(options), **jit_kwargs)


def enable_x64(on: bool = True):
    """A context in which this thread computes in float64 (``on``) or float32."""
    import jax

    if hasattr(jax, "enable_x64"):
        return jax.enable_x64(on)
    from jax import experimental

    # jax.experimental's x64 contexts, before JAX 0.8 (gone from the reference JAX's stubs)
    return experimental.enable_x64() if on else experimental.disable_x64()  # pyright: ignore[reportAttributeAccessIssue]


def disable_bit(flag: str) -> int:
    """The ``mjtDisableBit`` of ``flag`` (``spring``, ``gravity``: the name without ``mjDSBL_``,
    lower case); ``spring`` and ``damper`` are ``mjDSBL_PASSIVE`` (both) where MuJoCo has no
    separate bits."""
    bits = mujoco.mjtDisableBit
    name = f"mjDSBL_{flag.upper()}"
    if not hasattr(bits, name) and flag in ("spring", "damper"):
        name = "mjDSBL_PASSIVE"
    return int(getattr(bits, name))


def sensor_types(*names: str) -> tuple[int, ...]:
    """The ``mjtSensor`` values of those of ``names`` (``mjSENS_TOUCH``) this MuJoCo has."""
    return tuple(int(getattr(mujoco.mjtSensor, n)) for n in names if hasattr(mujoco.mjtSensor, n))


def full_inertia(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    """The (nv, nv) joint-space inertia matrix of ``d`` (after ``mj_forward``), dense."""
    qm = np.zeros((m.nv, m.nv))
    if _FULLM_TAKES_DATA:
        mujoco.mj_fullM(m, d, qm)
    else:
        mujoco.mj_fullM(m, qm, d.qM)
    return qm


_FULLM_TAKES_DATA = "d: mujoco._structs.MjData" in (mujoco.mj_fullM.__doc__ or "")


def put_model(m: mujoco.MjModel, impl: str = "jax") -> Any:
    """``mjx.put_model(m, impl=impl)``; the JAX implementation without the argument, which MJX 3.3.0 lacks."""
    from mujoco import mjx

    return mjx.put_model(m) if impl == "jax" else mjx.put_model(m, impl=impl)


def data_impl(dx: Any) -> Any:
    """The part of an MJX ``Data`` that holds its JAX implementation's fields (``contact``,
    ``efc_J``, ``qM``, ...): ``dx._impl``, or ``dx`` where MJX keeps them on ``Data``."""
    return getattr(dx, "_impl", dx)


def with_impl(dx: Any, **fields: Any) -> Any:
    """``dx`` with implementation fields (:func:`data_impl`) replaced."""
    if hasattr(dx, "_impl"):
        return dx.replace(_impl=dx._impl.replace(**fields))  # noqa: SLF001
    return dx.replace(**fields)


def impl_fields() -> tuple[str, ...]:
    """The names of the implementation fields kept apart from ``Data``'s (none where MJX keeps
    them on ``Data``)."""
    from mujoco.mjx._src import types

    return tuple(f.name for f in types.DataJAX.fields()) if hasattr(types, "DataJAX") else ()


def mjx_lacks(*names: str) -> list[str]:
    """Those of ``names`` (functions of ``mujoco.mjx``) this MJX does not have."""
    from mujoco import mjx

    return [n for n in names if not hasattr(mjx, n)]


# ----------------------------------------------------------------------------
# mujoco.batch (MuJoCo 4.0) or a loop


class LoopSimulationError(RuntimeError):
    """MuJoCo raised an error in some simulations of a call (as ``mujoco.batch.SimulationError``):
    ``ids`` lists them; they kept the state they had before the call."""

    def __init__(self, ids: Sequence[int], message: str, nsim: int):
        super().__init__(f"{len(ids)} of {nsim} simulations failed; first: {message}")
        self.ids = np.asarray(ids, int)


#: State fields a caller may write before a call, as on ``Batch``.
_STATE = ("qpos", "qvel", "act", "ctrl")


class LoopBatch:
    """``nsim`` simulations of ``model``, each its own ``MjData``, stepped one after another:
    the part of :class:`mujoco.batch.Batch` mjxdiff uses (``set_models``, the state arrays
    ``qpos``/``qvel``/``act``/``ctrl``, ``warning``, ``get_data``, ``rollout``), for MuJoCo
    releases before 4.0. ``nthread`` and ``persistent`` are accepted and ignored (every
    simulation keeps its ``MjData``)."""

    def __init__(self, model: mujoco.MjModel, nsim: int, nthread: int = 0, persistent: bool = False):
        self.model, self.nsim = model, nsim
        self._models = [model] * nsim
        self._datas = [mujoco.MjData(model) for _ in range(nsim)]
        self._arrays = {f: np.stack([np.array(getattr(d, f)) for d in self._datas]) for f in _STATE}
        self.warning = np.zeros((nsim, len(self._datas[0].warning), 2))  # [lastinfo, number] per warning

    def __getattr__(self, name: str) -> np.ndarray:
        if name in _STATE:
            return self.__dict__["_arrays"][name]
        raise AttributeError(f"'LoopBatch' object has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _STATE:
            self._arrays[name][...] = value
        else:
            object.__setattr__(self, name, value)

    def set_models(self, models: Sequence[mujoco.MjModel]) -> None:
        self._models = list(models)

    def _load(self, i: int) -> mujoco.MjData:
        d = self._datas[i]
        for f in _STATE:
            getattr(d, f)[...] = self._arrays[f][i]
        return d

    def _save(self, i: int, d: mujoco.MjData) -> None:
        for f in _STATE:
            self._arrays[f][i] = getattr(d, f)
        self.warning[i] = [(w.lastinfo, w.number) for w in d.warning]

    def get_data(self, sim: int, data: mujoco.MjData | None = None) -> mujoco.MjData:
        """Simulation ``sim``'s ``MjData`` with its state and the derived fields of its last
        step: a copy; or, given ``data`` (as ``Batch`` takes one to fill), the simulation's own
        ``MjData``, to read only (MuJoCo before 4.0 has no ``mj_copyData`` in Python)."""
        d = self._load(sim)
        return copy.copy(d) if data is None else d

    def rollout(self, nstep: int, control=None, record: Sequence[Any] = ("qpos",),
                out: dict[Any, np.ndarray] | None = None, ids=None) -> dict[Any, np.ndarray]:
        """Each simulation of ``ids`` (default all) advanced ``nstep`` ``mj_step`` calls, ``ctrl``
        set from ``control`` (n, nstep, nu) before each, ``record`` items (MjData field names or
        mjtState specs) recorded after each into (n, nstep, ...) arrays; a simulation whose
        warning counters rise stops and its remaining records repeat its last ones."""
        ids = range(self.nsim) if ids is None else [int(i) for i in ids]
        out = dict(out or {})
        for item in record:
            if item not in out:
                template = (np.zeros(mujoco.mj_stateSize(self.model, int(item))) if not isinstance(item, str)
                            else np.asarray(getattr(self._datas[0], item)))
                out[item] = np.zeros((len(ids), nstep, *template.shape), template.dtype)
        failed, message = [], ""
        for row, i in enumerate(ids):
            m, d = self._models[i], self._load(i)
            before = copy.copy(d)
            warned = sum(w.number for w in d.warning)
            try:
                for k in range(nstep):
                    if control is not None:
                        d.ctrl[:] = control[row, k]
                    mujoco.mj_step(m, d)
                    for item, buf in out.items():
                        if isinstance(item, str):
                            buf[row, k] = getattr(d, item)
                        else:
                            mujoco.mj_getState(m, d, buf[row, k], int(item))
                    if sum(w.number for w in d.warning) > warned:
                        for buf in out.values():
                            buf[row, k + 1:] = buf[row, k]
                        break
            except mujoco.FatalError as e:
                failed.append(i)
                message = message or str(e)
                self._datas[i] = d = before
            self._save(i, d)
        if failed:
            raise LoopSimulationError(failed, message, self.nsim)
        return out


try:
    from mujoco.batch import Batch, SimulationError

    HAS_BATCH = True
except ImportError:  # MuJoCo before 4.0
    Batch, SimulationError = LoopBatch, LoopSimulationError  # type: ignore[misc,assignment]
    HAS_BATCH = False
