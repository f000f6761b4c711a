"""Differential fuzzing: Hypothesis generates models, states and controls; a
divergence is shrunk to a minimal MJCF and saved as a reproducer.

The property: for a generated MJX-supported model and a batch of initial
states and control sequences of that one model (so one compile serves the
batch), MJX and C rollouts agree under the same verdict as the sweep
(tolerance floors and the chaos envelope). A failure is shrunk by Hypothesis
(fewer bodies and geoms, default options, zero velocities, shorter horizons),
and Hypothesis's example database keeps it so the next run tries it first.

Only the property's own divergence signal counts as a find: any other exception
raised while generating, simulating or judging an example stops the run and is
reported (:attr:`FuzzResult.harness_error`), never read as "no divergence".

Features whose C/MJX divergence is already known and documented (see
:data:`KNOWN_DIVERGENCES` and the scenario notes) are left out unless
``include_known`` is set, so that an unmodified MJX gives no alarm.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import traceback
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, Phase, assume, given, note, seed as hseed, settings
from hypothesis import strategies as st
from hypothesis.database import DirectoryBasedExampleDatabase
from hypothesis.errors import Flaky, HypothesisException

from mjxdiff import report, reproducer, strategies
from mjxdiff.inputs import BatchedInputs
from mjxdiff.scenario import Tolerances
from mjxdiff.sweep import release_compiled_if_crowded
from mjxdiff.verdict import ScenarioResult

__all__ = ["DEFAULT_BUDGET", "KNOWN_DIVERGENCES", "FuzzResult", "fuzz", "model_strategy"]

#: Seconds of generation before the fuzzer stops looking (shrinking a found failure may take longer).
DEFAULT_BUDGET = 60.0

#: Features left out by default because C 4.0.0 and MJX 3.17.0 are known to differ on them.
KNOWN_DIVERGENCES = {
    "connect/weld equality": "efc_aref of equality rows differs (scenarios/equality.toml notes)",
    "RK4, implicitfast": "free/ball rotation and RK4 sensordata differ (scenarios/integrator_*.toml notes)",
    "box and mesh geoms": "box-box contact points differ (scenarios/box_stack.toml notes)",
}


@dataclasses.dataclass(frozen=True)
class FuzzResult:
    """What a fuzzing run found.

    Attributes:
      examples: models tried (each with a batch of states and controls).
      seconds: wall time.
      failure: None, or the shrunk failing example: ``xml``, ``nbody``,
        ``ngeom``, ``features``, ``message`` and ``reproducer`` (path or None).
      harness_error: None, or ``"ExcType: message"`` (one line) of an exception
        raised by the fuzzing harness itself (generation, the engines, the
        verdict, Hypothesis), which stopped the run: then nothing can be
        concluded about divergence from the examples tried.
      harness_traceback: the full traceback text of ``harness_error``.
      harness_example: MJCF of the generated model being tried when the harness
        failed (None if it failed before a model was drawn).
    """

    examples: int
    seconds: float
    failure: dict[str, Any] | None
    harness_error: str | None = None
    harness_traceback: str | None = None
    harness_example: str | None = None


class _Divergence(AssertionError):
    """The property's own signal: MJX and C disagree on this example (the only exception that is a find)."""


class _HarnessFailure(BaseException):
    """Carries an exception raised by the harness out of Hypothesis at once.

    Not an :class:`Exception`, so Hypothesis neither shrinks it nor mistakes it
    for a failing example (as it does with :class:`KeyboardInterrupt`).
    """

    def __init__(self, error: BaseException):
        super().__init__(error)
        self.error = error


def _is_find(e: BaseException) -> bool:
    """Whether ``e``, raised by the Hypothesis run, is only the property's divergence signal."""
    if isinstance(e, _Divergence):
        return True
    return isinstance(e, BaseExceptionGroup) and not isinstance(e, Flaky) and all(map(_is_find, e.exceptions))


def model_strategy(include_known: bool = False, max_bodies: int = 3) -> st.SearchStrategy:
    """MJX-supported models; without ``include_known``, none of :data:`KNOWN_DIVERGENCES`."""
    if include_known:
        return strategies.mjcf_models(max_bodies=max_bodies)
    options = st.fixed_dictionaries({
        "integrator": st.just("Euler"),
        "timestep": st.sampled_from([0.002, 0.005]),
        "cone": st.sampled_from(["pyramidal", "elliptic"]),
    })
    return strategies.mjcf_models(max_bodies=max_bodies, geom_types=("sphere", "capsule", "ellipsoid", "cylinder"),
                                  equality=False, options=options)


def _divergence(xml: str, qpos, qvel, act, ctrl, config) -> ScenarioResult:
    from mjxdiff.sweep import run_inputs

    m = strategies.MjcfModel(xml=xml, nbody=0, ngeom=0, features=(), unsupported_feature=None).model()
    inputs = BatchedInputs(qpos=qpos, qvel=qvel, act=act, ctrl=ctrl, models=(m,) * len(qpos), factors={}, seed=0)
    return run_inputs("fuzz", m, inputs, Tolerances(), config)


def is_divergence(result: ScenarioResult) -> bool:
    """Whether a generated example's verdict is a find: anything but a pass, except MuJoCo C
    itself blowing up (``error``/``unstable``: an unstable model, whatever MJX did) and MJX
    refusing the model (``unsupported``)."""
    unstable = result.status == "error" and result.error_kind == "unstable"
    return result.status != "pass" and not unstable and result.status != "unsupported"


