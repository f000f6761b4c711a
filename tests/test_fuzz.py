"""Fuzzing: finds an injected MJX bug from scratch and shrinks it; no alarm on unmodified MJX;
the pytest plugin's assertion helper carries the diagnosis."""

import dataclasses

import mujoco
import pytest
from mujoco.mjx._src import smooth as mjx_smooth

from mjxdiff.engine import engines
from mjxdiff.tools.fuzz import DEFAULT_BUDGET, DEFAULT_VARIANTS, JUDGE, fuzz, known_contact_divergence, variants
from mjxdiff.input.scenario import Tolerances
from mjxdiff.testing import MJXMismatch, assert_mjx_matches_c, compare


#: The fuzzer's own judgement of a model's variants (their rollouts: no one-step check), without
#: the drill-down and the host-interface check, neither of which these tests read (each a compile).
ROLLOUTS = dataclasses.replace(JUDGE, diagnose="none", transfer=False)



def _drilled_contact(rep) -> dict:
    """The contact detail (:func:`mjxdiff.compare.diagnose.contact_detail`) of the drill-down from a
    reproducer's first state, member 0, or {}."""
    from mjxdiff.compare import diagnose

    i = rep.inputs
    return diagnose.drill_down(rep.model, i.qpos[0], i.qvel[0], i.act[0], i.ctrl[0, 0], 0.0).contact or {}

def bias_force_0p1_percent(monkeypatch):
    """Coriolis/centrifugal/gravity force 0.1% too large (any moving model shows it)."""
    orig = mjx_smooth.rne
    monkeypatch.setattr(mjx_smooth, "rne", lambda m, d, *a, **k: (lambda d: d.replace(
        qfrc_bias=d.qfrc_bias * (1 + 1e-3)))(orig(m, d, *a, **k)))


@pytest.mark.slow  # 2.5 min here: a default-budget search plus shrinking, every candidate a new compile
def test_fuzz_finds_and_shrinks_an_injected_bug(fresh_mjx, monkeypatch, tmp_path):
    bias_force_0p1_percent(monkeypatch)
    result = fuzz(budget=DEFAULT_BUDGET, out=tmp_path, seed=0, shrink_budget=60)
    assert result.failure is not None, f"not found in {result.examples} models"
    failure = result.failure
    assert failure["nbody"] <= 3 and failure["ngeom"] <= 4, failure["xml"]
    assert "qfrc_bias" in failure["message"]
    # the shrunk model still fails, with the bug, from its own saved state
    from mjxdiff.output import reproducer
    from mjxdiff.input.scenario import Tolerances
    from mjxdiff.runner.sweep import run_inputs

    rep = reproducer.load(failure["reproducer"])
    again = run_inputs("shrunk", rep.model, rep.inputs, Tolerances(), ROLLOUTS)
    assert again.status == "fail"


@pytest.mark.slow  # 8 structures of 64 variants, each a compile: about 1.5 CI minutes
def test_fuzz_on_unmodified_mjx_finds_nothing(tmp_path):
    """8 generated structures, a count always reached (the budget is far beyond it, so it ends by
    its count, never the clock), pass or are set aside by a measured signature (those set aside,
    neither a pass nor a find, counted apart); nothing is flagged, nothing written as a
    reproducer, and the harness never fails."""
    result = fuzz(budget=1800, out=tmp_path, seed=1, max_examples=8)
    assert result.harness_error is None, result.harness_traceback
    assert result.failure is None, result.failure and (result.failure["message"] + "\n" + result.failure["xml"])
    assert result.structures - sum(result.set_aside.values()) == 8, (result.structures, result.set_aside)
    assert result.examples == DEFAULT_VARIANTS * result.structures
    assert not (tmp_path / "reproducers").exists()


def test_variants_are_one_structure_and_start_above_the_floor():
    """A structure's variants differ in parameters, state and controls, never in structure,
    and none starts sunk into another geom (C and MJX legitimately part there)."""
    import numpy as np

    from mjxdiff.tools.fuzz import MAX_INITIAL_PENETRATION, variants

    m = mujoco.MjModel.from_xml_string(SUNK)
    inputs = variants(m, seed=0, batch=16, steps=10, qpos_noise=0.5, spread=0.3)
    assert {mi.nbody for mi in inputs.models} == {m.nbody} and len({id(mi) for mi in inputs.models}) == 16
    assert np.ptp(np.stack([mi.body_mass for mi in inputs.models]), axis=0)[1] > 0, "masses vary"
    assert np.ptp(inputs.qpos, axis=0).max() > 0.1, "states vary"
    for mi, q in zip(inputs.models, inputs.qpos):
        d = mujoco.MjData(mi)
        d.qpos[:] = q
        mujoco.mj_forward(mi, d)
        assert d.ncon == 0 or d.contact.dist[:d.ncon].min() >= -MAX_INITIAL_PENETRATION


