"""Scenario files: what to simulate, how to randomize it, how strictly to judge it.

A scenario is a TOML file (read with :mod:`tomllib`) naming an MJCF model plus
batch size, horizon, randomization and tolerances; see ``scenarios/*.toml``
and the README for the schema. Any MJCF file can also stand in for a scenario:
it is then swept with the default randomization and tolerances.

This module only parses and validates. Turning a scenario into numbers is
:mod:`mjxdiff.input.inputs`; loading its model is :func:`load_model`.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import math
import os
import tomllib
from pathlib import Path
from typing import Any, Mapping

import mujoco

from mjxdiff.compat import later_feature
from mjxdiff.input.precision import THRESHOLDS, Precision

__all__ = [
    # served by the module __getattr__, which neither ruff nor pyright reads for __all__
    "BUNDLED_DIR",  # noqa: F822  # pyright: ignore[reportUnsupportedDunderAll]
    "BUNDLED_PACKAGE",
    "CONTROL_FAMILIES",
    "DISABLE_FLAGS",
    "SCALED_PARAMETERS",
    "Randomization",
    "Scenario",
    "ScenarioError",
    "Tolerances",
    "bundled_dir",
    "bundled_scenarios",
    "load_model",
    "load_scenario",
    "no_bundled_scenarios_message",
]

#: Data package the bundled scenarios install as (the repository's top-level
#: ``scenarios/``, mapped in pyproject.toml); ``$MJXDIFF_SCENARIOS`` overrides it.
BUNDLED_PACKAGE = "mjxdiff._scenarios"
CONTROL_FAMILIES = ("zero", "smooth", "sinusoid", "step")
#: Model parameters a scenario may scale per batch member, by a factor drawn
#: uniformly from ``[lo, hi]``: one factor per element (body, geom, dof,
#: actuator) or, for ``gravity`` and ``timestep``, one per member.
SCALED_PARAMETERS = ("body_mass", "geom_friction", "dof_damping", "actuator_gain", "gravity", "timestep")

# Where `brax:` and `mjx:` model references resolve: models shipped in wheels.
_WHEEL_MODEL_DIRS = {
    "brax": ("brax", "envs/assets"),
    "mjx": ("mujoco.mjx", "test_data"),
}


class ScenarioError(ValueError):
    """A scenario or model cannot be used; the message says what to fix, in one line."""


class LaterFeatureError(ScenarioError):
    """The installed MuJoCo is older than the reference and cannot express something the model
    uses (:func:`mjxdiff.compat.later_feature`): not a malformed model, an unsupported one here."""


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """Largest acceptable MJX-vs-C errors, per metric, at any step.

    Attributes:
      qpos: joint position error, m for translations and rad for rotations
        (quaternions compared by geodesic angle).
      qvel: joint velocity error, m/s or rad/s.
      act: actuator activation error, in the actuator's own units.
      sensordata: absolute sensor error, in each sensor's units.
      contact_mismatch: largest fraction of steps whose firm contacts differ pair by pair
        (:mod:`mjxdiff.engine.pairs`; grazing and ccd-ambiguous contacts are set aside, not
        judged). 0 by default, as in MuJoCo's parity method: any unambiguous mismatch fails
        unless C's own perturbed rerun shows as many (twice C's own fraction is allowed).
      rangefinder_mismatch: largest fraction of (step, ray) pairs where one
        engine hits and the other does not.
    """

    qpos: float = 1e-6
    qvel: float = 1e-5
    act: float = 1e-6
    sensordata: float = 1e-4
    contact_mismatch: float = 0.0
    rangefinder_mismatch: float = 0.02

    def for_precision(self, precision: Precision) -> "Tolerances":
        """Tolerances for ``precision``, each raised to its floor there
        (:data:`mjxdiff.input.precision.THRESHOLDS`: float64 none, float32 the measured floors).

        >>> Tolerances().for_precision("float32").qpos
        0.001
        >>> Tolerances(qpos=1e-2).for_precision("float32").qpos   # above its floor: kept
        0.01
        """
        floor = THRESHOLDS[precision].tolerance_floor
        return dataclasses.replace(self, **{k: max(getattr(self, k), v) for k, v in floor.items()}) if floor else self

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Randomization:
    """How batch members differ from one another.

    Attributes:
      qpos_noise: std of Gaussian noise added to hinge/slide/free-translation
        ``qpos`` (rad or m); quaternions are rotated by a random axis-angle of
        this std (rad).
      qvel_noise: std of Gaussian noise on ``qvel`` (m/s or rad/s).
      control: control family, one of :data:`CONTROL_FAMILIES`.
      control_scale: amplitude as a fraction of each actuator's ctrlrange
        half-width (unlimited actuators use [-1, 1]).
      scale: parameter name -> (lo, hi) multiplicative range, see
        :data:`SCALED_PARAMETERS`.
      values: model field -> (lo, hi): absolute values drawn uniformly, one per element
        and member (``[randomize.set]``), for parameters whose default (often 0) no factor
        can move: ``dof_armature``, ``jnt_stiffness``, ``"geom_solref[0]"`` (one column),
        ``"opt.impratio"``; see :func:`mjxdiff.input.inputs.settable`.
      ctrl_outside: fraction of the batch (its last members, rounded down) whose controls
        are 1.5x as wide and not clipped to ``ctrlrange``: the engines' own clamp (and, with
        ``clampctrl`` disabled, its absence) is behaviour too.
      frame_rotation: std (rad) of a random rotation of every site a frame, velocity or
        force sensor reads (as its object or reference), in odd members; even members keep
        the model's frames. Sites that actuators, equalities, rangefinders or touch sensors
        use are left as they are.
      spring_range: in odd members, a tendon spring at one length L gets the deadband
        ``[L - w, L + w]``, ``w ~ U[0.5, 1] * spring_range`` (m, or rad for fixed tendons
        of hinges); even members keep the single length.
      disable: disable flags (``mjtDisableBit`` names without ``mjDSBL_``, lower case) that
        each seed draws, each with probability 1/2, for the whole scenario (one compile).
    """

    qpos_noise: float = 0.05
    qvel_noise: float = 0.05
    control: str = "smooth"
    control_scale: float = 1.0
    scale: Mapping[str, tuple[float, float]] = dataclasses.field(
        default_factory=lambda: {
            "body_mass": (0.9, 1.1),
            "geom_friction": (0.9, 1.1),
            "dof_damping": (0.9, 1.1),
            "actuator_gain": (0.9, 1.1),
            "gravity": (0.98, 1.02),
            "timestep": (1.0, 1.0),
        }
    )
    values: Mapping[str, tuple[float, float]] = dataclasses.field(default_factory=dict)
    ctrl_outside: float = 0.25
    frame_rotation: float = 0.5
    spring_range: float = 0.1
    disable: tuple[str, ...] = ()


#: Disable flags a scenario may draw (``[randomize] disable``): those MJX switches on.
DISABLE_FLAGS = ("constraint", "equality", "frictionloss", "limit", "contact", "spring", "damper", "gravity",
                 "clampctrl", "warmstart", "filterparent", "actuation", "refsafe", "sensor", "eulerdamp")


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One bundled or user scenario: a model, a batch and how to judge it."""

    name: str
    model: str
    source: Path | None = None
    description: str = ""
    exercises: tuple[str, ...] = ()
    batch: int = 8
    steps: int = 200
    keyframe: str | None = None
    notes: str = ""
    energy: bool = False
    randomize: Randomization = dataclasses.field(default_factory=Randomization)
    tolerance: Tolerances = dataclasses.field(default_factory=Tolerances)

    @property
    def model_path(self) -> Path:
        """The MJCF file this scenario simulates."""
        return _resolve_model(self.model, self.source)


