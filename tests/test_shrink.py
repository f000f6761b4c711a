"""Shrinking a diverging model (mjxdiff.tools.shrink) and its bug bundle (mjxdiff.tools.bundle): an injected
MJX bug shrinks to a minimal model that shows it with the bug and passes without it; a real
divergence of MJX 3.17 shrinks through the CLI to a bundle whose standalone script reproduces
it in a fresh process."""

import json
import subprocess
import sys

import mujoco
import numpy as np
import pytest

import injected_bugs
from mjxdiff.engine import engines
from mjxdiff.tools import shrink
from mjxdiff.cli import main

#: Four bodies on a floor: a free sphere, a free box, a two-link arm with a capsule and a sphere
#: tip, with actuators, a sensor and non-default options; the injected plane-sphere bug
#: (radius 1% large) shows in collision.
FLOOR_XML = """
<mujoco>
  <option timestep="0.004" integrator="implicitfast" iterations="3"/>
  <default><geom friction="0.8"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1"/>
    <body name="ball" pos="0 0 0.049"><freejoint/><geom name="ball" type="sphere" size="0.05"/></body>
    <body name="crate" pos="0.5 0 0.06"><freejoint/><geom type="box" size="0.05 0.05 0.05"/></body>
    <body name="arm" pos="-0.5 0 0.3"><joint name="shoulder" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02"/>
      <body name="tip" pos="0.2 0 0"><joint name="elbow" axis="0 1 0"/><geom type="sphere" size="0.03"/></body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder"/><position joint="elbow" kp="10"/></actuator>
  <sensor><jointpos joint="elbow"/></sensor>
</mujoco>
"""


def test_ddmin_finds_the_smallest_subset_that_keeps_the_property():
    calls = []

    def keeps(subset):
        calls.append(list(subset))
        return {"c", "f"} <= set(subset)
    assert shrink.ddmin(list("abcdefgh"), keeps) == ["c", "f"]
    assert shrink.ddmin(list("abc"), lambda s: True) == []  # all dropped at once first
    assert len(calls) < 2 ** 8  # not every subset


def test_a_welded_joint_leaves_every_geom_where_the_state_holds_it():
    spec = shrink._explicit(shrink.named(mujoco.MjSpec.from_string(FLOOR_XML)))
    m = spec.compile()
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    d.qpos[:] = m.qpos0 + 0.3 * rng.standard_normal(m.nq)
    for adr in (3, 10):
        d.qpos[adr:adr + 4] /= np.linalg.norm(d.qpos[adr:adr + 4])
    state = shrink.State.of(m, d)
    before = state.data(m)
    mujoco.mj_kinematics(m, before)
    for names in (["shoulder"], ["elbow"], ["shoulder", "elbow"], shrink.element_names(spec, "joints")):
        w = shrink.drop(spec, "joints", names, m, state).compile()
        after = state.data(w)
        mujoco.mj_kinematics(w, after)
        assert w.njnt == m.njnt - len(names)
        assert w.nu == m.nu - sum(n in ("shoulder", "elbow") for n in names)  # their actuators went with them
        for g in range(m.ngeom):
            name = m.geom(g).name
            np.testing.assert_allclose(after.geom_xpos[w.geom(name).id], before.geom_xpos[g], atol=1e-12)
            np.testing.assert_allclose(after.geom_xmat[w.geom(name).id], before.geom_xmat[g], atol=1e-12)


#: A free body whose jointless child holds a mesh tetrahedron: fusing, boxing and rounding have
#: something to do.
MESH_XML = """
<mujoco>
  <asset><mesh name="tet" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/></asset>
  <worldbody>
    <body name="a" pos="0 0 1.234567"><freejoint name="free"/><geom name="tet" type="mesh" mesh="tet" pos="0.5 0 0"/>
      <body name="b" pos="0.1234567 0 0"><geom name="ball" size="0.1234567"/></body>
    </body>
  </worldbody>
</mujoco>
"""


def test_fusing_boxing_and_rounding_keep_what_they_must():
    """Fusing a jointless body keeps the mass and the geoms' places; a mesh becomes the box of its
    bounding box where the mesh was, its asset dropped; rounding rounds lengths and masses only."""
    spec = shrink._explicit(shrink.named(mujoco.MjSpec.from_string(MESH_XML)))
    m = spec.compile()
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)

    f = shrink.fused(spec)
    mf = f.compile()
    df = mujoco.MjData(mf)
    mujoco.mj_kinematics(mf, df)
    assert (mf.nbody, mf.ngeom) == (m.nbody - 1, m.ngeom)
    assert mf.body_mass[1] == pytest.approx(m.body_subtreemass[1], rel=1e-12)
    np.testing.assert_allclose(df.geom_xpos[mf.geom("ball").id], d.geom_xpos[m.geom("ball").id], atol=1e-12)

    b = shrink.boxed(spec, m, shrink.mesh_geoms(spec))
    mb = b.compile()
    g = mb.geom("tet").id
    assert mb.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX and len(b.meshes) == 0
    np.testing.assert_allclose(mb.geom_size[g], m.geom_aabb[m.geom("tet").id][3:])
    np.testing.assert_allclose(mb.body_mass, m.body_mass)  # explicit inertia: the mass stays
    mujoco.mj_kinematics(mb, db := mujoco.MjData(mb))
    centre = d.geom_xpos[g] + d.geom_xmat[g].reshape(3, 3) @ m.geom_aabb[g][:3]
    np.testing.assert_allclose(db.geom_xpos[g], centre, atol=1e-12)

    mr = shrink.rounded(spec, 2).compile()
    assert mr.body_pos[1][2] == 1.2 and mr.geom_size[mr.geom("ball").id][0] == 0.12
    np.testing.assert_allclose(mr.body_quat, m.body_quat)


