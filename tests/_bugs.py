"""The one scaffold of the sweep-level injected-bug tests: *reaches, catches, passes clean*.

A bug is ``bug(mp: pytest.MonkeyPatch) -> None``: it patches one function inside
``mujoco.mjx._src`` for as long as ``mp`` is active (:func:`model_edited` builds the common kind,
MJX reading one model parameter wrong). :func:`sweep` runs a scenario with a bug applied, the
compiled rollouts cleared around it so the patch is traced and nothing patched outlives it.
:func:`caught` is the whole proof of a catch: the scenario at that config passes unmodified
(:func:`clean`, once per scenario and config in a test process), and with the bug it fails
naming the field and the object the bug must produce (:class:`Expect`), at a step inside the
rollout, beyond its tolerance. :func:`mutant` builds the other kind, a source-mutation audit's
slip: a function recompiled from its source with one line changed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import re
import textwrap
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco.mjx._src.types import Model

from mjxdiff.engine import engines
from mjxdiff.runner import sweep as sweep_module
from mjxdiff.input.scenario import Scenario, load_scenario
from mjxdiff.runner.sweep import ScenarioResult, SweepConfig, run_scenario

Bug = Callable[[pytest.MonkeyPatch], None]


def _undecorated(fn):
    """The function a decorator wraps (``collision_convex.collider`` and ``named_scope`` keep it
    in their closure)."""
    inner = [c.cell_contents for c in fn.__closure__ or () if inspect.isfunction(c.cell_contents)]
    return inner[0] if inner else fn


def mutant(module, fn, old: str, new: str):
    """``fn`` (of ``module``) compiled from its source with its one line ``old`` (stripped) now
    ``new``, decorators included: a source-mutation audit's one-line slip, to patch in."""
    lines = textwrap.dedent(inspect.getsource(_undecorated(fn))).splitlines(keepends=True)
    hits = [i for i, line in enumerate(lines) if line.strip() == old]
    assert len(hits) == 1, f"{fn.__name__}: {old!r} found {len(hits)} times (MJX changed?)"
    i = hits[0]
    lines[i] = lines[i][:len(lines[i]) - len(lines[i].lstrip())] + new + "\n"
    namespace = dict(vars(module))
    exec(compile("".join(lines), inspect.getsourcefile(module), "exec"), namespace)
    return namespace[_undecorated(fn).__name__]


def model_edited(mp: pytest.MonkeyPatch, module, name: str, edit: Callable) -> None:
    """Patches ``module.name(m, d, *args)`` to run on ``edit(m)``: MJX reading a parameter wrong."""
    orig = getattr(module, name)
    mp.setattr(module, name, lambda m, d, *args: orig(edit(m), d, *args))


@dataclasses.dataclass(frozen=True)
class Expect:
    """What a catch must name. ``fields``: the first divergent field is one of these (``qpos``,
    ``qvel``, ``act``, ``sensordata``, ``contacts``); ``object``: a regular expression the
    first divergence's object (``"joint 'hinge'"``, ``"sensor 'r' (rangefinder)"``) matches
    in full."""

    fields: tuple[str, ...]
    object: str = ".*"


def _scenario(scenario: str | Scenario) -> Scenario:
    return load_scenario(scenario) if isinstance(scenario, str) else scenario


def _gate(args, kwargs) -> jax.Array:
    models = [a for a in (*args, *kwargs.values()) if isinstance(a, Model)]
    assert models, "a switched bug patches a function that is given no mjx.Model: switch it off (among=())"
    return models[0].opt._impl.o_margin


def _select(on: jax.Array, new, old):
    """``new`` where ``on``, else ``old``, leaf by leaf; static leaves must agree."""
    def pick(a, b):
        if a is b or (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and np.array_equal(a, b)):
            return a
        if isinstance(a, (jax.Array, np.ndarray)) or isinstance(b, (jax.Array, np.ndarray)):
            return jnp.where(on, a, b)
        assert a == b, f"a switched bug changes a static value: {a!r} != {b!r}"
        return a
    return jax.tree.map(pick, new, old)


def _switched(k: int, new: Callable, old: Callable) -> Callable:
    def either(*args, **kwargs):
        return _select(_gate(args, kwargs) == k, new(*args, **kwargs), old(*args, **kwargs))
    either.__dict__.update(getattr(new, "__dict__", {}))  # what MJX reads off a collider (ncon)
    return either