def fuzz(max_examples: int = 300, seed: int = 0, budget: float = DEFAULT_BUDGET, out: str | Path | None = None,
         database: str | Path | None = None, include_known: bool = False, batch: int = 4,
         steps: int = 40, progress: bool = False, shrink_budget: float | None = None) -> FuzzResult:
    """Runs the differential property until a divergence, ``max_examples`` or ``budget`` seconds.

    Args:
      max_examples: most models to try.
      seed: Hypothesis seed (same seed and database, same sequence).
      budget: seconds of generation; once spent, further examples are skipped.
      out: directory for the reproducer of a found divergence.
      database: Hypothesis example database directory (default ``out/.hypothesis``
        or ``~/.cache/mjxdiff/hypothesis``).
      include_known: also generate features with known divergences.
      batch: states and control sequences per model (one compile each).
      steps: longest horizon (Hypothesis shrinks toward 10).
      shrink_budget: seconds allowed for shrinking a find (default max(120, 2 x budget));
        each shrink candidate is a new model structure, hence a new compile.
    """
    from mjxdiff.sweep import SweepConfig

    config = SweepConfig(diagnose="basic")
    db_dir = Path(database) if database else (Path(out) / ".hypothesis" if out else
                                              Path.home() / ".cache" / "mjxdiff" / "hypothesis")
    t0 = time.perf_counter()
    shrink_budget = max(120.0, 2 * budget) if shrink_budget is None else shrink_budget
    seen = {"examples": 0, "last_failure": None, "xml": None}

    @hseed(seed)
    @settings(max_examples=max_examples, deadline=None, database=DirectoryBasedExampleDatabase(str(db_dir)),
              suppress_health_check=list(HealthCheck), phases=[Phase.reuse, Phase.generate, Phase.shrink],
              derandomize=False, print_blob=False)
    @given(data=st.data())
    def property_(data):
        seen["xml"] = None
        try:
            example(data)
        except (_Divergence, HypothesisException):  # a find, or Hypothesis's control flow (assume)
            raise
        except Exception as e:  # the harness itself failed: stop, and say so
            raise _HarnessFailure(e) from e

    def example(data):
        mj = data.draw(model_strategy(include_known), label="model")
        seen["xml"] = mj.xml
        m = mj.model()
        horizon = data.draw(st.integers(10, steps), label="steps")
        state = data.draw(strategies.initial_states(m, batch=batch), label="state")
        ctrl = data.draw(strategies.control_sequences(m, horizon, batch=batch), label="ctrl")
        # Out of time: pass without simulating (drawing stays deterministic, which Hypothesis
        # checks). While shrinking a find, allow shrink_budget more; the smallest failure so
        # far is kept in `seen`.
        searching = seen["last_failure"] is None
        if time.perf_counter() - t0 > (budget if searching else budget + shrink_budget):
            return
        seen["examples"] += searching
        if progress:
            print(f"[fuzz] example {seen['examples']}: {mj.nbody} bodies, {mj.ngeom} geoms, {horizon} steps"
                  f" ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        release_compiled_if_crowded()  # every generated structure compiles anew
        result = _divergence(mj.xml, state.qpos, state.qvel, state.act, ctrl, config)
        if not is_divergence(result):
            assume(result.status == "pass")  # C blew up or MJX refused the model: not a divergence either
            return
        seen["last_failure"] = dict(mj=mj, state=state, ctrl=ctrl, result=result)
        note(mj.xml)
        raise _Divergence(result.message)

    harness: BaseException | None = None
    example_xml = None
    try:
        property_()
    except _HarnessFailure as e:
        harness, example_xml = e.error, seen["xml"]
    except Flaky as e:
        # with a find: its final replay came after the shrink budget and passed; without one,
        # an exception was raised once and not again, by the harness
        if seen["last_failure"] is None:
            harness = e
    except Exception as e:
        if not _is_find(e):  # e.g. Hypothesis's Unsatisfiable: no conclusion either
            harness = e
    seconds = time.perf_counter() - t0
    errors = {}
    if harness is not None:
        errors = dict(harness_error=" ".join(f"{type(harness).__name__}: {harness}".split()),
                      harness_traceback="".join(traceback.format_exception(harness)), harness_example=example_xml)
    found = seen["last_failure"]
    if found is None:
        return FuzzResult(seen["examples"], seconds, None, **errors)
    mj, result = found["mj"], found["result"]
    path = None
    if out is not None:
        m = mj.model()
        inputs = BatchedInputs(qpos=found["state"].qpos, qvel=found["state"].qvel, act=found["state"].act,
                               ctrl=found["ctrl"], models=(m,) * batch, factors={}, seed=seed)
        member = max(result.first_divergence["member"], 0) if result.first_divergence else 0
        path = reproducer.save(report.path_under(Path(out) / "reproducers", "fuzz.json"), "fuzz", member, inputs,
                               mj.xml, Tolerances(), config.as_dict(), report.result_dict(result), report.versions())
    return FuzzResult(seen["examples"], seconds, dict(
        xml=mj.xml, nbody=mj.nbody, ngeom=mj.ngeom, features=list(mj.features), message=result.message,
        status=result.status, reproducer=str(path) if path else None), **errors)
