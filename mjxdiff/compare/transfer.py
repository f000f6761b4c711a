"""Does MJX's host interface give back what MuJoCo C holds?

Every MJX user moves state between the engines: ``mjx.put_data`` to start from a C state,
``mjx.get_data`` to look at or render an MJX state in C, ``mjx.get_state``/``set_state``
to checkpoint, ``mjx.id2name``/``name2id`` and ``Model.bind``/``Data.bind`` to read
observations by name. A slip there corrupts every comparison built on it, silently. At a
C state ``d`` (after ``mj_forward``), :func:`check` asks, each against C's definition:

* ``get_data(put_data(d))``: every public ``mjx.Data`` field comes back as C holds it, and
  so do the penetrating contacts (geoms, distance, position, frame; see
  :data:`CONTACTS_COMPARED`);
* ``state_size``, ``get_state`` and ``set_state`` for each state element, one at a time,
  against ``mj_stateSize`` and ``mj_getState``; an element MJX refuses is reported as
  unsupported, not as a mismatch;
* ``id2name`` and ``name2id`` for every named object, against ``mj_id2name``;
* ``Model.bind`` and ``Data.bind`` of all bodies, joints, geoms, sites, cameras, tendons,
  actuators, sensors and equalities (with the model's ``MjSpec``): each bound field equals
  that element's slice of the C field (``qpos`` at ``jnt_qposadr``, ``sensordata`` at
  ``sensor_adr``, ...), and ``BindData.set`` writes where ``d.<field>[slice]`` would.

Errors are relative, ``|mjx - c| / (1 + max|c|)``, judged against :data:`RTOL` (copies in
float64 come back exact; float32 rounds once).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from mjxdiff.input import joints
from mjxdiff.input.precision import THRESHOLDS, Precision
from mjxdiff.errors import one_line
from mjxdiff.files import atomic_write

__all__ = ["RTOL", "Mismatch", "TransferCheck", "check", "check_scenario_states", "cached_check_scenario_states",
           "CONTACTS_COMPARED"]

#: Largest relative difference a value may pick up going through MJX's host interface.
RTOL = {p: t.transfer_rtol for p, t in THRESHOLDS.items()}

#: Contacts ``get_data`` is compared on: the penetrating ones (``dist <= 0``). MJX 3.17's
#: ``get_data`` drops contacts inside the margin (``0 < dist < margin``) that C holds, with
#: constraint rows of their own (a known divergence: ``tests/test_known_divergences.py``).
CONTACTS_COMPARED = "dist <= 0"

_CONTACT_FIELDS = ("geom", "dist", "pos", "frame")

#: spec list, model-field prefix, data-field prefix of ``BindData``, the data fields bound
_BIND_KINDS = (
    ("bodies", "body_", "", ("xpos", "xquat", "xmat", "xipos", "ximat", "subtree_com", "cvel", "xfrc_applied")),
    ("joints", "jnt_", "jnt_", ("qpos", "qvel", "qacc", "qfrc_bias", "qfrc_passive", "qfrc_actuator",
                                "qfrc_constraint", "qfrc_applied")),
    ("geoms", "geom_", "geom_", ("xpos", "xmat")),
    ("sites", "site_", "site_", ("xpos", "xmat")),
    ("cameras", "cam_", "cam_", ("xpos", "xmat")),
    ("tendons", "tendon_", "ten_", ("length",)),
    ("actuators", "actuator_", "actuator_", ("ctrl", "force", "length")),
    ("sensors", "sensor_", "sensor_", ("sensordata",)),
    ("equalities", "eq_", "eq_", ("active",)),
)

_NAMED = (mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_SITE,
          mujoco.mjtObj.mjOBJ_CAMERA, mujoco.mjtObj.mjOBJ_LIGHT, mujoco.mjtObj.mjOBJ_MESH,
          mujoco.mjtObj.mjOBJ_HFIELD, mujoco.mjtObj.mjOBJ_TENDON, mujoco.mjtObj.mjOBJ_ACTUATOR,
          mujoco.mjtObj.mjOBJ_SENSOR, mujoco.mjtObj.mjOBJ_EQUALITY, mujoco.mjtObj.mjOBJ_PAIR,
          mujoco.mjtObj.mjOBJ_KEY)


@dataclasses.dataclass(frozen=True)
class Mismatch:
    """One value MJX's host interface got wrong.

    Attributes:
      call: the MJX call, e.g. ``get_state(mjSTATE_QVEL)`` or ``Data.bind(joints).qpos``.
      field: the field or element compared.
      error: relative error (``inf`` when sizes or names differ).
      index: flat index of the worst component (-1 when sizes differ).
      detail: what C holds there and what MJX gave.
      state: the C state it was found at (steps from the initial state).
    """

    call: str
    field: str
    error: float
    index: int
    detail: str
    state: int = 0


@dataclasses.dataclass(frozen=True)
class TransferCheck:
    """The host interface checked at some C states of one model."""

    mismatches: tuple[Mismatch, ...]
    unsupported: tuple[str, ...]
    checked: int
    states: tuple[int, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return dict(mismatches=[dataclasses.asdict(x) for x in self.mismatches], unsupported=list(self.unsupported),
                    checked=self.checked, states=list(self.states))

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> TransferCheck:
        """The check :meth:`as_dict` wrote."""
        return cls(tuple(Mismatch(**x) for x in doc["mismatches"]), tuple(doc["unsupported"]), int(doc["checked"]),
                   tuple(int(t) for t in doc["states"]))


def _compare(out: list, call: str, field: str, c: Any, x: Any, rtol: float) -> None:
    c, x = np.asarray(c, float), np.asarray(x, float)
    if c.size != x.size:
        out.append(Mismatch(call, field, float("inf"), -1, f"C has {c.size} values, MJX {x.size}"))
        return
    if not c.size:
        return
    diff = np.abs(c.ravel() - x.ravel()) / (1.0 + np.abs(c).max())
    diff = np.where(np.isnan(diff), np.inf, diff)
    i = int(diff.argmax())
    if diff[i] > rtol:
        out.append(Mismatch(call, field, float(diff[i]), i, f"C {c.ravel()[i]:.9g}, MJX {x.ravel()[i]:.9g}"))


def _contacts(c: Any) -> np.ndarray:
    """Penetrating contacts, one row each (geom1, geom2, dist, pos, frame), sorted."""
    keep = np.asarray(c.dist) <= 0
    if not keep.any():
        return np.zeros((0, 15))
    rows = np.concatenate([np.asarray(getattr(c, f), float).reshape(len(keep), -1)[keep] for f in _CONTACT_FIELDS],
                          axis=1)
    return rows[np.lexsort(rows[:, ::-1].T)] if len(rows) else rows


def _get_data(m: mujoco.MjModel, d: mujoco.MjData, dx: Any, rtol: float, out: list) -> int:
    from mujoco import mjx
    from mujoco.mjx._src import types

    back = mjx.get_data(m, dx)
    assert isinstance(back, mujoco.MjData)  # one Data, not a batch
    n = 0
    for f in types.Data.fields():
        if f.name == "_impl" or not hasattr(d, f.name):
            continue
        _compare(out, "get_data(put_data(d))", f.name, getattr(d, f.name), getattr(back, f.name), rtol)
        n += 1
    _compare(out, "get_data(put_data(d))", f"contact ({CONTACTS_COMPARED}: geom, dist, pos, frame)",
             _contacts(d.contact), _contacts(back.contact), rtol)
    return n + 1


def _state(m: mujoco.MjModel, d: mujoco.MjData, mx: Any, dx: Any, blank: Any, rtol: float, out: list,
           unsupported: list) -> int:
    """``state_size`` of each element, then ``get_state`` and ``set_state`` of all those MJX
    knows at once (three calls: few small XLA programs), mismatches named by element."""
    from mujoco import mjx

    from mjxdiff.compat import installed, mjx_lacks

    lacks = mjx_lacks("state_size", "get_state", "set_state")
    if lacks:
        unsupported.append(f"{', '.join(lacks)}: not in this MJX (mujoco-mjx {installed()['mujoco-mjx']})")
        return 0
    elements, n = [], 0
    for i in range(mujoco.mjtState.mjNSTATE.value):
        element = mujoco.mjtState(1 << i)
        try:
            size = mjx.state_size(mx, element)
        except ValueError as e:  # an element MJX does not know ("Invalid state element")
            unsupported.append(f"get_state({element.name}): {' '.join(str(e).split())[:120]}")
            continue
        except Exception as e:  # noqa: BLE001 - one MJX knows but cannot size: its own inconsistency
            out.append(Mismatch(f"state_size({element.name})", element.name, float("inf"), -1,
                                f"MJX raised {one_line(e, 120)}"))
            continue
        if size != mujoco.mj_stateSize(m, element):
            out.append(Mismatch(f"state_size({element.name})", element.name, float("inf"), -1,
                                f"C {mujoco.mj_stateSize(m, element)}, MJX {size}"))
            continue
        elements.append(element)
        n += 1
    spec = sum(int(e) for e in elements)
    if not spec:
        return n
    state_c = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, state_c, spec)
    ends = np.cumsum([mujoco.mj_stateSize(m, e) for e in elements])

    def compare(call: str, got: Any) -> None:
        found: list[Mismatch] = []
        _compare(found, call, "state", state_c, got, rtol)
        for x in found:  # name the element the worst component belongs to
            name = elements[int(np.searchsorted(ends, x.index, side="right"))].name if x.index >= 0 else "state"
            out.append(dataclasses.replace(x, call=call.replace("SPEC", name), field=name))

    compare("get_state(SPEC)", mjx.get_state(mx, dx, spec))
    # set_state into data that holds none of it: get_state must then give C's state back
    # MJX annotates a jax.Array; it takes numpy's as any jax function does
    put = mjx.set_state(mx, blank, np.asarray(state_c, np.asarray(dx.qpos).dtype), spec)  # pyright: ignore[reportArgumentType]
    compare("get_state(set_state(SPEC))", mjx.get_state(mx, put, spec))
    return n + 2


def _names(m: mujoco.MjModel, mx: Any, out: list, unsupported: list) -> int:
    """``id2name`` and ``name2id`` of every named object against C. An object type MJX keeps no
    name table for (lights in MJX 3.17: ``name2id`` raises KeyError, ``id2name`` gives None) is
    listed in ``unsupported`` once, as refused, not failed."""
    from mujoco import mjx

    n = 0
    for obj in _NAMED:
        named = [(i, mujoco.mj_id2name(m, obj, i)) for i in range(_count(m, obj))]
        probe = next((name for _, name in named if name), None)
        if probe is not None:
            try:
                mjx.name2id(mx, obj, probe)
            except (KeyError, NotImplementedError) as e:
                unsupported.append(f"id2name/name2id({obj.name}): {type(e).__name__}, no name table in MJX")
                continue
        for i, name_c in named:
            name_x = mjx.id2name(mx, obj, i)
            if (name_c or None) != (name_x or None):
                out.append(Mismatch("id2name", f"{obj.name} {i}", float("inf"), i, f"C {name_c!r}, MJX {name_x!r}"))
            if name_c:
                j = mjx.name2id(mx, obj, name_c)
                if j != mujoco.mj_name2id(m, obj, name_c):
                    out.append(Mismatch("name2id", f"{obj.name} {name_c!r}", float("inf"), i,
                                        f"C {mujoco.mj_name2id(m, obj, name_c)}, MJX {j}"))
            n += 1
    return n


def _count(m: mujoco.MjModel, obj: mujoco.mjtObj) -> int:
    return {mujoco.mjtObj.mjOBJ_BODY: m.nbody, mujoco.mjtObj.mjOBJ_JOINT: m.njnt, mujoco.mjtObj.mjOBJ_GEOM: m.ngeom,
            mujoco.mjtObj.mjOBJ_SITE: m.nsite, mujoco.mjtObj.mjOBJ_CAMERA: m.ncam,
            mujoco.mjtObj.mjOBJ_LIGHT: m.nlight, mujoco.mjtObj.mjOBJ_MESH: m.nmesh,
            mujoco.mjtObj.mjOBJ_HFIELD: m.nhfield, mujoco.mjtObj.mjOBJ_TENDON: m.ntendon,
            mujoco.mjtObj.mjOBJ_ACTUATOR: m.nu, mujoco.mjtObj.mjOBJ_SENSOR: m.nsensor,
            mujoco.mjtObj.mjOBJ_EQUALITY: m.neq, mujoco.mjtObj.mjOBJ_PAIR: m.npair,
            mujoco.mjtObj.mjOBJ_KEY: m.nkey}[obj]


_QPOS_WIDTH, _DOF_WIDTH = joints.QPOS_WIDTH, joints.DOF_WIDTH


def _data_slice(m: mujoco.MjModel, d: mujoco.MjData, kind: str, field: str, ids: np.ndarray) -> np.ndarray:
    """C's values of ``field`` for the elements ``ids`` of ``kind``, by the field's definition."""
    if kind == "joints":
        adr, width = (m.jnt_qposadr, _QPOS_WIDTH) if field == "qpos" else (m.jnt_dofadr, _DOF_WIDTH)
        return np.concatenate([getattr(d, field)[adr[j]:adr[j] + width[int(m.jnt_type[j])]] for j in ids])
    if kind == "sensors":
        return np.concatenate([d.sensordata[m.sensor_adr[s]:m.sensor_adr[s] + m.sensor_dim[s]] for s in ids])
    name = {"bodies": field, "actuators": "ctrl" if field == "ctrl" else f"actuator_{field}",
            "tendons": f"ten_{field}", "equalities": f"eq_{field}"}.get(kind, f"{kind[:-1]}_{field}")
    if kind == "cameras":
        name = f"cam_{field}"
    return getattr(d, name)[ids]


def _bind(m: mujoco.MjModel, d: mujoco.MjData, spec: mujoco.MjSpec, mx: Any, dx: Any, rtol: float,
          out: list) -> int:
    from mujoco.mjx._src import types

    import jax

    model_fields = {f.name for f in types.Model.fields()}
    data_fields = {f.name for f in types.Data.fields()}
    # reads index host copies (numpy: no XLA program per shape); BindData.set needs MJX's arrays
    mx_host, dx_host = jax.device_get(mx), jax.device_get(dx)
    n = 0
    for kind, model_prefix, data_prefix, fields in _BIND_KINDS:
        elements = list(getattr(spec, kind))
        if kind == "bodies":
            elements = elements[1:]  # the world body: no joint, no mocap
        if not elements:
            continue
        ids = np.array([e.id for e in elements])
        bound_m = mx_host.bind(elements)
        for name in sorted(model_fields):
            if name.startswith(model_prefix) and hasattr(m, name) and not name.endswith("_adr"):
                value = getattr(m, name)
                if isinstance(value, np.ndarray) and value.ndim and value.shape[0] == _count_of(m, kind):
                    _compare(out, f"Model.bind({kind}).{name[len(model_prefix):]}", name, value[ids],
                             getattr(bound_m, name[len(model_prefix):]), rtol)
                    n += 1
        bound_d = dx_host.bind(mx_host, elements)
        for field in fields:
            if (data_prefix + field) not in data_fields and field not in data_fields:
                continue
            _compare(out, f"Data.bind({kind}).{field}", field, _data_slice(m, d, kind, field, ids),
                     getattr(bound_d, field), rtol)
            n += 1
        n += _bind_set(m, d, mx, dx, kind, elements, ids, fields, rtol, out)
    return n


def _count_of(m: mujoco.MjModel, kind: str) -> int:
    return dict(bodies=m.nbody, joints=m.njnt, geoms=m.ngeom, sites=m.nsite, cameras=m.ncam, tendons=m.ntendon,
                actuators=m.nu, sensors=m.nsensor, equalities=m.neq)[kind]


def _bind_set(m, d, mx, dx, kind, elements, ids, fields, rtol, out) -> int:
    """``Data.bind(...).set`` of a writable field: MJX's whole field afterwards equals C's field
    after ``d.<field>[slice] = value``."""
    writable = {"joints": "qvel", "actuators": "ctrl", "bodies": "xfrc_applied"}.get(kind)
    if writable is None:
        return 0
    c_name = {"actuators": "ctrl"}.get(kind, writable)
    value = np.arange(1, _data_slice(m, d, kind, writable, ids).size + 1, dtype=float) / 8.0
    expected = np.array(getattr(d, c_name), float)
    if kind == "joints":
        i = 0
        for j in ids:
            adr, w = m.jnt_dofadr[j], _DOF_WIDTH[int(m.jnt_type[j])]
            expected[adr:adr + w] = value[i:i + w]
            i += w
    else:
        expected[ids] = value.reshape(expected[ids].shape)
    after = dx.bind(mx, elements).set(writable, value)
    _compare(out, f"Data.bind({kind}).set({writable!r})", c_name, expected, getattr(after, c_name), rtol)
    return 1


def check(m: mujoco.MjModel, d: mujoco.MjData, spec: mujoco.MjSpec | None = None,
          precision: Precision = "float64") -> TransferCheck:
    """MJX's host interface at the C state ``d`` of ``m`` (``mj_forward`` already run).

    Args:
      spec: the ``MjSpec`` that compiled ``m`` (its signature must match); ``None`` leaves
        out the bind checks.
      precision: of the caller's JAX (``jax_enable_x64`` must already match it).
    """
    from mujoco import mjx

    rtol = RTOL[precision]
    out: list[Mismatch] = []
    unsupported: list[str] = []
    mx = mjx.put_model(m)
    dx = mjx.put_data(m, d)
    n = _get_data(m, d, dx, rtol, out)
    n += _state(m, d, mx, dx, mjx.make_data(m), rtol, out, unsupported)
    n += _names(m, mx, out, unsupported)
    if spec is not None and spec.compile().signature == m.signature:
        n += _bind(m, d, spec, mx, dx, rtol, out)
    return TransferCheck(tuple(out), tuple(unsupported), n)


def check_scenario_states(m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray,
                          ctrl: np.ndarray, time: float, model_path: str | Path | None = None,
                          precision: Precision = "float64") -> TransferCheck:
    """:func:`check` at two C states of one member: its initial state and the state with the
    most contacts along C stepping it with its controls ``ctrl`` ``(T, nu)``.

    Returns:
      The union of both checks, with ``states`` the step counts checked (0: initial).
    """
    spec = None
    if model_path is not None and Path(model_path).suffix.lower() == ".xml":
        try:
            spec = mujoco.MjSpec.from_file(str(model_path))
        except Exception:  # noqa: BLE001 - without a spec only the bind checks are left out
            spec = None
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.act[:], d.time = qpos, qvel, act, time
    if len(ctrl):
        d.ctrl[:] = ctrl[0]
    mujoco.mj_forward(m, d)
    first = check(m, d, spec, precision)
    best, best_ncon, snapshot = 0, d.ncon, None
    for t in range(len(ctrl)):
        d.ctrl[:] = ctrl[t]
        mujoco.mj_step(m, d)
        if d.ncon > best_ncon:
            best, best_ncon = t + 1, d.ncon
            snapshot = _snapshot(m, d)
    if snapshot is None:
        return dataclasses.replace(first, states=(0,))
    d2 = mujoco.MjData(m)
    mujoco.mj_setState(m, d2, snapshot, mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(m, d2)
    second = check(m, d2, spec, precision)
    return TransferCheck(first.mismatches + tuple(dataclasses.replace(x, state=best) for x in second.mismatches),
                         tuple(dict.fromkeys(first.unsupported + second.unsupported)),
                         first.checked + second.checked, (0, best))


def _snapshot(m: mujoco.MjModel, d: mujoco.MjData) -> np.ndarray:
    state = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(m, d, state, mujoco.mjtState.mjSTATE_INTEGRATION)
    return state


def cached_check_scenario_states(cache: Path | None, m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray,
                                 act: np.ndarray, ctrl: np.ndarray, time: float,
                                 model_path: str | Path | None = None,
                                 precision: Precision = "float64") -> tuple[TransferCheck, bool]:
    """:func:`check_scenario_states`, or what an earlier run of the very same check found, saved
    under ``cache`` (None: always checked, nothing saved). Its key is everything the check reads
    or runs (:func:`_key`), so a loaded result is the one a check now would give; an entry that
    cannot be read is checked afresh and rewritten (fail closed).

    Why: the check runs MJX's host functions eagerly, ~50 small XLA computations of each model's
    shapes, lowered and compiled (or looked up) one by one in every process: 1.5-2.5 CPU-s a
    scenario, the largest phase of a warm sweep after MJX's stepping.

    Returns:
      (the check, whether it was loaded).
    """
    path = None
    if cache is not None:
        try:
            key = _key(m, qpos, qvel, act, ctrl, time, model_path, precision)
            path = Path(cache) / "mjxdiff-checks" / f"transfer-{key}.json"
            return TransferCheck.from_dict(json.loads(path.read_text())), True
        except Exception:  # noqa: BLE001 - no key, no entry or a damaged one: check afresh
            pass
    found = check_scenario_states(m, qpos, qvel, act, ctrl, time, model_path, precision)
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, json.dumps(found.as_dict()))
        except OSError:
            pass  # a read-only cache: the check stands, unsaved
    return found, False


def _key(m: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, ctrl: np.ndarray, time: float,
         model_path: str | Path | None, precision: Precision) -> str:
    """Hex SHA-256 of what :func:`check_scenario_states` reads and runs: the code of MJX and of
    this module, the versions and JAX settings (:func:`mjxdiff.engine.digest.rollout_digest`, as
    a rollout's artifact is keyed), the precision, the compiled model (``mj_saveModel``), the state
    and controls, and the model file (its spec gives the ``bind`` checks)."""
    from mjxdiff.engine.digest import code_digest, rollout_digest

    h = hashlib.sha256()
    for part in (rollout_digest(), code_digest((__name__,)), precision, repr(float(time))):
        h.update(part.encode() + b"\0")
    model = np.empty(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, model)
    h.update(model.tobytes())
    for a in (qpos, qvel, act, ctrl):
        a = np.ascontiguousarray(a, np.float64)
        h.update(repr(a.shape).encode() + a.tobytes())
    if model_path is not None and Path(model_path).suffix.lower() == ".xml":
        h.update(Path(model_path).read_bytes())
    return h.hexdigest()