def _resolve_model(ref: str, source: Path | None) -> Path:
    prefix, sep, rest = ref.partition(":")
    if sep and prefix in _WHEEL_MODEL_DIRS:
        module, sub = _WHEEL_MODEL_DIRS[prefix]
        import importlib.util

        spec = importlib.util.find_spec(module)
        if spec is None or not spec.submodule_search_locations:
            raise ScenarioError(f"model {ref!r}: package {module!r} is not installed")
        return Path(list(spec.submodule_search_locations)[0]) / sub / rest
    path = Path(ref)
    if not path.is_absolute() and source is not None:
        path = source.parent / path
    return path


def _expect(cond: bool, where: str, msg: str) -> None:
    if not cond:
        raise ScenarioError(f"{where}: {msg}")


def _positive_int(table: Mapping[str, Any], key: str, default: int, where: str) -> int:
    value = table.get(key, default)
    _expect(isinstance(value, int) and not isinstance(value, bool) and value > 0,
            where, f"'{key}' must be a positive integer, got {value!r}")
    return value


def _nonneg_float(table: Mapping[str, Any], key: str, default: float, where: str) -> float:
    value = table.get(key, default)
    _expect(isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value >= 0,
            where, f"'{key}' must be a non-negative number, got {value!r}")
    return float(value)


