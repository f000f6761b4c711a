"""The reference can be wrong: MuJoCo C 4.0.0 (what pip gives MJX users) against 4.0.1 on a model
that meets its sparse-Cholesky bug, and the caveat a failing verdict gains on such models."""

import dataclasses
import json
from pathlib import Path

import mujoco
import numpy as np

from mjxdiff.compare import reference
from mjxdiff.compare.result import ScenarioResult

#: benchmarks/scripts/sparse_cholesky_401.py: a branching tree's state at step 6 under C 4.0.0,
#: and the qacc of 4.0.0 and 4.0.1 from it.
DATA = json.loads((Path(__file__).parent / "data" / "sparse_cholesky_401.json").read_text())


def _qacc_here() -> np.ndarray:
    m = mujoco.MjModel.from_xml_string(DATA["xml"])
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, np.asarray(DATA["state"]), mujoco.mjtState.mjSTATE_FULLPHYSICS)
    d.qacc_warmstart[:] = DATA["warmstart"]
    mujoco.mj_forward(m, d)
    return d.qacc.copy()


def test_the_installed_c_computes_its_release_s_recorded_qacc_and_only_4_0_0_is_suspect():
    """From the same state, this C gives its own release's recorded qacc bit for bit; 4.0.0's is
    thousands away from 4.0.1's (the bug), and only 4.0.0 is flagged on this model."""
    old, fixed = (np.asarray(DATA["qacc"][v]) for v in ("4.0.0", "4.0.1"))
    assert np.abs(old - fixed).max() > 0.1 * np.abs(fixed).max()  # 7,978 on a scale of 15,261
    m = mujoco.MjModel.from_xml_string(DATA["xml"])
    here = DATA["qacc"].get(mujoco.__version__)
    if here is not None:
        np.testing.assert_array_equal(_qacc_here(), here)
    assert (reference.suspect(m) is not None) == (mujoco.__version__ == "4.0.0")


def test_only_newton_on_a_sparse_branching_tree_is_suspect():
    m = mujoco.MjModel.from_xml_string(DATA["xml"])
    assert reference.suspect(m, "4.0.0") == reference.SPARSE_CHOLESKY
    assert reference.suspect(m, "4.0.1") is None
    for option, value in (("solver", mujoco.mjtSolver.mjSOL_CG), ("jacobian", mujoco.mjtJacobian.mjJAC_DENSE)):
        other = mujoco.MjModel.from_xml_string(DATA["xml"])
        setattr(other.opt, option, value)
        assert reference.suspect(other, "4.0.0") is None, option
    chain = "".join('<body pos="0.1 0 0"><joint type="hinge"/><geom size="0.02"/>' for _ in range(4)) + "</body>" * 4
    two_trees = ('<mujoco><option jacobian="sparse"/><worldbody><geom type="plane" size="1 1 .1"/>'
                 f'<body><freejoint/><geom size="0.05"/>{chain}</body>'
                 f'<body pos="1 0 0"><freejoint/><geom size="0.05"/>{chain}</body></worldbody></mujoco>')
    assert reference.suspect(mujoco.MjModel.from_xml_string(two_trees), "4.0.0") is None, "chains, separate trees"


def test_a_failure_on_a_suspect_model_says_how_to_rule_c_out(monkeypatch):
    from mjxdiff.runner import followup

    m = mujoco.MjModel.from_xml_string(DATA["xml"])
    monkeypatch.setattr(reference.mujoco, "__version__", "4.0.0")
    failed = ScenarioResult(name="tree", status="fail", message="qacc differs")
    info: dict = {}
    said = followup.suspect_reference(failed, m, info)
    assert said.message.startswith("qacc differs; the reference may be wrong here: MuJoCo C 4.0.0's sparse Cholesky")
    assert "pip install --no-deps mujoco-core==4.0.1" in said.message and "google-deepmind/mujoco#3767" in said.message
    assert info["suspect_reference"]["fixed_in"] == "4.0.1"
    passed = dataclasses.replace(failed, status="pass", message="ok")
    assert followup.suspect_reference(passed, m, {}) is passed
    monkeypatch.setattr(reference.mujoco, "__version__", "4.0.1")
    assert followup.suspect_reference(failed, m, {}) is failed


def test_c_is_named_the_outlier_only_where_mjx_and_mjwarp_agree_and_both_fail_against_c():
    """``--impl both``'s three verdicts of a scenario: both failures against C gain the clause
    (and ``info["reference_outlier"]``) only where MuJoCo Warp against MJX passes; MJWarp passing
    against C, or failing against MJX, leaves every verdict as it was."""
    from mjxdiff.runner.pipeline import _c_outliers

    def three(name, vs_c, warp_vs_c, warp_vs_mjx):
        return [ScenarioResult(name + suffix, status, "m") for suffix, status in
                zip(reference.PAIRS, (vs_c, warp_vs_c, warp_vs_mjx))]

    results = three("tree", "fail", "fail", "pass") + three("box", "fail", "fail", "fail") + three(
        "arm", "fail", "pass", "pass")
    out = {r.name: r for r in _c_outliers(results)}
    assert [r.name for r in _c_outliers(results)] == [r.name for r in results]
    for name in ("tree", "tree@warp"):
        assert out[name].info["reference_outlier"] and "C is the outlier" in out[name].message, out[name]
        assert "tree@mjx-warp passes" in out[name].message
    unchanged = [r for r in results if not r.name.startswith("tree") or r.name == "tree@mjx-warp"]
    for r in unchanged:
        assert out[r.name] == r
