"""Self-contained reproducers of failing scenario members, and their replay.

A reproducer is one JSON file holding everything needed to re-run one failing
batch member with nothing else installed but mjxdiff's dependencies: the
member's compiled model as base64 MJB (exact: scaled parameters and
``mj_setConst`` constants included), the original MJCF text for reading, the
initial state, the controls, the seed, tolerances, the configuration, the
versions, and the verdict it produced. ``python -m mjxdiff replay FILE`` runs
it again; both engines are deterministic on the CPU, so the replay prints the
same diagnosis every time.

A derivative reproducer (kind ``grad-reproducer``, written by ``mjxdiff grad --out``) holds one
state of a model whose MJX Jacobians disagree with C's: replay judges that state again.

Both are JSON outputs in the report envelope (:func:`mjxdiff.output.report.envelope`: ``kind``,
``schema_version``, versions, code digests, machine, config, seed). Files of the older shape
(``format: mjxdiff-reproducer/1`` or ``mjxdiff-grad-reproducer/1``) are still read.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from mjxdiff.input.precision import PRECISIONS
from mjxdiff.files import atomic_write
from mjxdiff.input.inputs import FACTOR_SHAPES, BatchedInputs
from mjxdiff.input.scenario import ScenarioError, Tolerances

__all__ = ["KIND", "GRAD_KIND", "FORMAT", "GRAD_FORMAT", "Reproducer", "GradReproducer", "document", "save", "load",
           "save_grad", "load_any", "member_inputs"]

KIND = "reproducer"  # the envelope kind of a sweep reproducer
GRAD_KIND = "grad-reproducer"
FORMAT = "mjxdiff-reproducer/1"  # the shape before the envelope: read, no longer written
GRAD_FORMAT = "mjxdiff-grad-reproducer/1"
_VERSION = 1  # the last version of the old shape


@dataclasses.dataclass(frozen=True)
class Reproducer:
    """One failing member: its model, inputs, settings and the verdict it gave."""

    scenario: str
    member: int
    model: mujoco.MjModel
    model_xml: str
    inputs: BatchedInputs
    tolerances: Tolerances
    config: dict[str, Any]
    verdict: dict[str, Any]
    versions: dict[str, str]


def _model_to_b64(m: mujoco.MjModel) -> str:
    buf = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    return base64.b64encode(buf.tobytes()).decode()


def _model_from_b64(text: str) -> mujoco.MjModel:
    """The model of a base64 MJB; ValueError with MuJoCo's reason (warnings collected, not printed)."""
    data = base64.b64decode(text, validate=True)  # binascii.Error (a ValueError) on bad base64
    fd, path = tempfile.mkstemp(suffix=".mjb")
    warnings: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(warnings.append)  # else MuJoCo prints to stderr and MUJOCO_LOG.TXT
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        try:
            return mujoco.MjModel.from_binary_path(path)
        except Exception as e:  # noqa: BLE001 - whatever MuJoCo raises becomes a ValueError with its reason
            raise ValueError("; ".join([str(e), *warnings])) from None
    finally:
        mujoco.set_mju_user_warning(previous)
        os.unlink(path)


def member_inputs(inputs: BatchedInputs, member: int) -> BatchedInputs:
    """A batch of one: ``member`` of ``inputs``, keeping its identity for seeded draws."""
    return inputs.take(slice(member, member + 1))


def document(scenario: str, member: int, inputs: BatchedInputs, model_xml: str, tolerances: Tolerances,
             config: dict[str, Any], verdict: dict[str, Any]) -> dict[str, Any]:
    """Member ``member`` of ``inputs`` as a reproducer: a JSON-ready document of kind
    :data:`KIND` (the config's seed is the one the inputs were drawn from)."""
    from mjxdiff.output import report

    one = member_inputs(inputs, member)
    return report.envelope(
        KIND, dict(config, seed=inputs.seed), scenario=scenario, member=member, member_id=int(one.ids[0]),
        energy=inputs.energy, steps=inputs.steps, tolerances=tolerances.as_dict(), verdict=verdict,
        model_mjb_base64=_model_to_b64(one.models[0]), model_xml=model_xml,
        factors={k: v[0].tolist() for k, v in one.factors.items()},
        qpos=one.qpos[0].tolist(), qvel=one.qvel[0].tolist(), act=one.act[0].tolist(), ctrl=one.ctrl[0].tolist())