def _check_keys(table: Mapping[str, Any], allowed: set[str], where: str) -> None:
    unknown = sorted(set(table) - allowed)
    _expect(not unknown, where, f"unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _parse_randomization(table: Mapping[str, Any], where: str) -> Randomization:
    where = f"{where} [randomize]"
    _check_keys(table, {"qpos_noise", "qvel_noise", "control", "control_scale", "scale", "set", "ctrl_outside",
                        "frame_rotation", "spring_range", "disable"}, where)
    default = Randomization()
    control = table.get("control", default.control)
    _expect(control in CONTROL_FAMILIES, where,
            f"'control' must be one of {list(CONTROL_FAMILIES)}, got {control!r}")
    scale = dict(default.scale)
    raw_scale = table.get("scale", {})
    _expect(isinstance(raw_scale, dict), where, "'scale' must be a table")
    _check_keys(raw_scale, set(SCALED_PARAMETERS), f"{where}.scale")
    for key, rng in raw_scale.items():
        ok = (isinstance(rng, list) and len(rng) == 2
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rng)
              and 0 < rng[0] <= rng[1] and math.isfinite(rng[1]))
        _expect(ok, f"{where}.scale", f"'{key}' must be [lo, hi] with 0 < lo <= hi, got {rng!r}")
        scale[key] = (float(rng[0]), float(rng[1]))
    raw_set = table.get("set", {})
    _expect(isinstance(raw_set, dict), where, "'set' must be a table")
    values = {}
    for key, rng in raw_set.items():
        ok = (isinstance(rng, list) and len(rng) == 2
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in rng)
              and rng[0] <= rng[1])
        _expect(ok, f"{where}.set", f"'{key}' must be [lo, hi] with lo <= hi, got {rng!r}")
        values[key] = (float(rng[0]), float(rng[1]))
    disable = table.get("disable", [])
    _expect(isinstance(disable, list) and all(f in DISABLE_FLAGS for f in disable), where,
            f"'disable' must be a list of {list(DISABLE_FLAGS)}, got {disable!r}")
    ctrl_outside = _nonneg_float(table, "ctrl_outside", default.ctrl_outside, where)
    _expect(ctrl_outside <= 1, where, f"'ctrl_outside' is a fraction of the batch, in [0, 1], got {ctrl_outside!r}")
    return Randomization(
        qpos_noise=_nonneg_float(table, "qpos_noise", default.qpos_noise, where),
        qvel_noise=_nonneg_float(table, "qvel_noise", default.qvel_noise, where),
        control=control,
        control_scale=_nonneg_float(table, "control_scale", default.control_scale, where),
        scale=scale,
        values=values,
        ctrl_outside=ctrl_outside,
        frame_rotation=_nonneg_float(table, "frame_rotation", default.frame_rotation, where),
        spring_range=_nonneg_float(table, "spring_range", default.spring_range, where),
        disable=tuple(disable),
    )


def _parse_tolerances(table: Mapping[str, Any], where: str) -> Tolerances:
    where = f"{where} [tolerance]"
    fields = {f.name for f in dataclasses.fields(Tolerances)}
    _check_keys(table, fields, where)
    default = Tolerances()
    return Tolerances(**{k: _nonneg_float(table, k, getattr(default, k), where) for k in fields})


_TOP_KEYS = {"name", "description", "model", "exercises", "batch", "steps", "keyframe",
             "notes", "energy", "randomize", "tolerance"}


def scenario_from_dict(data: Mapping[str, Any], source: Path | None, default_name: str) -> Scenario:
    """Validates a parsed scenario table; raises :class:`ScenarioError` naming the bad key."""
    where = str(source) if source else default_name
    _check_keys(data, _TOP_KEYS, where)
    _expect(isinstance(data.get("model"), str) and data["model"], where, "'model' (path to an MJCF file) is required")
    exercises = data.get("exercises", [])
    _expect(isinstance(exercises, list) and all(isinstance(e, str) for e in exercises),
            where, "'exercises' must be a list of strings")
    keyframe = data.get("keyframe")
    _expect(keyframe is None or isinstance(keyframe, str), where, "'keyframe' must be a keyframe name")
    energy = data.get("energy", False)
    _expect(isinstance(energy, bool), where, "'energy' must be true or false")
    randomize = data.get("randomize", {})
    tolerance = data.get("tolerance", {})
    _expect(isinstance(randomize, dict), where, "[randomize] must be a table")
    _expect(isinstance(tolerance, dict), where, "[tolerance] must be a table")
    return Scenario(
        name=str(data.get("name", default_name)),
        model=data["model"],
        source=source,
        description=str(data.get("description", "")),
        exercises=tuple(exercises),
        batch=_positive_int(data, "batch", Scenario.batch, where),
        steps=_positive_int(data, "steps", Scenario.steps, where),
        keyframe=keyframe,
        notes=str(data.get("notes", "")),
        energy=energy,
        randomize=_parse_randomization(randomize, where),
        tolerance=_parse_tolerances(tolerance, where),
    )


def _from_toml(path: Path) -> Scenario:
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{path}: invalid TOML: {e}") from None
    return scenario_from_dict(data, path, path.stem)


