"""The verdict streamed in pieces is the verdict on whole trajectories.

The judge keeps only per-member running values, so that memory does not grow
with the horizon; these tests hold it to the whole-trajectory answer. The
unit tests take a real C rollout as the reference and, as the MJX side, the
same rollout with errors injected at known members and steps, so the expected
verdict is known exactly; the last test runs both engines for real.
"""

import dataclasses

import jax
import numpy as np
import pytest

from mjxdiff.engines import CEngine, Trajectory, concat
from mjxdiff.inputs import make_inputs
from mjxdiff.noise import NoiseFloor, perturb
from mjxdiff.scenario import load_model, load_scenario
from mjxdiff.sweep import SweepConfig, run_inputs
from mjxdiff.verdict import Judge, judge, rangefinder_mask

B, T = 6, 40


@pytest.fixture(scope="module")
def lidar():
    """A real C rollout of the lidar scenario (rangefinders with misses, slide and hinge joints, contacts)."""
    scenario = load_scenario("lidar")
    m = load_model(scenario)
    inputs = dataclasses.replace(make_inputs(scenario, m, 0, B, T), energy=True)
    c = CEngine()
    return scenario, m, inputs, c.rollout(inputs), c.rollout(perturb(inputs, "float64"))


def _with_bugs(traj: Trajectory) -> Trajectory:
    """``traj`` with a qvel error from step 23 in member 2, a sensor error from step 9 in
    member 4, a contact-count mismatch at step 31 in member 1 and a NaN blow-up in member 5."""
    qvel, sens = traj.qvel.copy(), traj.sensordata.copy()
    ncon, qpos = traj.ncon.copy(), traj.qpos.copy()
    qvel[2, 23:, 1] += 1e-3
    sens[4, 9:, 0] += 5e-2
    ncon[1, 31] += 1
    qpos[5, 17:] = np.nan
    diverged = traj.diverged_at.copy()
    diverged[5] = 17
    return dataclasses.replace(traj, qvel=qvel, sensordata=sens, ncon=ncon, qpos=qpos, diverged_at=diverged)


def _pieces(traj: Trajectory, k: int) -> list[Trajectory]:
    out = []
    for start in range(0, traj.time.shape[1], k):
        cut = {f.name: getattr(traj, f.name)[:, start:start + k] for f in dataclasses.fields(Trajectory)
               if f.name != "diverged_at"}
        at = traj.diverged_at
        inside = (at >= start) & (at < start + k)
        out.append(Trajectory(**cut, diverged_at=np.where(inside | (at >= 0) & (at < start), at, -1)))
    return out


def _streamed(m, tol, traj_c, traj_mjx, perturbed, k, threshold=0.95, groups=(slice(None),)):
    """The verdict from pieces of k steps, member group by member group."""
    j = Judge(m, tol, *traj_c.time.shape)
    floor = NoiseFloor(m, rangefinder_mask(m), *traj_c.time.shape) if perturbed is not None else None
    for members in groups:
        rows = lambda traj: None if traj is None else jax.tree.map(lambda x: x[members], traj)
        pieces = [_pieces(rows(t), k) if t is not None else [None] * T for t in (traj_c, traj_mjx, perturbed)]
        for i, (c, x, p) in enumerate(zip(*pieces)):
            j.update(c, x, floor.update(p, c, i * k, members) if floor else None, i * k, members)
    return j.result("lidar", threshold, floor)


