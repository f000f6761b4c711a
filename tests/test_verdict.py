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

from mjxdiff.engine.engines import CEngine, Trajectory, concat
from mjxdiff.input.inputs import make_inputs
from mjxdiff.compare.noise import NoiseFloor, perturb
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, run_inputs
from mjxdiff.compare.verdict import Judge, judge, rangefinder_mask

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
    member 4, a contact in another geom pair at step 31 in member 1 (its pair sums changed: the
    count is the same) and a NaN blow-up in member 5."""
    qvel, sens = traj.qvel.copy(), traj.sensordata.copy()
    pair_sums, qpos = traj.pairs.copy(), traj.qpos.copy()
    qvel[2, 23:, 1] += 1e-3
    sens[4, 9:, 0] += 5e-2
    pair_sums[1, 31] += np.uint32(12345)
    qpos[5, 17:] = np.nan
    diverged = traj.diverged_at.copy()
    diverged[5] = 17
    return dataclasses.replace(traj, qvel=qvel, sensordata=sens, pairs=pair_sums, qpos=qpos, diverged_at=diverged)


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
        assert numbers(fa) == pytest.approx(numbers(fb), rel=1e-12, abs=0, nan_ok=True), fa.field
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
    # MJX non-finite where C is finite: the strongest divergence, a fail naming step and fields
    assert result.status == "fail" and result.diverged_members == (
        dict(engine="mjx", member=5, step=17, time=round(18 * float(m.opt.timestep), 9), last_finite_step=16,
             nonfinite_fields=["qpos"], finite_fields=["qvel", "act", "sensordata"]),)
    assert "MJX goes non-finite at step 17" in result.message and "last finite step 16" in result.message
    assert "non-finite: qpos" in result.message
    qpos, qvel, sens, contacts = (result.field(f) for f in ("qpos", "qvel", "sensordata", "contacts"))
    assert (qpos.first_step, qpos.member) == (17, 5) and np.isnan(qpos.max_error)
    assert (qvel.first_step, qvel.member, qvel.max_error) == (23, 2, pytest.approx(1e-3))
    assert (sens.first_step, sens.member) == (9, 4)
    # no contact mismatch is allowed by default: one step in another pair fails member 1
    assert (contacts.first_step, contacts.member, contacts.max_error) == (31, 1, pytest.approx(1 / T))
    assert contacts.ratio == np.inf
    assert result.pass_rate == pytest.approx(1 - 4 / 6)  # members 1, 2, 4 and the non-finite 5
    assert result.first_divergence["step"] == 9 and result.first_divergence["field"] == "sensordata"
    # the object it names, as data too (what known entries match)
    element = result.first_divergence["element"]
    assert element["kind"] == "sensor" and result.first_divergence["object"] == (
        f"sensor '{element['name']}' ({element['type']})"), result.first_divergence


def test_mjx_non_finite_fails_whatever_the_threshold(lidar):
    scenario, m, _, traj_c, _ = lidar
    qvel = traj_c.qvel.copy()
    qvel[3, 30:] = np.inf
    blown = dataclasses.replace(traj_c, qvel=qvel, diverged_at=np.where(np.arange(B) == 3, 30, -1))
    result = judge("lidar", m, traj_c, blown, scenario.tolerance, threshold=0.0)
    assert result.status == "fail" and result.first_divergence["step"] == 30
    assert result.first_divergence["member"] == 3 and result.first_divergence["field"] == "qvel"


def test_c_blowing_up_is_an_unstable_scenario_not_a_divergence(lidar):
    scenario, m, _, traj_c, _ = lidar
    qpos = traj_c.qpos.copy()
    qpos[1, 12:] = np.nan
    c_blown = dataclasses.replace(traj_c, qpos=qpos, diverged_at=np.where(np.arange(B) == 1, 12, -1))
    result = judge("lidar", m, c_blown, c_blown, scenario.tolerance)
    assert (result.status, result.error_kind) == ("error", "unstable"), result.message
    assert "MuJoCo C itself" in result.message and "step 12" in result.message


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


def test_the_reports_numbers_are_what_mjxdiff_metrics_computes(lidar):
    """One error core: every number of a real sweep's report (both engines, streamed in pieces) is
    what the public metrics give on the same trajectories, computed member by member here."""
    from mjxdiff import metrics
    from mjxdiff.output import report
    from mjxdiff.engine.engines import MJXEngine

    scenario, m, inputs, traj_c, _ = lidar
    tol = scenario.tolerance
    config = SweepConfig(envelope=False, diagnose="none", piece_steps=15)
    doc = report.result_dict(run_inputs("lidar", m, inputs, tol, config))
    traj_mjx = MJXEngine().rollout(inputs)  # the same inputs: the same rollout, bit for bit
    layout, mask = metrics.qpos_layout(m), rangefinder_mask(m)
    per_member = {
        "qpos": [metrics.qpos_error(traj_mjx.qpos[i], traj_c.qpos[i], layout) for i in range(B)],
        "qvel": [metrics.qvel_error(traj_mjx.qvel[i], traj_c.qvel[i]) for i in range(B)],
        "act": [jax.numpy.abs(traj_mjx.act[i] - traj_c.act[i]) for i in range(B)],
        "sensordata": [metrics.sensor_relative_error(traj_mjx.sensordata[i], traj_c.sensordata[i], mask)
                       for i in range(B)],
    }
    for field, errors in per_member.items():
        got = doc["fields"][field]
        worst = max(float(metrics.max_over_time(e)) if e.size else 0.0 for e in errors)
        assert got["max_error"] == pytest.approx(worst, rel=1e-12), field
        steps = [int(metrics.first_exceedance(e, getattr(tol, field))) for e in errors]
        assert got["first_step"] == min([s for s in steps if s >= 0], default=-1), field
    contacts = [float(metrics.contact_pair_mismatch(traj_mjx.pairs[i], traj_c.pairs[i])) for i in range(B)]
    assert doc["fields"]["contacts"]["max_error"] == pytest.approx(max(contacts), rel=1e-12)
    rays = [float(np.mean(metrics.rangefinder_hit_mismatch(traj_mjx.sensordata[i], traj_c.sensordata[i], mask)))
            / mask.sum() for i in range(B)]
    assert doc["fields"]["rangefinder"]["max_error"] == pytest.approx(max(rays), rel=1e-12, abs=1e-300)
    assert any(doc["fields"][f]["max_error"] > 0 for f in per_member), "the comparison compared nothing"


@pytest.mark.parametrize("factor, status", [(50.0, "pass"), (1e4, "fail")])
def test_one_member_far_out_of_bound_fails_whatever_the_pass_rate(lidar, factor, status):
    """5 of 6 members pass (83%, above a threshold of 0.8); the sixth is 50x its bound (within
    what a pass rate may excuse) or 1e4x (an outlier: a bug, not scatter)."""
    scenario, m, _, traj_c, _ = lidar
    qvel = traj_c.qvel.copy()
    qvel[2, 23:] += factor * scenario.tolerance.qvel
    result = judge("lidar", m, traj_c, dataclasses.replace(traj_c, qvel=qvel), scenario.tolerance, threshold=0.8)
    assert result.pass_rate == pytest.approx(5 / 6)
    assert result.status == status, result.message
    if status == "fail":
        assert result.first_divergence["member"] == 2 and result.first_divergence["step"] == 23
        assert "member 2 is 1e+04x its bound: an outlier" in result.message


def test_a_pass_says_how_sharp_its_bound_was(lidar):
    """Bound relative to the field's own scale (RMS of C's values): the fixed tolerance is sharp;
    an envelope wide enough to pass a difference of half the field's size is a weak pass,
    named on the line and counted in the summary; the same error against that bound, sharp
    or not, is judged the same way."""
    from mjxdiff.output.report import format_text, summary
    from mjxdiff.compare.verdict import WEAK_BOUND

    scenario, m, _, traj_c, _ = lidar
    tol = scenario.tolerance
    sharp = judge("lidar", m, traj_c, traj_c, tol)
    qpos = sharp.field("qpos")
    assert qpos.scale == pytest.approx(np.sqrt(np.mean(np.asarray(traj_c.qpos) ** 2)), rel=1e-9)
    assert qpos.bound_scale == pytest.approx((tol.qpos / qpos.scale,) * 2)
    assert sharp.status == "pass" and not sharp.weak and "weak" not in sharp.message

    j = Judge(m, tol, *traj_c.time.shape)
    wide = {key: np.full(traj_c.time.shape, 0.5 * qpos.scale) for key in ("qpos", "qvel", "act", "sensordata")}
    shifted = dataclasses.replace(traj_c, qpos=traj_c.qpos + 0.1 * qpos.scale)  # 10% of the scale: passes 50%
    j.update(traj_c, shifted, wide)
    weak = j.result("lidar")
    assert weak.status == "pass" and "qpos" in weak.weak
    assert weak.field("qpos").bound_scale[1] == pytest.approx(0.5) and weak.field("qpos").weak
    assert "weak: the" in weak.message and "bound is" in weak.message
    assert summary([sharp, weak], 0.95)["weak"] == 1
    assert f"2 pass (1 weak: bound over {WEAK_BOUND:.0%}" in format_text([sharp, weak], 0.95)