def test_an_injected_bug_shrinks_to_a_model_that_shows_it_with_the_bug_and_passes_without(fresh_mjx):
    bug = injected_bugs.by_id("contact_distance")
    spec = mujoco.MjSpec.from_string(FLOOR_XML)
    m = spec.compile()
    assert shrink.find_state(m, steps=5) is None  # unmodified MJX: no divergence to shrink
    with pytest.MonkeyPatch.context() as mp:
        bug.patch(mp)
        engines.clear_compiled()
        state, signature, step = shrink.find_state(m, steps=5)
        assert signature == shrink.Signature("forward", "collision", "contact", "plane-sphere"), signature
        shrunk = shrink.shrink(spec, state, signature, budget=300)
        assert shrunk.complete and shrunk.signature == signature
        minimal = shrunk.spec.compile()
        assert shrink.probe(minimal, shrunk.state) == signature  # the same divergence, not another
    engines.clear_compiled()
    assert shrink.probe(minimal, shrunk.state) is None  # and it is the bug's: gone without it
    before, after = shrunk.before, shrunk.after
    assert (before.bodies, before.geoms, before.joints, before.actuators, before.sensors) == (4, 5, 4, 2, 1)
    # the floor and the ball's sphere, the ball's free joint: nothing else
    assert (after.bodies, after.geoms, after.joints, after.actuators, after.sensors, after.options) == (
        1, 2, 1, 0, 0, 0)
    assert {mujoco.mjtGeom(t).name for t in minimal.geom_type} == {"mjGEOM_PLANE", "mjGEOM_SPHERE"}
    assert shrunk.compiles <= shrunk.candidates + 2  # one compile per structure at most


def test_a_real_divergence_shrinks_to_a_bundle_whose_script_reproduces_it(tmp_path, capsys, repo_root):
    """MJX 3.17 reads 0 from an accelerometer in a model without constraint rows (the catalogued
    acceleration-sensors-without-constraints): shrunk from an arm with a payload, bundled, and
    the bundle's script, run alone, shows it (exit 1)."""
    model = repo_root / "tests" / "data" / "shrink_accelerometer.xml"
    assert main(["shrink", str(model), "--out", str(tmp_path / "b"), "--bundle", "--steps", "3"]) == 0
    out = capsys.readouterr().out
    assert "mj_forward differs first at sensors: sensordata" in out, out
    doc = json.loads((tmp_path / "b" / "signature.json").read_text())
    assert doc["signature"] == dict(check="forward", stage="sensors", field="sensordata", kinds="")
    assert doc["after"]["bodies"] <= 3 and doc["after"]["geoms"] <= 4 and doc["after"]["sensors"] == 1
    assert doc["magnitude"]["object"] == "sensor 'imu_acc' (accelerometer)"
    assert any(a["edit"] == "drop sensor 'imu_acc'" and a["result"] == "removes it" for a in doc["ablations"])
    script = tmp_path / "b" / "repro.py"
    assert len(script.read_text().splitlines()) <= 40
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)  # a fresh process: nothing of mjxdiff imported
    assert run.returncode == 1, run.stdout + run.stderr
    assert "C   sensordata: [0.   0.   9.81]" in run.stdout and "MJX sensordata: [0. 0. 0.]" in run.stdout, run.stdout
    readme = (tmp_path / "b" / "README.md").read_text()
    assert "sensor 'imu_acc' (accelerometer)" in readme and "| drop sensor 'imu_acc' | removes it |" in readme


def test_a_reproducer_is_shrunk_from_its_failing_member_s_state(repo_root):
    """A sweep's or the fuzzer's reproducer (JSON) starts the search at the failing member's
    state with its controls: the committed fuzz find of a tendon's armature across two trees
    shows the qM divergence at once (the bundle tests/data/bundles/tendon-armature-trees was
    shrunk from it)."""
    from mjxdiff.cli.tools import shrink_input

    spec, found, source = shrink_input(str(repo_root / "tests/data/fuzz_tendon_armature_trees.json"), None, 1)
    assert found is not None and source is None
    state, signature, step = found
    assert (signature, step) == (shrink.Signature("forward", "inertia", "qM"), 0)
    assert {n for n, _, _ in state.joints} == {"j0", "j1"} and len(spec.tendons) == 1


@pytest.mark.parametrize("text, message", [
    ("<mujoco><worldbody><body><geom size='x'/></body></worldbody></mujoco>", "mjxdiff shrink: error: "),
    ("<mujoco><worldbody><body><joint/><geom size='.1'/></body></worldbody></mujoco>",
     "no divergence in the first 2 states"),
])
def test_bad_or_agreeing_models_are_one_line_errors(tmp_path, capsys, text, message):
    path = tmp_path / "m.xml"
    path.write_text(text)
    assert main(["shrink", str(path), "--steps", "2", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