def bundled_dir() -> Path | None:
    """The directory bundled scenarios are read from, looked up on each call.

    ``$MJXDIFF_SCENARIOS`` when set and not empty, else the installed data package
    :data:`BUNDLED_PACKAGE` (a real directory in a wheel or editable install, so
    a scenario's relative ``model`` path resolves beside its TOML file); None when
    that package is not installed.

    Raises:
      ScenarioError: the package is installed but not as files on disk (a zip).
    """
    override = os.environ.get("MJXDIFF_SCENARIOS")
    if override:
        return Path(override)
    try:
        root = importlib.resources.files(BUNDLED_PACKAGE)
    except ModuleNotFoundError:
        return None
    if not isinstance(root, Path):
        raise ScenarioError(f"bundled scenarios are in {root}, not a directory; "
                            "install mjxdiff as files (pip install) or set MJXDIFF_SCENARIOS")
    return root


def _bundled_tomls() -> list[Path]:
    where = bundled_dir()
    return sorted(where.glob("*.toml")) if where is not None else []


def is_bundled(scenario: Scenario) -> bool:
    """Whether ``scenario`` is one mjxdiff ships (its TOML in :func:`bundled_dir`), not the user's."""
    where = bundled_dir()
    return (scenario.source is not None and where is not None
            and scenario.source.resolve().parent == Path(where).resolve())


def no_bundled_scenarios_message() -> str:
    """One line for a run that found no bundled scenario: where it looked, what to do."""
    override = os.environ.get("MJXDIFF_SCENARIOS")
    if override:
        where = f"MJXDIFF_SCENARIOS={override}"
    else:
        try:
            found = bundled_dir()
        except ScenarioError:
            found = None
        where = str(found) if found is not None else f"{BUNDLED_PACKAGE} (not installed)"
    return (f"no bundled scenarios found in {where}; "
            "reinstall mjxdiff or pass a scenario .toml or MJCF .xml")


def __getattr__(name: str) -> Any:
    if name == "BUNDLED_DIR":  # the former constant, now looked up when asked for
        return bundled_dir()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def bundled_scenarios() -> list[Scenario]:
    """Every scenario in :func:`bundled_dir` (``*.toml``, not subdirectories), sorted by name."""
    return sorted((_from_toml(p) for p in _bundled_tomls()), key=lambda s: s.name)


def load_scenario(ref: str | os.PathLike) -> Scenario:
    """A scenario from a bundled name, a scenario ``.toml`` path or an MJCF ``.xml`` path.

    Raises:
      ScenarioError: unknown name, missing file or invalid scenario values.
    """
    path = Path(ref)
    if path.suffix == ".toml":
        _expect(path.is_file(), str(path), "scenario file not found")
        return _from_toml(path)
    if path.suffix in (".xml", ".mjcf"):
        _expect(path.is_file(), str(path), "MJCF file not found")
        return Scenario(name=path.stem, model=str(path.resolve()), description=f"user model {path.name}")
    where = bundled_dir()
    bundled = where / f"{ref}.toml" if where is not None else None
    if bundled is not None and bundled.is_file():
        return _from_toml(bundled)
    names = [p.stem for p in _bundled_tomls()]
    import difflib

    close = difflib.get_close_matches(str(ref), names, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ScenarioError(f"unknown scenario {str(ref)!r}{hint}; run 'python -m mjxdiff list' to see them, "
                        "or pass a path to a .toml scenario or .xml model")


def _xml_error(path: Path) -> str | None:
    """Where ``path`` stops being well-formed XML, from Python's parser, or None if it is.

    MuJoCo's parser reports an element never closed at the element's opening line (line 1 for a
    file cut short), Python's where the text ends."""
    import xml.etree.ElementTree as ET
    from xml.parsers import expat

    try:
        ET.parse(path)
    except ET.ParseError as e:
        line, column = e.position
        if e.code == expat.errors.codes[expat.errors.XML_ERROR_NO_ELEMENTS]:
            return f"not well-formed XML: the file ends at line {line} with elements still open (cut short?)"
        return f"not well-formed XML: {expat.ErrorString(e.code)} at line {line}, column {column + 1}"
    return None


def load_model(scenario: Scenario) -> mujoco.MjModel:
    """Compiles the scenario's MJCF with MuJoCo C; one-line :class:`ScenarioError` on failure."""
    path = scenario.model_path
    _expect(path.is_file(), scenario.name, f"model file not found: {path}")
    try:
        m = mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        first = _xml_error(path) or " ".join(str(e).split())
        message = f"{scenario.name}: MuJoCo cannot compile {path.name}: {first}"
        later = later_feature(message)
        raise (LaterFeatureError(later) if later else ScenarioError(message)) from None
    if scenario.keyframe is not None and mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, scenario.keyframe) < 0:
        raise ScenarioError(f"{scenario.name}: keyframe {scenario.keyframe!r} not in {path.name}")
    return m