def write(path: str | Path, doc: dict[str, Any]) -> Path:
    """Writes a reproducer document (atomically); floats round-trip exactly through repr."""
    return atomic_write(path, json.dumps(doc, indent=1) + "\n")


def save(path: str | Path, scenario: str, member: int, inputs: BatchedInputs, model_xml: str,
         tolerances: Tolerances, config: dict[str, Any], verdict: dict[str, Any]) -> Path:
    """Writes member ``member`` of ``inputs`` as a reproducer file (:func:`document`)."""
    return write(path, document(scenario, member, inputs, model_xml, tolerances, config, verdict))


class _Bad(Exception):
    """What is wrong with a reproducer document (turned into a :class:`ScenarioError` naming the file)."""


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _get(doc: dict, key: str, types: type | tuple[type, ...], what: str, where: str = "") -> Any:
    """``doc[key]``, which must be one of ``types`` (bool is never taken for int); ``where``: the
    enclosing key, for the message."""
    label = f"{where} {key!r}" if where else repr(key)
    if key not in doc:
        raise _Bad(f"{label} is missing")
    value = doc[key]
    types = types if isinstance(types, tuple) else (types,)
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
        raise _Bad(f"{label} must be {what}, got {type(value).__name__}")
    return value


def _array(doc: dict, key: str, shape: tuple[int, ...], meaning: str, where: str = "") -> np.ndarray:
    """``doc[key]`` as a finite float64 array of exactly ``shape`` (a plain number when ``shape`` is ())."""
    label = f"{where} {key!r}" if where else repr(key)
    value = (_get(doc, key, (int, float), "a number", where) if shape == () else
             _get(doc, key, list, "a list of numbers", where))
    try:
        a = np.asarray(value)
    except ValueError:
        raise _Bad(f"{label} is ragged (expected shape {shape}, {meaning})") from None
    if a.size and a.dtype.kind not in "iuf":
        raise _Bad(f"{label} must hold numbers only")
    a = a.astype(np.float64)
    if a.shape != shape:
        raise _Bad(f"{label} has shape {a.shape}, expected {shape} ({meaning})")
    if not np.all(np.isfinite(a)):
        raise _Bad(f"{label} holds non-finite values")
    return a


def _tolerances(doc: dict) -> Tolerances:
    tol = _get(doc, "tolerances", dict, "an object")
    fields = [f.name for f in dataclasses.fields(Tolerances)]
    unknown = sorted(set(tol) - set(fields))
    if unknown:
        raise _Bad(f"unknown tolerance {unknown[0]!r}")
    for name in fields:
        v = _get(tol, name, (int, float), "a number", "tolerances")
        if not (math.isfinite(v) and v >= 0):
            raise _Bad(f"tolerance {name!r} must be a finite number >= 0, got {v!r}")
    return Tolerances(**{k: float(v) for k, v in tol.items()})


def _config(doc: dict) -> dict[str, Any]:
    """The saved sweep configuration; its known settings are checked as ``replay`` will use them."""
    from mjxdiff.input.config import NOISE_FLOOR_MODES, SweepConfig

    config = _get(doc, "config", dict, "an object")
    choices = dict(precision=PRECISIONS, noise_floor=NOISE_FLOOR_MODES,
                   diagnose=("none", "basic", "full"))
    for key, allowed in choices.items():
        if key in config and config[key] not in allowed:
            raise _Bad(f"config {key!r} must be one of {', '.join(allowed)}, got {config[key]!r}")
    for key in ("quick", "envelope"):
        if key in config:
            _get(config, key, bool, "true or false", "config")
    if "threshold" in config:
        t = _get(config, "threshold", (int, float), "a number", "config")
        if not 0 <= t <= 1:
            raise _Bad(f"config 'threshold' must be in [0, 1], got {t!r}")
    for key in ("seed", "batch", "steps", "piece_steps", "group_size"):
        if config.get(key) is not None:
            v = _get(config, key, int, "an integer or null", "config")
            if key != "seed" and v <= 0:
                raise _Bad(f"config {key!r} must be positive, got {v}")
    saved = {k: v for k, v in config.items() if k in SweepConfig.__dataclass_fields__}
    try:
        SweepConfig(**{**saved, "reproducers": None})
    except (TypeError, ValueError) as e:
        raise _Bad(f"bad config: {e}") from None
    return config


