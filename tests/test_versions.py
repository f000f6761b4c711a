"""mjxdiff versions: targets, requirements, the scenario x version table, and a run where one
version cannot be installed (a real pip failure) while another is swept for real."""

import json
import sys
from pathlib import Path

import pytest

from mjxdiff import cli
from mjxdiff.output import report
from mjxdiff.tools import versions
from mjxdiff.tools.versions import Target, parse_target


@pytest.mark.parametrize("text, mjx, jax, mujoco, core", [
    ("3.9.0", "3.9.0", None, "3.9.0", None),
    ("3.9.0/0.7.2", "3.9.0", "0.7.2", "3.9.0", None),
    ("3.17.0", "3.17.0", None, "4.0.0", None),
    ("3.17.1/0.10.2", "3.17.1", "0.10.2", "4.0.1", None),
    ("3.17.0+core4.0.1", "3.17.0", None, "4.0.0", "4.0.1"),
    ("3.17.0/0.10.2+core4.0.1", "3.17.0", "0.10.2", "4.0.0", "4.0.1"),
])
def test_a_target_names_mjx_its_mujoco_and_a_jax(text, mjx, jax, mujoco, core):
    t = parse_target(text)
    assert (t.mjx, t.jax, t.mujoco, t.core) == (mjx, jax, mujoco, core)
    assert parse_target(t.label.replace("/jax", "/")) == t  # the label names the target


@pytest.mark.parametrize("text", ["3.9", "latest", "3.9.0/", "3.9.0/jax", "3.9.0/0.7", "3.17.0+core", "3.17.0+core4.0"])
def test_a_malformed_target_exits_2_in_one_line(text, capsys, monkeypatch):
    monkeypatch.setattr(versions, "run", lambda *a, **k: pytest.fail(f"{text!r} was taken for a target"))
    with pytest.raises(SystemExit) as e:
        cli.main(["versions", text])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not MJX[/JAX][+coreC]" in err[0]


def test_requirements_pin_the_release_and_keep_the_rest_as_declared():
    reqs = versions.requirements(Target("3.9.0", "0.7.2"), extras=("test",))
    assert reqs[:4] == ["mujoco==3.9.0", "mujoco-mjx==3.9.0", "jax[cpu]==0.7.2", "jaxlib==0.7.2"]
    assert not [r for r in reqs[4:] if r.split("[")[0].split(">")[0].split("=")[0] in ("mujoco", "jax", "jaxlib")]
    assert any(r.startswith("pytest") for r in reqs) and any(r.startswith("hypothesis") for r in reqs)
    assert not any(r.startswith("pytest") for r in versions.requirements(Target("3.9.0")))  # no extras
    assert not any("extra" in r for r in reqs)


def _doc(*cells):
    return dict(scenarios=[dict(name=n, status=s, fields={"qpos": dict(ratio=r)},
                                first_divergence=dict(step=k) if k >= 0 else None,
                                known=dict(id=known) if known else None) for n, s, r, k, known in cells])


def test_the_table_marks_what_changed_since_the_previous_version():
    a, b, c = Target("3.3.5", "0.7.0"), Target("3.9.0"), Target("3.17.0")
    t = versions.table([
        (a, _doc(("pendulum", "pass", 0.1, -1, ""), ("box", "fail", 3.0, 19, ""))),
        (b, "pip install failed (no such version); log: x"),
        (c, _doc(("pendulum", "pass", 0.2, -1, ""), ("box", "fail", 2.0, 19, "contacts"),
                 ("new", "pass", 0.1, -1, ""))),
    ])
    assert t["versions"] == ["3.3.5/jax0.7.0", "3.9.0", "3.17.0"] and list(t["errors"]) == ["3.9.0"]
    rows = t["rows"]
    assert not rows["pendulum"]["3.17.0"]["changed"]  # a ratio alone is no change
    assert rows["box"]["3.17.0"]["changed"] and rows["box"]["3.17.0"]["known"] == "contacts"
    assert not rows["new"]["3.17.0"]["changed"] and "3.3.5/jax0.7.0" not in rows["new"]
    text = versions.format_table(t)
    assert "*fail 2 @19 [contacts]" in text and "3.9.0: ERROR pip install failed" in text


def test_a_version_that_cannot_be_installed_is_one_line_and_the_others_run(tmp_path, monkeypatch, capsys):
    """99.1.0 does not exist (pip fails for real); 3.17.0 is this environment, swept for real
    in a subprocess of its Python."""
    real = versions.prepare

    def prepare(target, cache, extras=(), say=print):
        return Path(sys.prefix) if target.mjx == "3.17.0" else real(target, cache, extras, say)

    monkeypatch.setattr(versions, "prepare", prepare)
    out = tmp_path / "out"
    code = cli.main(["versions", "99.1.0", "3.17.0", "--scenarios", "pendulum", "--quick", "--out", str(out),
                     "--envs", str(tmp_path / "envs")])
    text = capsys.readouterr().out
    assert code == 1, text  # a version could not be installed
    assert "99.1.0: ERROR pip install failed" in text and "No matching distribution" in text
    assert "pendulum  -" in text and "pass" in text
    doc = json.loads((out / "versions.json").read_text())
    assert report.validate(doc, "versions") == []
    assert doc["table"]["rows"]["pendulum"]["3.17.0"]["status"] == "pass"
    assert doc["supported"] == {"99.1.0": False, "3.17.0": True}
    assert (out / "3.17.0" / "report.json").is_file() and (out / "history").is_dir()
