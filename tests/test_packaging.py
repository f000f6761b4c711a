"""Packaging: the bundled scenarios ship in the wheel and are found where mjxdiff is installed;
a run that finds no scenario says so in one line and exits 2, never "consistent"."""

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from mjxdiff.input import scenario
from mjxdiff.cli import main
from mjxdiff.input.scenario import ScenarioError, bundled_scenarios, load_scenario

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "scenarios"
TOMLS = sorted(SCENARIOS.glob("*.toml"))
MODELS = sorted(p for p in (SCENARIOS / "models").iterdir() if p.is_file())
DATA = "mjxdiff/_scenarios/"  # where scenarios/ lands in the wheel


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the checkout (the build writes build/ and *.egg-info
    beside its sources: not in a working tree others use). Build isolation: the venv's own
    setuptools may be older than pyproject's build requirement."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        ".*", "__pycache__", "build", "dist", "*.egg-info", "mjxdiff-out", "tests"))
    assert (src / "scenarios" / "wip").is_dir() or not (SCENARIOS / "wip").is_dir()
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps",
                           "-w", str(tmp / "dist"), str(src)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (whl,) = (tmp / "dist").glob("mjxdiff-*.whl")
    return whl


def test_wheel_ships_every_scenario_and_model_and_nothing_from_wip(wheel):
    assert TOMLS and MODELS
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        for path in TOMLS + MODELS:
            arcname = DATA + path.relative_to(SCENARIOS).as_posix()
            assert arcname in names, f"{arcname} missing from {wheel.name}"
            assert z.read(arcname) == path.read_bytes()
        shipped = {n for n in names if n.startswith(DATA)}
    assert {n for n in shipped if n.endswith(".toml")} == {DATA + p.name for p in TOMLS}
    assert not [n for n in names if "wip" in n.split("/")], "scenarios/wip must not be shipped"
    assert not [n for n in names if "sdf_pairs" in n]
    assert not [n for n in names if n.startswith("scenarios/")], "scenarios/ belongs under mjxdiff/"


def test_scenarios_resolve_from_the_unpacked_wheel(wheel, tmp_path):
    """Installed files, not the checkout: bundled scenarios and their models load from the
    wheel's own mjxdiff/_scenarios (run outside the repository, the checkout not on the path)."""
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as z:
        z.extractall(site)
    env = {k: v for k, v in os.environ.items() if k != "MJXDIFF_SCENARIOS"}
    env["PYTHONPATH"] = str(site)
    code = ("import mjxdiff, mjxdiff.input.scenario as s\n"
            "print(mjxdiff.__file__)\n"
            "print(s.bundled_dir())\n"
            "for x in s.bundled_scenarios():\n"
            "    s.load_model(x)\n"
            "    print(x.source.name, x.model_path)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    package, where, *rows = proc.stdout.splitlines()
    assert Path(package).is_relative_to(site)
    assert Path(where) == site / "mjxdiff" / "_scenarios"
    assert sorted(r.split()[0] for r in rows) == [p.name for p in TOMLS]
    for row in rows:
        model = Path(row.split(maxsplit=1)[1])
        assert model.is_file()
        assert model.is_relative_to(where) or "brax" in model.parts  # brax:ant.xml lives in brax
    listed = subprocess.run([sys.executable, "-m", "mjxdiff", "list"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert listed.returncode == 0, listed.stderr
    assert sum(not line.startswith(" ") for line in listed.stdout.splitlines()) == len(TOMLS)


def test_bundled_scenarios_are_the_repositorys_and_resolve_their_models(monkeypatch):
    monkeypatch.delenv("MJXDIFF_SCENARIOS", raising=False)
    found = bundled_scenarios()
    assert sorted(s.source.name for s in found) == [p.name for p in TOMLS]
    for s in found:
        assert s.model_path.is_file(), f"{s.name}: {s.model_path}"
    assert "sdf_pairs" not in {s.name for s in found}  # scenarios/wip is not bundled


def test_environment_override_resolves_models_beside_the_toml_and_hints(tmp_path, monkeypatch):
    shutil.copytree(SCENARIOS / "models", tmp_path / "models")
    shutil.copy(SCENARIOS / "pendulum.toml", tmp_path / "my_pendulum.toml")
    monkeypatch.setenv("MJXDIFF_SCENARIOS", str(tmp_path))
    assert scenario.bundled_dir() == tmp_path
    (only,) = bundled_scenarios()
    assert only.model_path == tmp_path / "models" / "pendulum.xml"
    assert load_scenario("my_pendulum").model_path == tmp_path / "models" / "pendulum.xml"
    with pytest.raises(ScenarioError, match="did you mean 'my_pendulum'"):
        load_scenario("my_pendulm")
    with pytest.raises(ScenarioError, match="unknown scenario 'pendulum'"):
        load_scenario("pendulum")  # the override replaces the bundled set


@pytest.mark.parametrize("command", [["sweep"], ["list"]])
def test_no_bundled_scenarios_exits_2_with_one_line(command, tmp_path, monkeypatch, capsys):
    (tmp_path / "wip").mkdir()
    (tmp_path / "wip" / "x.toml").write_text('model = "x.xml"\n')  # subdirectories are not bundled
    monkeypatch.setenv("MJXDIFF_SCENARIOS", str(tmp_path))
    assert bundled_scenarios() == []
    assert main(command) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and err.startswith("mjxdiff: error: ")
    assert "no bundled scenarios found" in err and str(tmp_path) in err
    if command == ["sweep"]:
        assert "no scenarios selected" in err


@pytest.mark.parametrize("command", [["sweep"], ["list"]])
def test_missing_data_package_exits_2_with_one_line(command, monkeypatch, capsys):
    monkeypatch.delenv("MJXDIFF_SCENARIOS", raising=False)
    monkeypatch.setattr(scenario, "BUNDLED_PACKAGE", "mjxdiff._no_such_scenarios")
    assert scenario.bundled_dir() is None
    assert main(command) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.count("\n") == 1 and "mjxdiff._no_such_scenarios (not installed)" in err