def _format_problem(doc: Any, formats: tuple[str, ...] = (FORMAT,)) -> str | None:
    """Why ``doc`` is not a reproducer in one of ``formats`` (old shape) or of their kinds (the
    envelope) that this mjxdiff reads, or None."""
    from mjxdiff.output import report

    expected = " or ".join(repr(f) for f in formats)
    kinds = tuple(_KIND_OF[f] for f in formats)
    if not isinstance(doc, dict):
        return f"not a reproducer (a JSON {type(doc).__name__}, expected an object of kind {' or '.join(kinds)})"
    if "kind" in doc:
        version = doc.get("schema_version")
        if doc["kind"] not in kinds:
            return f"not a reproducer (kind {doc['kind']!r}, expected {' or '.join(map(repr, kinds))})"
        if isinstance(version, int) and not isinstance(version, bool) and version > report.SCHEMA_VERSION:
            return (f"reproducer written by a newer mjxdiff (schema_version {version}); this mjxdiff reads "
                    f"{report.SCHEMA_VERSION}: upgrade mjxdiff to replay it")
        if version != report.SCHEMA_VERSION:
            return f"unsupported reproducer schema_version {version!r}, expected {report.SCHEMA_VERSION}"
        return None
    fmt = doc.get("format")
    version = re.fullmatch(r"(mjxdiff-(?:grad-)?reproducer)/(\d+)", fmt) if isinstance(fmt, str) else None
    if version is None or not any(f.startswith(version.group(1) + "/") for f in formats):
        return f"not a reproducer (format {fmt!r}, expected {expected})"
    if int(version.group(2)) > _VERSION:
        return (f"reproducer written by a newer mjxdiff (format {fmt!r}); this mjxdiff reads version "
                f"{_VERSION} ({expected}): upgrade mjxdiff to replay it")
    if fmt not in formats:
        return f"unsupported reproducer format {fmt!r}, expected {expected}"
    return None


_KIND_OF = {FORMAT: KIND, GRAD_FORMAT: GRAD_KIND}


def _is_grad(doc: dict) -> bool:
    return doc.get("kind") == GRAD_KIND or doc.get("format") == GRAD_FORMAT


def _parse(doc: dict) -> Reproducer:
    scenario = _get(doc, "scenario", str, "a string")
    member = _get(doc, "member", int, "an integer")
    member_id = _get(doc, "member_id", int, "an integer")
    seed = _get(doc, "seed", int, "an integer")
    for key, v in (("member", member), ("member_id", member_id), ("seed", seed)):
        if v < 0:
            raise _Bad(f"{key!r} must be >= 0, got {v}")
    energy = _get(doc, "energy", bool, "true or false")
    steps = _get(doc, "steps", int, "an integer")
    if steps <= 0:
        raise _Bad(f"'steps' must be positive, got {steps}")
    model_xml = _get(doc, "model_xml", str, "a string")
    versions = _get(doc, "versions", dict, "an object")
    verdict = _get(doc, "verdict", dict, "an object")
    _get(verdict, "status", str, "a string", "verdict")
    if not isinstance(verdict.get("first_divergence") or {}, dict):
        raise _Bad("verdict's 'first_divergence' must be an object or null")
    tolerances = _tolerances(doc)
    config = _config(doc)
    try:
        m = _model_from_b64(_get(doc, "model_mjb_base64", str, "a string"))
    except ValueError as e:
        raise _Bad(f"the model does not decode ({_one_line(e)})") from None
    qpos = _array(doc, "qpos", (m.nq,), f"the model's nq = {m.nq}")
    qvel = _array(doc, "qvel", (m.nv,), f"the model's nv = {m.nv}")
    act = _array(doc, "act", (m.na,), f"the model's na = {m.na}")
    ctrl = _array(doc, "ctrl", (steps, m.nu), f"'steps' = {steps} by the model's nu = {m.nu}")
    factors = {}
    for name, value in _get(doc, "factors", dict, "an object").items():
        if name not in FACTOR_SHAPES:
            raise _Bad(f"unknown factor {name!r} (known: {', '.join(FACTOR_SHAPES)})")
        factors[name] = _array(doc["factors"], name, FACTOR_SHAPES[name](m), "its size in the model", "factors")[None]
    inputs = BatchedInputs(qpos=qpos[None], qvel=qvel[None], act=act[None], ctrl=ctrl[None], models=(m,),
                           factors=factors, seed=seed, energy=energy, member_ids=np.array([member_id]))
    return Reproducer(scenario=scenario, member=member, model=m, model_xml=model_xml, inputs=inputs,
                      tolerances=tolerances, config=config, verdict=verdict, versions=versions)