SUNK = """<mujoco><worldbody><geom type="plane" size="0 0 1"/>
  <body pos="0 0 0.12"><joint type="slide" axis="0 0 1"/><geom type="cylinder" size="0.05 0.05"/></body>
  </worldbody></mujoco>"""


PENDULUM = """<mujoco><option timestep="0.002"/><worldbody>
  <body pos="0 0 1"><joint name="swing" type="hinge" axis="0 1 0" damping="0.1"/>
  <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.03" mass="1"/></body></worldbody>
  <actuator><motor name="m" joint="swing" ctrlrange="-1 1"/></actuator></mujoco>"""


def test_assert_helper_passes_unmodified_and_explains_a_bug(fresh_mjx, monkeypatch, mjx_matches_c):
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    assert mjx_matches_c is assert_mjx_matches_c  # the plugin's fixture
    result = mjx_matches_c(m, qpos=[0.5], ctrl=[[0.3]] * 100)
    assert result.status == "pass"
    bias_force_0p1_percent(monkeypatch)
    engines.clear_compiled()
    with pytest.raises(MJXMismatch, match=r"joint 'swing'.*first field to differ: qfrc_bias") as info:
        mjx_matches_c(m, qpos=[0.5], ctrl=[[0.3]] * 100)
    assert info.value.result.status == "fail"


def test_compare_batches_states():
    m = mujoco.MjModel.from_xml_string(PENDULUM)
    result = compare(m, qpos=[[0.1], [0.2], [0.3]], steps=50)
    assert result.status == "pass" and result.info["batch"] == 3


def test_only_the_contact_frame_divergence_is_excused(fresh_mjx, monkeypatch):
    """The fuzzer leaves out a divergence only on its measured signature (MJX's contact at C's
    place with another tangent, under a pyramidal cone, and nothing else once MJX has C's frame):
    the committed find has it; a 0.1% bias force bug on a sphere, a cylinder and a capsule lying on
    a plane shows the turned tangent too, yet is not excused (it was, before MJX given C's frames
    had to reproduce C)."""
    from pathlib import Path

    from mjxdiff.tools import fuzz as fuzz_module
    from mjxdiff.output import reproducer
    from mjxdiff.runner.sweep import run_inputs

    config = ROLLOUTS
    rep = reproducer.load(Path(__file__).parent / "data" / "fuzz_capsule_plane_frame.json")
    known = run_inputs("fuzz", rep.model, rep.inputs, rep.tolerances, config)
    assert known.status == "fail"
    assert known_contact_divergence(rep.model, rep.inputs, known) == "contact tangent frames"

    bias_force_0p1_percent(monkeypatch)
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><option cone='pyramidal'/><worldbody><geom type='plane' size='2 2 .1'/>"
        "<body pos='0 0 0.1'><freejoint/><geom size='0.1'/></body>"
        "<body pos='0.5 0 0.1'><freejoint/><geom type='cylinder' size='0.1 0.05'/></body>"
        "<body pos='-0.5 0 0.045' euler='1.4 0.3 0.7'><freejoint/><geom type='capsule' size='0.05 0.1'/></body>"
        "</worldbody></mujoco>")
    inputs = variants(m, 0, 4, 40, qvel_noise=1.0)
    bug = run_inputs("fuzz", m, inputs, Tolerances(), config)
    assert bug.status == "fail" and bug.first_divergence, bug.message
    assert known_contact_divergence(m, inputs, bug) is None, bug.message
    monkeypatch.setattr(fuzz_module, "_c_contacts_explain", lambda *args: True)
    assert known_contact_divergence(m, inputs, bug) == "contact tangent frames", "the tangent turned there"


