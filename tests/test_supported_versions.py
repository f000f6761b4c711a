"""What must hold on every supported MuJoCo / MJX / JAX set, not only the reference one: CI runs
this module in an environment of the oldest and of a middle supported set too (.ci/run), as
well as here. The installed set is in range; MuJoCo C streams its rollout bit for bit (through
mujoco.batch or the loop that stands in for it); the unmodified MJX passes; a 0.1% damping bug
injected into this MJX's passive forces is caught, naming the field, the stage and the step."""

import dataclasses

import numpy as np
from mujoco.mjx._src import passive as mjx_passive

from mjxdiff import compat
from mjxdiff.engine.engines import CEngine
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig, sweep
from mjxdiff.engine.trajectory import Trajectory, concat

_CONFIG = SweepConfig(seed=0, batch=4, steps=100, diagnose="basic", transfer=False)


def test_the_installed_set_is_supported():
    compat.check_versions()


def test_c_streams_its_rollout_bit_for_bit():
    scenario = load_scenario("primitives_on_plane")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=3, steps=40)
    whole, pieces = CEngine().rollout(inputs), concat(list(CEngine().stream(inputs, 13)))
    assert whole.ncon.max() > 0
    for f in dataclasses.fields(Trajectory):
        np.testing.assert_array_equal(getattr(pieces, f.name), getattr(whole, f.name), err_msg=f.name)


def test_unmodified_mjx_passes_and_an_injected_damping_bug_is_caught(fresh_mjx, monkeypatch):
    clean = sweep([load_scenario("pendulum"), load_scenario("cartpole")], _CONFIG)
    assert [r.status for r in clean] == ["pass", "pass"], [r.message for r in clean]

    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) - 1e-3 * m.dof_damping * d.qvel)
    from mjxdiff.engine import engines

    engines.clear_compiled()
    [bad] = sweep([load_scenario("pendulum")], _CONFIG)
    assert bad.status == "fail", bad.message
    first = bad.first_divergence
    assert first is not None and first["field"] in ("qpos", "qvel") and first["step"] >= 0
    assert "joint 'hinge'" in bad.message
    drill = bad.diagnosis["drill_down"]
    assert drill["first_field"] == "qfrc_passive" and drill["first_stage"] == "passive", drill


def test_the_report_names_the_versions_it_ran_on():
    from mjxdiff.output import report

    versions = report.versions()
    assert {k: versions[k] for k in compat.SUPPORTED} == compat.installed()


def test_the_fast_compile_is_used_only_where_it_was_validated():
    import jax

    from mjxdiff.engine.xla import xla_options

    _, choice = xla_options("fast", 10)(jax.jit(lambda x: x + 1.0).lower(1.0))
    assert (choice["level"] == "fast") == compat.fast_compile_validated()


def test_a_version_specific_entry_matches_only_on_its_release(monkeypatch):
    from mjxdiff.compare import support

    entry = support.Entry("x", "t", "e", pattern=r"\(mesh-mesh:", only_on=("3.3.",))
    failing = dict(status="fail", message="first field to differ: contact (geoms a / b (mesh-mesh: C 1, MJX 4))")
    monkeypatch.setattr(support, "_mjx_version", lambda: "3.3.5")
    assert entry.matches(failing)
    monkeypatch.setattr(support, "_mjx_version", lambda: "3.17.0")
    assert not entry.matches(failing)
    assert dataclasses.replace(entry, only_on=()).matches(failing)


def test_a_flex_is_a_catalogued_divergence_before_3_3_5_and_unsupported_since(fresh_mjx):
    """A bug MJX fixed (by refusing flex models) is a known divergence of the releases before the
    fix: MJX 3.3.0-3.3.4 accept a cloth and make none of its contacts; later releases say so."""
    from pathlib import Path

    from mjxdiff.compare import known, support
    from mjxdiff.output import report

    [r] = sweep([load_scenario(Path(__file__).parent / "data" / "flex_cloth.xml")],
                dataclasses.replace(_CONFIG, steps=40))
    flex = next(f for f in support.UNSUPPORTED_FEATURES if f.name == "flex")
    release = compat._release(compat.installed()["mujoco-mjx"])
    if release >= compat._release(flex.refused_since):
        assert r.status == "unsupported" and "Flex" in r.message, r.message
        return
    assert r.status == "fail", r.message
    assert "flex 'cloth'" in r.diagnosis["drill_down"]["object"], r.diagnosis
    entry = known.match(report.result_dict(r))
    assert entry is not None and entry.id == "flex-ignored-3.3", r.message


def test_mesh_contacts_mjx_fixed_later_are_known_only_before(monkeypatch):
    """plane-mesh contacts differed from C's on every release swept before 3.14, capsule-mesh
    before 3.15 (bisected with mjxdiff versions, support.CATALOGUE's evidence): labelled there,
    not on the releases that fixed them."""
    from mjxdiff.compare import known, support

    def failing(pair):
        return dict(status="fail", message="", diagnosis=dict(drill_down=dict(
            first_stage="collision", object=f"geoms a / b ({pair}: C 3, MJX 4 contacts)",
            contact=dict(pair=pair, geoms=["a", "b"], c=3, mjx=4, part="count"))))
    for release, plane, capsule in (("3.3.7", True, True), ("3.9.0", True, True), ("3.12.0", True, True),
                                    ("3.14.0", False, True), ("3.15.0", False, False), ("3.17.0", False, False)):
        monkeypatch.setattr(support, "_mjx_version", lambda release=release: release)
        for pair, fixed_in, expect in (("plane-mesh", "3.14", plane), ("capsule-mesh", "3.15", capsule)):
            entry = known.match(failing(pair))
            assert (entry is not None and entry.id == f"{pair}-before-{fixed_in}") == expect, (release, pair, entry)