def _read(path: str | Path, formats: tuple[str, ...]) -> dict:
    """The JSON document of a reproducer file in one of ``formats`` (ScenarioError otherwise)."""
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise ScenarioError(f"{path}: reproducer file not found") from None
    except UnicodeDecodeError as e:
        raise ScenarioError(f"{path}: not a reproducer (not UTF-8 text: {_one_line(e)})") from None
    except OSError as e:
        raise ScenarioError(f"{path}: cannot read reproducer ({_one_line(e.strerror or e)})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        cut = e.pos >= len(text.rstrip()) or e.msg.startswith("Unterminated string")  # ran into the end
        cut = " (the file looks cut short)" if cut and text.strip() else ""
        raise ScenarioError(f"{path}: not a reproducer (invalid JSON{cut}: {_one_line(e)})") from None
    except RecursionError:
        raise ScenarioError(f"{path}: not a reproducer (JSON nested too deeply)") from None
    problem = _format_problem(doc, formats)
    if problem is not None:
        raise ScenarioError(f"{path}: {_one_line(problem)}")
    return doc


def load(path: str | Path) -> Reproducer:
    """Reads and checks a reproducer.

    Raises:
      ScenarioError: in one line naming the file and what is wrong: unreadable,
        not JSON or cut short, not a reproducer, written by a newer mjxdiff
        (format version above 1), a key missing or of the wrong type, a model
        that does not decode, or arrays whose lengths do not fit the model
        (``nq``, ``nv``, ``na``, ``nu``) and ``steps``.
    """
    doc = _read(path, (FORMAT,))
    try:
        return _parse(doc)
    except _Bad as e:
        raise ScenarioError(f"{path}: bad reproducer: {_one_line(e)}") from None


# ----------------------------------------------------------------------------
# derivative reproducers (``mjxdiff grad``)


@dataclasses.dataclass(frozen=True)
class GradReproducer:
    """One state whose MJX Jacobians disagree with C's finite differences: the model as judged
    (converged solver included), the state (qpos, qvel, act, ctrl) and the verdict it gave."""

    scenario: str
    index: int
    model: mujoco.MjModel
    model_xml: str
    state: dict[str, np.ndarray]
    verdict: dict[str, Any]
    versions: dict[str, str]


def save_grad(path: str | Path, scenario: str, index: int, m: mujoco.MjModel, model_xml: str,
              state: dict[str, np.ndarray], verdict: dict[str, Any], config: dict[str, Any]) -> Path:
    """Writes the ``index``-th sampled state of ``scenario`` as a derivative reproducer (kind
    :data:`GRAD_KIND`); ``config``: how the state was drawn and judged."""
    from mjxdiff.output import report

    return write(path, report.envelope(
        GRAD_KIND, config, scenario=scenario, index=index, verdict=verdict, model_mjb_base64=_model_to_b64(m),
        model_xml=model_xml, **{k: np.asarray(state[k], np.float64).tolist() for k in ("qpos", "qvel", "act", "ctrl")}))


def _parse_grad(doc: dict) -> GradReproducer:
    scenario = _get(doc, "scenario", str, "a string")
    index = _get(doc, "index", int, "an integer")
    verdict = _get(doc, "verdict", dict, "an object")
    _get(verdict, "status", str, "a string", "verdict")
    versions = _get(doc, "versions", dict, "an object")
    model_xml = _get(doc, "model_xml", str, "a string")
    try:
        m = _model_from_b64(_get(doc, "model_mjb_base64", str, "a string"))
    except ValueError as e:
        raise _Bad(f"the model does not decode ({_one_line(e)})") from None
    state = {k: _array(doc, k, (n,), f"the model's {size} = {n}")
             for k, size, n in (("qpos", "nq", m.nq), ("qvel", "nv", m.nv), ("act", "na", m.na), ("ctrl", "nu", m.nu))}
    return GradReproducer(scenario=scenario, index=index, model=m, model_xml=model_xml, state=state,
                          verdict=verdict, versions=versions)


def load_any(path: str | Path) -> Reproducer | GradReproducer:
    """A sweep reproducer (:func:`load`) or a derivative one (``mjxdiff grad``), by its format;
    ScenarioError as :func:`load`."""
    doc = _read(path, (FORMAT, GRAD_FORMAT))
    try:
        return _parse_grad(doc) if _is_grad(doc) else _parse(doc)
    except _Bad as e:
        raise ScenarioError(f"{path}: bad reproducer: {_one_line(e)}") from None