#: An ellipsoid resting 4 mm deep on a cylinder fixed in the world: a pair MJX collides by SDF
#: descent, in contact from the first step.
ELLIPSOID_ON_CYLINDER = """<mujoco><option cone="pyramidal"/><worldbody>
  <geom type="cylinder" size="0.1 0.1" pos="0 0 0.1"/>
  <body pos="0.03 0 0.266" euler="0.3 0.2 0"><freejoint/><geom type="ellipsoid" size="0.12 0.08 0.07"/></body>
  </worldbody></mujoco>"""


def test_only_the_sdf_contact_divergence_is_excused(fresh_mjx, monkeypatch):
    """A divergence of a pair MJX collides by SDF descent is set aside only where MJX, given C's
    contacts for those pairs, reproduces C's qacc and sensors: the committed ellipsoid-cylinder
    find (at its first contact C 2.882 mm deep, MJX 1.354 mm, qacc 99 apart) has it; a 0.1%
    bias-force bug on an ellipsoid resting on a cylinder diverges where their contacts differ
    too, yet is not excused (unmodified, that model is)."""
    from pathlib import Path

    from mjxdiff.tools import fuzz as fuzz_module
    from mjxdiff.output import reproducer
    from mjxdiff.runner.sweep import run_inputs

    config = ROLLOUTS
    rep = reproducer.load(Path(__file__).parent / "data" / "fuzz_ellipsoid_cylinder_contact.json")
    known = run_inputs("fuzz", rep.model, rep.inputs, rep.tolerances, config)
    assert known.status == "fail" and known.first_divergence is not None, known.message
    assert known.first_divergence["step"] == 25  # its first contact
    assert known_contact_divergence(rep.model, rep.inputs, known) == "convex pairs by SDF descent"

    bias_force_0p1_percent(monkeypatch)
    m = mujoco.MjModel.from_xml_string(ELLIPSOID_ON_CYLINDER)
    inputs = variants(m, 0, 4, 5)
    bug = run_inputs("fuzz", m, inputs, Tolerances(), config)
    assert bug.status == "fail" and bug.first_divergence is not None, bug.message
    assert known_contact_divergence(m, inputs, bug) is None, bug.message
    monkeypatch.setattr(fuzz_module, "_c_contacts_explain", lambda *args: True)
    assert known_contact_divergence(m, inputs, bug) == "convex pairs by SDF descent", "its contact differs there"


def test_only_the_regularized_capsule_divergence_is_excused(fresh_mjx, monkeypatch):
    """A capsule-capsule contact is set aside only where C's is the exact closest points and
    MJX's the same with its 1e-6 regularization (mjxdiff.compare.segments), and nothing else differs: the
    CI find of fuzz seed 1 (normal 4.3e-6 apart, qvel 0.002 at step 0) has it; the same model
    with MJX's segment points moved by 1e-7 m (less than the regularization's own effect) is no
    longer excused."""
    from pathlib import Path

    from mujoco.mjx._src import math as mjx_math

    from mjxdiff.output import reproducer
    from mjxdiff.compare import segments
    from mjxdiff.runner.sweep import run_inputs

    config = ROLLOUTS
    rep = reproducer.load(Path(__file__).parent / "data" / "fuzz_capsule_capsule_contact.json")
    known = run_inputs("fuzz", rep.model, rep.inputs, rep.tolerances, config)
    assert known.status == "fail" and known.first_divergence is not None, known.message
    assert (known.first_divergence["step"], known.first_divergence["object"]) == (0, "joint 'j1'")
    assert known_contact_divergence(rep.model, rep.inputs, known) == "capsule segment solves"
    # the sweep's drill-down tells it too, as data the catalogue reads (capsule-regularisation)
    assert _drilled_contact(rep).get("explained") == "segment regularisation", _drilled_contact(rep)

    orig = mjx_math.closest_segment_to_segment_points
    monkeypatch.setattr(mjx_math, "closest_segment_to_segment_points",
                        lambda *a: (lambda pa, pb: (pa, pb + 1e-7))(*orig(*a)))
    bug = run_inputs("fuzz", rep.model, rep.inputs, rep.tolerances, config)
    assert bug.status == "fail" and bug.first_divergence is not None, bug.message
    assert known_contact_divergence(rep.model, rep.inputs, bug) is None, bug.message
    assert _drilled_contact(rep) and "explained" not in _drilled_contact(rep), _drilled_contact(rep)
    monkeypatch.setattr(segments, "explains", lambda *args: True)
    assert known_contact_divergence(rep.model, rep.inputs, bug) == "capsule segment solves", "only the formulas refuse"