def install_switched(mp: pytest.MonkeyPatch, bugs: Sequence[Bug]) -> None:
    """Every one of ``bugs`` patched at once, bug ``bugs[k - 1]`` live only where the model's
    ``opt.o_margin`` is ``k`` (0: none; MJX never reads ``o_margin``, and C only with the override
    flag enabled). Each patched function computes the bug's output and the unpatched one and
    selects at run time, so one compile serves the whole set: the patched code, and so the
    artifact's key, is the same whichever bug is live. Bugs of one function nest (each traces
    the one before twice): the bundled sets patch any function at most twice."""
    for k, bug in enumerate(bugs, start=1):
        with pytest.MonkeyPatch.context() as probe:  # what the bug sets, then undone
            bug(probe)
            patched = [(target, name, getattr(target, name), False) for target, name, _ in probe._setattr]
            patched += [(target, name, target[name], True) for target, name, _ in probe._setitem]
        for target, name, new, item in patched:
            old = target[name] if item else getattr(target, name)
            (mp.setitem if item else mp.setattr)(target, name, _switched(k, new, old))


def _position(bug: Bug | None, among: Sequence[Bug]) -> int:
    """The ``opt.o_margin`` that makes ``bug`` the live one of :func:`install_switched`'s set (0: none)."""
    return 0 if bug is None else list(among).index(bug) + 1


@contextlib.contextmanager
def live(bug: Bug, among: Sequence[Bug], models: Sequence):
    """Within the block, every bug of ``among`` installed switched (:func:`install_switched`),
    ``bug`` live on ``models`` (C models: their ``opt.o_margin`` set, and restored after)."""
    k = _position(bug, among)
    before = [mi.opt.o_margin for mi in models]
    with pytest.MonkeyPatch.context() as mp:
        install_switched(mp, among)
        try:
            for mi in models:
                mi.opt.o_margin = k
            yield
        finally:
            for mi, value in zip(models, before):
                mi.opt.o_margin = value


def sweep(scenario: str | Scenario, config: SweepConfig, bug: Bug | None = None,
          among: Sequence[Bug] = ()) -> ScenarioResult:
    """``run_scenario`` with ``bug`` applied (None: unmodified MJX), traced afresh. With
    ``among`` (holding ``bug``), every bug of it is installed switched (:func:`install_switched`)
    and only ``bug`` live (None: none live): the tests of one set share one compiled rollout
    through the compile cache."""
    with pytest.MonkeyPatch.context() as mp:
        if among:
            install_switched(mp, among)
            live, load = _position(bug, among), sweep_module.load_model

            def load_live(s):
                m = load(s)
                m.opt.o_margin = live
                return m
            mp.setattr(sweep_module, "load_model", load_live)
        elif bug is not None:
            bug(mp)
        engines.clear_compiled()
        try:
            return run_scenario(_scenario(scenario), config)
        finally:
            engines.clear_compiled()


_CLEAN: dict[tuple[str, SweepConfig], ScenarioResult] = {}


def clean(scenario: str | Scenario, config: SweepConfig) -> ScenarioResult:
    """The unmodified sweep of ``scenario`` at ``config``, run once per test process."""
    s = _scenario(scenario)
    key = (repr(s), config)
    if key not in _CLEAN:
        _CLEAN[key] = sweep(s, config)
    return _CLEAN[key]


def assert_passes_clean(scenario: str | Scenario, config: SweepConfig) -> None:
    result = clean(scenario, config)
    assert result.status == "pass", f"the control fails: unmodified MJX on {result.name}: {result.message}"


def assert_names(result: ScenarioResult, expect: Expect, what: str) -> dict:
    """``result`` is a fail whose first divergence names ``expect``'s field and object, at a step
    inside the rollout, with an error above its tolerance. Returns the first divergence."""
    assert result.status == "fail", f"{what} not caught by {result.name}: {result.message}"
    first = result.first_divergence
    assert first is not None, result.message
    assert first["field"] in expect.fields, f"{what}: named {first['field']}, expected {expect.fields}: {first}"
    assert re.fullmatch(expect.object, first["object"]), f"{what}: named {first['object']!r}: {first}"
    assert 0 <= first["step"] < result.info["steps"], first
    assert first["error"] > first["tolerance"], first
    return first


def caught(bug: Bug, scenario: str | Scenario, config: SweepConfig, expect: Expect,
           among: Sequence[Bug] = ()) -> dict:
    """The proof of one catch: ``scenario`` at ``config`` passes unmodified, and fails with
    ``bug`` (live among the switched set ``among``, if given) naming ``expect``. Returns the
    first divergence."""
    assert_passes_clean(scenario, config)
    return assert_names(sweep(scenario, config, bug, among), expect, bug.__name__)
