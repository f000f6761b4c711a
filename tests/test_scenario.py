"""Scenario parsing: bundled files load, bad values are named in one line."""

import pytest

from mjxdiff.input.scenario import ScenarioError, Tolerances, bundled_scenarios, load_model, load_scenario


def test_bundled_scenarios_load_and_compile():
    scenarios = bundled_scenarios()
    assert len(scenarios) >= 15
    assert len({s.name for s in scenarios}) == len(scenarios)
    for s in scenarios:
        m = load_model(s)
        assert m.nq > 0, s.name
        assert s.exercises, f"{s.name} should say what it exercises"


def test_mjcf_path_is_a_scenario_with_defaults(tmp_path):
    xml = tmp_path / "bot.xml"
    xml.write_text('<mujoco><worldbody><body><joint type="hinge"/><geom size=".1"/></body></worldbody></mujoco>')
    s = load_scenario(xml)
    assert s.name == "bot"
    assert s.tolerance == Tolerances()
    assert load_model(s).nq == 1


def test_unknown_name_suggests_close_match():
    with pytest.raises(ScenarioError, match="did you mean 'pendulum'"):
        load_scenario("pendulm")


@pytest.mark.parametrize("body, message", [
    ('model = "x.xml"\nbatch = 0', "'batch' must be a positive integer"),
    ('model = "x.xml"\nsteps = "long"', "'steps' must be a positive integer"),
    ('model = "x.xml"\n[randomize]\ncontrol = "chaos"', "'control' must be one of"),
    ('model = "x.xml"\n[randomize.scale]\nbody_mass = [1.2, 0.8]', "'body_mass' must be \\[lo, hi\\]"),
    ('model = "x.xml"\n[randomize.scale]\nwings = [1, 2]', "unknown key"),
    ('model = "x.xml"\n[tolerance]\nqpos = -1', "'qpos' must be a non-negative number"),
    ('model = "x.xml"\ncolour = "red"', "unknown key"),
    ('batch = 4', "'model' .* is required"),
    ('model = "x.xml\n', "invalid TOML"),
])
def test_invalid_scenario_values_are_named(tmp_path, body, message):
    path = tmp_path / "bad.toml"
    path.write_text(body)
    with pytest.raises(ScenarioError, match=message) as info:
        load_scenario(path)
    assert "\n" not in str(info.value)


def test_malformed_mjcf_gives_one_line(tmp_path):
    xml = tmp_path / "broken.xml"
    xml.write_text("<mujoco><worldbody><body><geom type='sphere'</body></worldbody></mujoco>")
    with pytest.raises(ScenarioError, match="MuJoCo cannot compile broken.xml") as info:
        load_model(load_scenario(xml))
    assert "\n" not in str(info.value)


def test_missing_model_file(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text('model = "models/nothing.xml"')
    with pytest.raises(ScenarioError, match="model file not found"):
        load_model(load_scenario(path))


def test_float32_tolerances_are_looser_but_never_tighter():
    t64 = Tolerances(qpos=1e-2)
    t32 = t64.for_precision("float32")
    assert t32.qpos == 1e-2  # already above the float32 floor: kept
    assert t32.qvel > t64.qvel
    assert t64.for_precision("float64") is t64
    # no contact allowance in float64; float32 collision arithmetic gets one (mjxdiff.input.precision)
    assert (t64.contact_mismatch, t32.contact_mismatch) == (0.0, 0.05)