def _assert_same(a, b):
    assert (a.status, a.message, a.error_kind) == (b.status, b.message, b.error_kind)
    assert a.first_divergence == b.first_divergence
    assert a.diverged_members == b.diverged_members
    assert a.pass_rate == b.pass_rate
    for fa, fb in zip(a.fields, b.fields, strict=True):
        assert (fa.field, fa.first_step, fa.member, fa.object) == (fb.field, fb.first_step, fb.member, fb.object)
        numbers = lambda f: (f.max_error, f.tolerance, f.growth_rate, f.envelope, f.ratio)
        assert numbers(fa) == pytest.approx(numbers(fb), rel=1e-12, abs=0), fa.field
    assert a.noise_rate == pytest.approx(b.noise_rate, rel=1e-12)
    for engine in ("c", "mjx"):
        assert a.behaviour[engine] == pytest.approx(b.behaviour[engine], rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("envelope", [False, True], ids=["fixed", "envelope"])
@pytest.mark.parametrize("k", [1, 7, T])
def test_streamed_verdict_equals_whole(lidar, envelope, k):
    scenario, m, _, traj_c, perturbed = lidar
    bugged = _with_bugs(traj_c)
    whole = judge("lidar", m, traj_c, bugged, scenario.tolerance, perturbed=perturbed if envelope else None)
    _assert_same(_streamed(m, scenario.tolerance, traj_c, bugged, perturbed if envelope else None, k), whole)


@pytest.mark.parametrize("groups", [[slice(0, 3), slice(3, 6)], [np.array([4, 0]), np.array([5, 1, 2, 3])]],
                         ids=["halves", "shuffled"])
def test_member_groups_give_the_whole_verdict(lidar, groups):
    scenario, m, _, traj_c, perturbed = lidar
    bugged = _with_bugs(traj_c)
    whole = judge("lidar", m, traj_c, bugged, scenario.tolerance, perturbed=perturbed)
    _assert_same(_streamed(m, scenario.tolerance, traj_c, bugged, perturbed, 7, groups=groups), whole)


def test_verdict_names_the_injected_errors(lidar):
    scenario, m, _, traj_c, _ = lidar
    tol = scenario.tolerance
    result = _streamed(m, tol, traj_c, _with_bugs(traj_c), None, 7, threshold=1.0)
    assert result.status == "error" and result.diverged_members == (
        dict(engine="mjx", member=5, step=17, time=round(18 * float(m.opt.timestep), 9)),)
    qvel, sens, contacts = (result.field(f) for f in ("qvel", "sensordata", "contacts"))
    assert (qvel.first_step, qvel.member, qvel.max_error) == (23, 2, pytest.approx(1e-3))
    assert (sens.first_step, sens.member) == (9, 4)
    assert contacts.member == 1 and contacts.max_error == pytest.approx(1 / T)
    assert result.pass_rate == pytest.approx(1 - 2 / 5)  # members 2 and 4 of the 5 healthy ones


def test_unbugged_passes_in_pieces(lidar):
    scenario, m, _, traj_c, perturbed = lidar
    result = _streamed(m, scenario.tolerance, traj_c, traj_c, perturbed, 7)
    assert result.status == "pass" and result.pass_rate == 1.0
    assert all(f.max_error == 0 for f in result.fields)


def test_piece_boundaries_do_not_change_a_real_comparison(monkeypatch, fresh_mjx):
    """Both engines for real, a 0.1% damping bug in MJX: the same verdict from one piece of the
    whole batch and from 13-step pieces of two member groups (3 members and 1 padded to 3)."""
    from tests.test_detection import extra_damping

    extra_damping(monkeypatch)
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, 0, 4, 100)
    results = [run_inputs("pendulum", m, inputs, scenario.tolerance,
                          SweepConfig(diagnose="none", piece_steps=k, group_size=g)) for k, g in ((100, 4), (13, 3))]
    assert results[0].status == "fail"
    assert (results[1].info["groups"], results[1].info["pieces"]) == (2, 16)
    _assert_same(*results)


def test_streams_concatenate_to_the_rollout(lidar):
    _, _, inputs, traj_c, _ = lidar
    pieces = list(CEngine().stream(inputs, 9))
    assert [p.time.shape[1] for p in pieces] == [9, 9, 9, 9, 4]
    whole = concat(pieces)
    for f in dataclasses.fields(Trajectory):
        np.testing.assert_array_equal(getattr(whole, f.name), getattr(traj_c, f.name))
