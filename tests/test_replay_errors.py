"""`replay` rejects a bad reproducer in one line, exit code 2, never a traceback:
malformed, truncated, undecodable model, wrong array lengths, or a newer format."""

import base64
import copy
import json

import numpy as np
import pytest

from mjxdiff import cli
from mjxdiff.output import report, reproducer
from mjxdiff.input.inputs import make_inputs
from mjxdiff.input.scenario import ScenarioError, load_model, load_scenario
from mjxdiff.runner.sweep import SweepConfig

STEPS = 20


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A real pendulum reproducer (randomized factors included): its path and its JSON document."""
    scenario = load_scenario("pendulum")
    m = load_model(scenario)
    inputs = make_inputs(scenario, m, seed=0, batch=2, steps=STEPS)
    verdict = dict(name="pendulum", status="fail", first_divergence=dict(field="qvel", step=3, member=1))
    path = reproducer.save(tmp_path_factory.mktemp("good") / "pendulum-member1.json", "pendulum", 1, inputs,
                           scenario.model_path.read_text(), scenario.tolerance, SweepConfig(diagnose="none").as_dict(),
                           verdict)
    return path, json.loads(path.read_text())


def _edit(doc, key, value):
    doc = copy.deepcopy(doc)
    *parents, last = key.split(".")
    target = doc
    for p in parents:
        target = target[p]
    if value is _DELETE:
        del target[last]
    else:
        target[last] = value
    return doc


_DELETE = object()
_B64_GARBAGE = base64.b64encode(b"not an mjb model at all" * 4).decode()

# id -> (key, new value, words the message must contain)
MALFORMED = {
    "no kind": ("kind", _DELETE, "not a reproducer"),
    "other kind": ("kind", "sweep", "not a reproducer"),
    "newer schema": ("schema_version", report.SCHEMA_VERSION + 1, "newer mjxdiff"),
    "much newer schema": ("schema_version", 17, "newer mjxdiff"),
    "older schema": ("schema_version", 2, "schema_version 2"),
    "schema a string": ("schema_version", "3", "schema_version '3'"),
    "missing qpos": ("qpos", _DELETE, "'qpos'"),
    "missing model": ("model_mjb_base64", _DELETE, "'model_mjb_base64'"),
    "missing tolerances": ("tolerances", _DELETE, "'tolerances'"),
    "missing verdict": ("verdict", _DELETE, "'verdict'"),
    "missing steps": ("steps", _DELETE, "'steps'"),
    "missing seed": ("seed", _DELETE, "'seed'"),
    "missing config": ("config", _DELETE, "'config'"),
    "missing factors": ("factors", _DELETE, "'factors'"),
    "qpos a string": ("qpos", "1.2", "'qpos'"),
    "qpos holds text": ("qpos", ["a"], "'qpos'"),
    "ctrl ragged": ("ctrl", [[0.1], [0.2, 0.3]], "'ctrl'"),
    "qvel null": ("qvel", None, "'qvel'"),
    "qpos nan": ("qpos", [float("nan")], "'qpos'"),
    "steps a string": ("steps", "20", "'steps'"),
    "steps zero": ("steps", 0, "'steps'"),
    "member a float": ("member", 1.5, "'member'"),
    "member_id negative": ("member_id", -1, "'member_id'"),
    "seed a bool": ("seed", True, "'seed'"),
    "energy a string": ("energy", "yes", "'energy'"),
    "scenario a number": ("scenario", 3, "'scenario'"),
    "model not a string": ("model_mjb_base64", 12, "'model_mjb_base64'"),
    "bad base64": ("model_mjb_base64", "!!! not base64 !!!", "does not decode"),
    "model does not decode": ("model_mjb_base64", _B64_GARBAGE, "does not decode"),
    "empty model": ("model_mjb_base64", "", "does not decode"),
    "tolerances a list": ("tolerances", [1e-6], "'tolerances'"),
    "tolerance a string": ("tolerances.qpos", "tight", "'qpos'"),
    "tolerance negative": ("tolerances.qvel", -1.0, "'qvel'"),
    "unknown tolerance": ("tolerances.velocity", 1.0, "'velocity'"),
    "missing tolerance": ("tolerances.act", _DELETE, "'act'"),
    "verdict without status": ("verdict.status", _DELETE, "'status'"),
    "first_divergence a list": ("verdict.first_divergence", [1, 2], "first_divergence"),
    "versions a list": ("versions", [], "'versions'"),
    "config a list": ("config", [], "'config'"),
    "config bad precision": ("config.precision", "float16", "'precision'"),
    "config bad noise floor": ("config.noise_floor", "sometimes", "'noise_floor'"),
    "config bad diagnose": ("config.diagnose", "deep", "'diagnose'"),
    "config bad threshold": ("config.threshold", 2, "'threshold'"),
    "config steps a string": ("config.piece_steps", "10", "'piece_steps'"),
    "unknown factor": ("factors.friction", [1.0], "'friction'"),
    "factor wrong length": ("factors.body_mass", [1.0], "'body_mass'"),
}


def _lengths(doc):
    """Arrays of the wrong length for the model (pendulum: nq = nv = nu = 1, na = 0), or not matching steps."""
    ctrl = doc["ctrl"]
    return {
        "qpos too long": ("qpos", doc["qpos"] + [0.0], "nq = 1"),
        "qpos empty": ("qpos", [], "nq = 1"),
        "qvel too long": ("qvel", doc["qvel"] * 3, "nv = 1"),
        "act for no actuator state": ("act", [0.5], "na = 0"),
        "ctrl a row short": ("ctrl", ctrl[:-1], "'steps' = 20"),
        "ctrl rows too wide": ("ctrl", [row + [0.0] for row in ctrl], "nu = 1"),
        "ctrl flat": ("ctrl", [row[0] for row in ctrl], "'ctrl'"),
        "steps one more than ctrl": ("steps", STEPS + 1, "'steps' = 21"),
        "steps one less than ctrl": ("steps", STEPS - 1, "'steps' = 19"),
    }


def _replay_rejects(path, capfd, *words):
    code = cli.main(["replay", str(path)])
    out, err = capfd.readouterr()
    assert code == 2, (out, err)
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mjxdiff: error:"), err
    assert "Traceback" not in err
    assert str(path) in lines[0]
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_good_file_loads(good):
    path, doc = good
    rep = reproducer.load(path)
    assert rep.scenario == "pendulum" and rep.member == 1
    assert rep.inputs.batch == 1 and rep.inputs.steps == STEPS
    np.testing.assert_array_equal(rep.inputs.qpos[0], doc["qpos"])
    np.testing.assert_array_equal(rep.inputs.ctrl[0], doc["ctrl"])
    assert rep.model.nq == 1 and rep.model.nu == 1
    assert set(rep.inputs.factors) == set(doc["factors"])
    assert rep.tolerances.as_dict() == doc["tolerances"]


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed(case, good, tmp_path, capfd):
    path, doc = good
    key, value, word = MALFORMED[case]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(doc, key, value)))
    _replay_rejects(bad, capfd, word)


@pytest.mark.parametrize("case", list(_lengths({"qpos": [], "qvel": [], "ctrl": []})))
def test_wrong_lengths(case, good, tmp_path, capfd):
    path, doc = good
    key, value, word = _lengths(doc)[case]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(doc, key, value)))
    _replay_rejects(bad, capfd, word)


def _old_shape(doc):
    """``doc`` as reproducers were written before the report envelope (``format``, no ``kind``)."""
    old = {k: v for k, v in doc.items() if k not in report.ENVELOPE or k in ("versions", "config", "seed")}
    return dict(format=reproducer.FORMAT, **old)


def test_a_reproducer_is_a_report_envelope(good):
    path, doc = good
    assert report.validate(doc, "reproducer") == []
    assert doc["seed"] == 0 and doc["config"]["diagnose"] == "none"


def test_the_shape_before_the_envelope_still_loads(good, tmp_path):
    path, doc = good
    old = tmp_path / "old.json"
    old.write_text(json.dumps(_old_shape(doc)))
    a, b = reproducer.load(path), reproducer.load(old)
    assert (a.scenario, a.member, a.config, a.verdict) == (b.scenario, b.member, b.config, b.verdict)
    np.testing.assert_array_equal(a.inputs.ctrl, b.inputs.ctrl)


@pytest.mark.parametrize("key, value, word", [
    ("format", _DELETE, "not a reproducer"),
    ("format", "something-else/1", "not a reproducer"),
    ("format", "mjxdiff-reproducer/2", "newer mjxdiff"),
    ("format", "mjxdiff-reproducer/17", "newer mjxdiff"),
], ids=["no format", "other format", "newer format", "much newer format"])
def test_malformed_old_shape(key, value, word, good, tmp_path, capfd):
    path, doc = good
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(_old_shape(doc), key, value)))
    _replay_rejects(bad, capfd, word)


def test_newer_format_says_so(good, tmp_path, capfd):
    path, doc = good
    bad = tmp_path / "future.json"
    bad.write_text(json.dumps(dict(_edit(doc, "schema_version", report.SCHEMA_VERSION + 1), new_key={"x": 1})))
    line = _replay_rejects(bad, capfd, "newer mjxdiff", f"reads {report.SCHEMA_VERSION}")
    assert reproducer.FORMAT == "mjxdiff-reproducer/1"
    assert f"schema_version {report.SCHEMA_VERSION + 1}" in line


@pytest.mark.parametrize("fraction", [0.01, 0.5, 0.99])
def test_truncated(fraction, good, tmp_path, capfd):
    path, _ = good
    text = path.read_text()
    bad = tmp_path / "cut.json"
    bad.write_text(text[:int(len(text) * fraction)])
    _replay_rejects(bad, capfd, "invalid JSON", "cut short")


@pytest.mark.parametrize("content", [b"", b"[1, 2, 3]", b"null", b'"text"', b"\xff\xfe\x00garbage", b"{" * 100000])
def test_not_a_reproducer(content, tmp_path, capfd):
    bad = tmp_path / "bad.json"
    bad.write_bytes(content)
    _replay_rejects(bad, capfd)


def test_missing_file_and_directory(tmp_path, capfd):
    _replay_rejects(tmp_path / "nope.json", capfd, "not found")
    _replay_rejects(tmp_path, capfd)


def test_load_raises_scenario_error_only(good, tmp_path):
    path, doc = good
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_edit(doc, "qvel", [1.0, 2.0])))
    with pytest.raises(ScenarioError, match=r"bad\.json: bad reproducer: 'qvel' has shape \(2,\)"):
        reproducer.load(bad)
