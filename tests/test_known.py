"""The known-divergence catalogue: a tilted box landing on a plane (MJX's plane_convex corner
rule) is labelled with its entry in text and JSON; it still fails unless an accepted entry
and a baseline say otherwise."""

import json

import pytest

from mjxdiff.compare import known, support
from mjxdiff.cli import main


@pytest.fixture(scope="module")
def box(repo_root):
    return str(repo_root / "tests" / "data" / "tilted_box_on_plane.xml")


def test_a_tilted_box_on_a_plane_is_labelled_known(box, tmp_path, capsys):
    assert main(["sweep", box, "--batch", "4", "--steps", "300", "--no-history", "--diagnose", "basic",
                 "--out", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "[known: plane-box-corners]" in out, out
    advice = known.advice(next(e for e in known.CATALOGUE if e.id == "plane-box-corners"))
    assert f"what to do: {advice}" in out and "use sphere or capsule collision geoms" in advice, out
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["scenarios"][0]["known"]["id"] == "plane-box-corners"
    assert doc["scenarios"][0]["known"]["advice"] == advice
    html = (tmp_path / "report.html").read_text()
    assert "<td>plane-box-corners" in html and "<b>known: plane-box-corners</b>" in html
    assert "<b>What to do</b>: nothing to set: MJX drops corners" in html


def test_an_accepted_entry_of_the_user_passes_fail_on_new(box, tmp_path, capsys):
    (tmp_path / "empty.json").write_text(json.dumps(dict(scenarios=[])))
    (tmp_path / "ours.toml").write_text('[[known]]\nid = "our-box"\ntitle = "our tilted box"\n'
                                        'evidence = "measured"\nscenario = "tilted_box.*"\nstage = "collision"\n'
                                        'accepted = true\n')
    argv = ["sweep", box, "--batch", "4", "--steps", "300", "--no-history", "--diagnose", "basic",
            "--baseline", str(tmp_path / "empty.json"), "--fail-on", "new"]
    assert main(argv) == 1  # a new failure, explained by the catalogue but not accepted
    assert main([*argv, "--known", str(tmp_path / "ours.toml")]) == 0
    assert "[known: our-box]" in capsys.readouterr().out


def test_entries_match_on_what_the_diagnosis_says():
    box_box = dict(pair="box-box", geoms=["a", "b"], c=2, mjx=4, part="count")
    failing = dict(name="s", status="fail", message="first field to differ: contact (collision, geoms a / b "
                   "(box-box: C 2, MJX 4 contacts))",
                   diagnosis=dict(drill_down=dict(first_stage="collision", contact=box_box)))
    assert known.match(failing).id == "box-box-manifold"
    assert known.match(dict(failing, status="pass")) is None
    # contacts are matched on the drill-down's data, not on the message's wording
    assert known.match(dict(failing, message="qvel of joint 'a' leaves its bound")).id == "box-box-manifold"
    assert known.match(dict(failing, diagnosis=dict(drill_down=dict(first_stage="collision")))) is None
    # wherever a drill-down found it: the one-step check's too
    one_step = dict(failing, diagnosis={}, info=dict(onestep=dict(first_stage="collision", contact=box_box)))
    assert known.match(one_step).id == "box-box-manifold"
    # a sensor's type from the first divergence's element, not from its name
    accelerometer = dict(name="s", status="fail", message="sensordata of sensor 'imu' leaves its bound",
                         first_divergence=dict(field="sensordata", element=dict(kind="sensor", name="imu",
                                                                                type="accelerometer")))
    assert known.match(accelerometer).id == "acceleration-sensors-without-constraints"
    named_so = dict(accelerometer, first_divergence=dict(field="sensordata", object="sensor 'a' (accelerometer)",
                                                         element=dict(kind="sensor", name="a", type="touch")))
    assert known.match(named_so) is None
    frame = dict(box_box, pair="plane-capsule", c=1, mjx=1, part="tangent frame")
    assert known.match(dict(failing, diagnosis=dict(drill_down=dict(first_stage="collision", contact=frame)))
                       ).id == "contact-tangent-frame"
    # a tendon's wrap side shows in the tendons stage, named; a tendon's armature as a joint's qM,
    # which an armature or mass bug shows too: that entry labels nothing
    sided = dict(kind="tendon", name="t0", type="spatial-sidesite")
    wrap = dict(failing, message="first field to differ: ten_length (tendons, tendon 't0')",
                diagnosis=dict(drill_down=dict(first_stage="tendons", object="tendon 't0'", element=sided)))
    assert known.match(wrap).id == "tendon-wrap-sidesite"
    # a fixed tendon's length (a source mutation of MJX dropping its coefficients was labelled so), or
    # a spatial tendon without a sidesite, is another matter
    for other in ("fixed", "spatial"):
        drill = dict(wrap["diagnosis"]["drill_down"], element=dict(sided, type=other))
        assert known.match(dict(wrap, diagnosis=dict(drill_down=drill))) is None, other
    inertia = dict(failing, message="first field to differ: qM (inertia, joint 'j1')",
                   diagnosis=dict(drill_down=dict(first_stage="inertia", object="joint 'j1'")))
    assert known.match(inertia) is None


def test_an_entry_about_mjx_s_code_does_not_label_another_implementation():
    """MuJoCo Warp (``--impl warp``) and MJX's warp implementation compute contacts with other code:
    the same box-box signature gets no MJX label there, while the solver's settings label any."""
    box_box = dict(pair="box-box", geoms=["a", "b"], c=2, mjx=4, part="count")
    failing = dict(name="s", status="fail", message="", info=dict(impl="mjx"),
                   diagnosis=dict(drill_down=dict(first_stage="collision", contact=box_box)))
    assert known.match(failing).id == "box-box-manifold"
    for impl in ("warp", "mjx.warp"):
        assert known.match(dict(failing, info=dict(impl=impl))) is None, impl
    truncated = dict(name="s", status="fail", message="", info=dict(impl="warp"),
                     diagnosis=dict(cause=dict(cause="solver convergence")))
    assert known.match(truncated).id in support.ANY_IMPL
    # MuJoCo Warp's own: the model must have what the divergence needs
    solref = dict(name="s", status="fail", message="", info=dict(impl="mjx.warp", features=[]),
                  diagnosis=dict(drill_down=dict(first_stage="collision", contact=dict(
                      pair="plane-sphere", geoms=["floor", "puck"], c=1, mjx=1, part="solref"))))
    assert known.match(solref) is None
    feature = dict(solref["info"], features=["contact:direct-solref-under-priority"])
    assert known.match(dict(solref, info=feature)).id == "warp-solref-priority"
    assert known.match(dict(solref, info=dict(feature, impl="mjx"))) is None


def test_model_features_name_a_direct_solref_under_a_higher_priority_geom():
    import mujoco

    def features(floor: str, ball: str) -> tuple[str, ...]:
        return support.model_features(mujoco.MjModel.from_xml_string(
            f'<mujoco><worldbody><geom type="plane" size="1 1 .1" {floor}/><body><freejoint/>'
            f'<geom size=".05" {ball}/></body></worldbody></mujoco>'))

    assert features('priority="1"', 'solref="-2000 -40"') == ("contact:direct-solref-under-priority",)
    assert features('priority="1"', 'solref="0.01 1"') == ()
    assert features('', 'solref="-2000 -40"') == ()


def test_every_mjx_bug_of_the_catalogue_has_a_minimal_bundle(repo_root):
    """A bug entry's bundle is in the repository, whole (bundle.FILES), at most 3 bodies and 4
    geoms, shrunk to completion from tests/data/known/ID.xml or a committed fuzz find; an
    approximation has none; a bug of older releases says why it has none.
    (tests/test_known_divergences.py runs each bundle's repro.py as a strict xfail.)"""
    import mujoco

    from mjxdiff.tools import bundle
    from mjxdiff.compare.support import FIXED_SINCE

    fuzz_finds = sorted((repo_root / "tests/data").glob("fuzz_*.json"))
    kinds = {e.kind for e in known.CATALOGUE}
    assert kinds == {"approximation", "bug", "fixed"}, kinds
    for e in known.CATALOGUE:
        if e.kind == "approximation":
            assert e.bundle == "", e.id
        elif e.kind == "fixed":
            assert e.bundle == FIXED_SINCE, e.id
        elif "mjx" not in e.impl:  # a MuJoCo Warp bug: a strict xfail of the suite is its reproducer
            path, name = e.bundle.split("::")
            assert path.startswith("tests/") and f"def {name}(" in (repo_root / path).read_text(), e.id
        else:
            where = repo_root / e.bundle
            assert e.bundle == f"tests/data/bundles/{e.id}", e.id
            assert sorted(p.name for p in where.iterdir() if p.is_file()) == sorted(bundle.FILES), e.id
            m = mujoco.MjModel.from_xml_path(str(where / "model.xml"))
            assert m.nbody - 1 <= 3 and m.ngeom <= 4, (e.id, m.nbody - 1, m.ngeom)
            doc = json.loads((where / "signature.json").read_text())
            # shrunk to completion from a model or a fuzz find committed beside it
            assert doc["complete"] and doc["origin"] in (f"tests/data/known/{e.id}.xml",
                                                         *(str(f.relative_to(repo_root)) for f in fuzz_finds)), e.id
            assert (repo_root / doc["origin"]).is_file(), e.id


def test_known_list_shows_each_entry_with_its_bundle(capsys, tmp_path):
    assert main(["known", "--list"]) == 0
    out = capsys.readouterr().out
    for e in known.CATALOGUE:
        assert f"{e.id} " in out and e.title in out, e.id
        assert e.remedy and f"what to do: {known.advice(e)}\n" in out, e.id
        upstream = "mujoco_warp" if "mjx" not in e.impl else "mujoco"
        assert (f"report it at https://github.com/google-deepmind/{upstream}/issues" in known.advice(e)) == (
            e.kind == "bug" and e.bundle.startswith("tests/")), e.id
    for e in (e for e in known.CATALOGUE if e.kind == "bug" and "mjx" in e.impl):
        assert f"bundle: tests/data/bundles/{e.id}\n" in out
    assert out.splitlines()[-1].startswith(f"{len(known.CATALOGUE)} entries: ")
    (tmp_path / "bad.toml").write_text("[[known]]\nid = 3\n")
    assert main(["known", "--known", str(tmp_path / "bad.toml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("mjxdiff known: error: ") and err.count("\n") == 1, err


def _failing(message: str, **parts) -> dict:
    return dict(name="s", status="fail", message=message, info=dict(impl="mjx"), **parts)


#: Failures as real sweeps report them (the messages and data of tests/data/known/*.xml swept,
#: drill-downs' fields left out), each with the entry that labels it.
REPORTED = [
    ("equality-aref", _failing(
        "qpos of joint '#0' leaves the envelope at step 1 (t=0.004 s), member 3; worst 0.0115; first field to differ: "
        "qfrc_constraint (constraint, joint '#0'); likely cause: equality constraints (passes with equality "
        "constraints disabled)",
        first_divergence=dict(field="qpos", step=1, object="joint '#0'",
                              element=dict(kind="joint", name="#0", type="free")),
        diagnosis=dict(cause=dict(cause="equality constraints", ablation="equality constraints disabled"),
                       drill_down=dict(first_stage="constraint", first_field="qfrc_constraint",
                                       object="joint '#0'")))),
    ("rotation-integration", dict(_failing(
        "qpos of joint 'ball' leaves the envelope at step 2 (t=0.03 s), member 3; worst 9.78e-05; every forward "
        "stage agrees, the one-step error does not: integration; likely cause: integration (passes with other "
        "integrator (Euler <-> RK4))",
        first_divergence=dict(field="qpos", step=2, object="joint 'ball'",
                              element=dict(kind="joint", name="ball", type="ball")),
        diagnosis=dict(cause=dict(cause="integration", ablation="other integrator (Euler <-> RK4)"),
                       drill_down=dict(first_stage="integration", first_field="qpos/qvel update", object=""))),
        info=dict(impl="mjx", integrator="rk4"))),
    ("box-box-manifold", _failing(
        "first field to differ: contact (collision, geoms a / b (box-box: C 2, MJX 4 contacts))",
        diagnosis=dict(drill_down=dict(first_stage="collision", object="geoms a / b (box-box: C 2, MJX 4 contacts)",
                                       contact=dict(pair="box-box", geoms=["a", "b"], c=2, mjx=4, part="count"))))),
    ("implicit-affine-ctrl-clamp", dict(_failing(
        "qpos of joint 'slide' leaves the envelope at step 0 (t=0.004 s), member 6; worst 0.00333; every forward stage "
        "agrees, the one-step error does not: integration; likely cause: integration (passes with other integrator "
        "(Euler <-> RK4))",
        first_divergence=dict(field="qpos", step=0, object="joint 'slide'",
                              element=dict(kind="joint", name="slide", type="slide")),
        diagnosis=dict(cause=dict(cause="integration", ablation="other integrator (Euler <-> RK4)"),
                       drill_down=dict(first_stage="integration", first_field="qpos/qvel update", object=""))),
        info=dict(impl="mjx", integrator="implicitfast", features=["actuator:affine-gain-velocity-clamped-ctrl"]))),
    ("implicit-clamped-actuator", dict(_failing(
        "qvel of joint 'knee' leaves the envelope at step 0; likely cause: actuator force clamping",
        diagnosis=dict(cause=dict(cause="actuator force clamping"))), info=dict(impl="mjx",
                                                                                integrator="implicitfast"))),
]


def test_a_contact_entry_needs_the_contacts_to_be_the_whole_story():
    """A box-box difference labels a failure only where nothing else says the engines part apart from
    contacts: not where the failure stays with contacts disabled, nor where a stage that reads no
    contact differs at the same state (``beside_contacts``)."""
    failing = dict(REPORTED)["box-box-manifold"]
    tried = [dict(ablation="contacts disabled", passed=False, error="")]
    stays = dict(failing, diagnosis=dict(failing["diagnosis"], cause=dict(cause="contact generation", tried=tried)))
    assert known.match(stays) is None
    could_not_run = [dict(tried[0], error="MJX failed")]
    assert known.match(dict(stays, diagnosis=dict(stays["diagnosis"], cause=dict(tried=could_not_run)))
                       ).id == "box-box-manifold"
    drill = dict(failing["diagnosis"]["drill_down"], beside_contacts=dict(stage="bias", field="qfrc_bias", object=""))
    assert known.match(dict(failing, diagnosis=dict(drill_down=drill))) is None
    # MJX's capsule regularisation moves a contact, it makes or drops none: a radius slip (C 1, MJX 0) is not it
    capsules = dict(pair="capsule-capsule", geoms=["rail", "cap"], c=1, mjx=1, part="normal",
                    explained="segment regularisation")
    moved = dict(failing, diagnosis=dict(drill_down=dict(first_stage="collision", contact=capsules)))
    assert known.match(moved).id == "capsule-regularisation"
    # a capsule contact the segment formulas do not account for is a slip in MJX's code, not it
    unexplained = {k: v for k, v in capsules.items() if k != "explained"}
    assert known.match(dict(moved, diagnosis=dict(drill_down=dict(first_stage="collision", contact=unexplained)))
                       ) is None
    dropped = dict(capsules, mjx=0, part="count")
    assert known.match(dict(moved, diagnosis=dict(drill_down=dict(first_stage="collision", contact=dropped)))) is None


def test_a_constraint_failure_the_equality_ablation_removes_is_equality_aref():
    """The Robotiq 2F-85's sweep (its four-bar connects; README, "shrink and bundles"): the drill-down
    names a joint, the equality-constraints ablation names the cause, and that is what matches."""
    from mjxdiff.compare import diagnose

    failing = dict(REPORTED)["equality-aref"]
    assert known.match(failing).id == "equality-aref"
    genuine = dict(failing, diagnosis=dict(failing["diagnosis"], cause=dict(cause=diagnose.GENUINE)))
    assert known.match(genuine) is None
    assert any(cause == diagnose.EQUALITY for cause, _, _ in diagnose.ABLATIONS)
    assert all(e.pattern is None for e in known.CATALOGUE), "a catalogue entry matches message text"
    # a rotation integrated otherwise is about free and ball joints, not a hinge's update
    rotation = dict(REPORTED)["rotation-integration"]
    hinge = dict(rotation["first_divergence"], element=dict(kind="joint", name="j", type="hinge"))
    assert known.match(dict(rotation, first_divergence=hinge)) is None


@pytest.mark.parametrize("expected, failing", REPORTED, ids=[e for e, _ in REPORTED])
def test_rewording_every_message_changes_no_label(expected, failing):
    """Labels come from the report's data, never from its prose: the message and every object named
    in words are replaced, and the same entry labels the failure (issue 52)."""
    assert known.match(failing).id == expected
    drill = dict(failing.get("diagnosis", {}).get("drill_down") or {}, object="reworded")
    reworded = dict(failing, message="something else entirely",
                    diagnosis=dict(failing.get("diagnosis", {}), drill_down=drill))
    assert known.match(reworded).id == expected


def test_a_user_entry_on_the_message_s_wording_still_matches_and_warns_once(tmp_path):
    (tmp_path / "ours.toml").write_text('[[known]]\nid = "ours"\ntitle = "t"\nevidence = "e"\npattern = "weld"\n')
    with pytest.warns(UserWarning, match="ours match the message's wording") as caught:
        ours = known.load_entries(tmp_path / "ours.toml")
    assert len(caught) == 1
    assert known.match(_failing("a weld parts"), ours).id == "ours"
