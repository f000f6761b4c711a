"""Nothing is written outside --out: scenario names become plain file names, and
every file mjxdiff writes under an output directory is checked to stay inside it."""

import json
import os
from pathlib import Path

import pytest
from mujoco.mjx._src import passive as mjx_passive

from mjxdiff import cli
from mjxdiff.output import report

ROOT = Path(__file__).resolve().parent.parent
EVIL = "../../escaped/evil"


def extra_damping(monkeypatch):
    """1% more joint damping force in MJX than the model says: fails the pendulum within 50 steps."""
    orig = mjx_passive._spring_damper
    monkeypatch.setattr(mjx_passive, "_spring_damper", lambda m, d: orig(m, d) - 1e-2 * m.dof_damping * d.qvel)


def _files(root: Path) -> set[Path]:
    return {Path(dirpath, f) for dirpath, _, files in os.walk(root) for f in files}


def test_escaping_scenario_name_writes_its_reproducer_inside_out(tmp_path, fresh_mjx, monkeypatch, capsys):
    toml = tmp_path / "evil.toml"
    model = (ROOT / "scenarios" / "models" / "pendulum.xml").resolve()
    toml.write_text(f'name = "{EVIL}"\nmodel = "{model}"\nbatch = 4\nsteps = 50\nkeyframe = "swing"\n')
    out = tmp_path / "deep" / "out"  # an escape would land in tmp_path/deep/escaped or above
    extra_damping(monkeypatch)

    code = cli.main(["sweep", str(toml), "--out", str(out), "--quick", "--diagnose", "none"])

    captured = capsys.readouterr()
    assert code == 1, captured.out + captured.err
    assert "FAIL" in captured.out
    outside = {p for p in _files(tmp_path) if out not in p.parents}
    assert outside == {toml}
    assert not any(p.name == "escaped" for p in tmp_path.rglob("*"))
    assert not (tmp_path.parent / "escaped").exists()
    reproducers = sorted((out / "reproducers").iterdir())
    assert len(reproducers) == 1
    saved = reproducers[0]
    assert saved.name.startswith("_.._escaped_evil-member") and saved.suffix == ".json"
    doc = json.loads(saved.read_text())
    assert doc["scenario"] == EVIL  # the real name is kept inside the file
    rep = json.loads((out / "report.json").read_text())
    (scenario,) = rep["scenarios"]
    assert scenario["name"] == EVIL and Path(scenario["info"]["reproducer"]).resolve() == saved.resolve()


@pytest.mark.parametrize("name", [
    "../x", "/abs/path", "..", ".", "a/b\\c", "", "x" * 500, "ünïcødé/名前", "...", "./.hidden",
    "a\x00b", "con:nul", " ", "-", "..\\..\\windows",
])
def test_safe_filename_is_one_plain_name(name, tmp_path):
    safe = report.safe_filename(name)
    assert safe and safe not in (".", "..")
    assert not safe.startswith(".")
    assert len(safe) <= report.MAX_FILENAME
    assert all(c.isascii() and (c.isalnum() or c in "._-") for c in safe), safe
    path = report.path_under(tmp_path, safe)
    assert path.parent == tmp_path
    path.write_text("x")  # a real, writable file name
    assert path.resolve().parent == tmp_path.resolve()


def test_safe_filename_keeps_plain_names_and_separates_long_ones():
    assert report.safe_filename("pendulum") == "pendulum"
    assert report.safe_filename("box_stack-2.v1") == "box_stack-2.v1"
    assert report.safe_filename("../x") == "_x"
    assert report.safe_filename("") == "_"
    a, b = report.safe_filename("x" * 500 + "a"), report.safe_filename("x" * 500 + "b")
    assert a != b and len(a) == len(b) == report.MAX_FILENAME
    assert report.safe_filename("x" * 500) == report.safe_filename("x" * 500)  # deterministic


@pytest.mark.parametrize("name", ["../x", "..", "/etc/passwd", "a/../../b", ".", ""])
def test_path_under_refuses_escapes(name, tmp_path):
    with pytest.raises(ValueError, match="not inside"):
        report.path_under(tmp_path / "out", name)


def test_path_under_refuses_a_symlink_out(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "link.json").symlink_to(tmp_path / "elsewhere.json")
    with pytest.raises(ValueError):
        report.path_under(out, "link.json")
    assert report.path_under(out, "sub/ok.json") == out / "sub" / "ok.json"


def test_write_report_stays_in_its_directory(tmp_path):
    out = tmp_path / "out"
    path = report.write_report(out, {"a": 1}, "../../escaped.json")
    assert path.parent == out and path.name == "_.._escaped.json"
    assert _files(tmp_path) == {path}
    assert report.write_report(out, {"a": 1}).name == "report.json"
