"""mjxdiff.engine.stages: contacts read the same way from both engines. C (MuJoCo 4.0: includemargin is
the margin) keeps a contact in the gap zone (``margin <= dist < margin + gap``, ``exclude = 1``,
no constraint) in ``d.contact`` and ``d.ncon``; MJX drops it, so MJX's contacts are counted with
``dist < includemargin + gap``."""

import mujoco
import numpy as np
from mujoco import mjx

from mjxdiff.engine import engines, stages

#: A ball 2.5 mm above the floor, geom margin 2 mm and gap 1 mm: in the gap zone; a capsule 5 mm
#: above it in an explicit pair with margin 4 mm and gap 3 mm: in the gap zone too; a box 50 mm
#: above: out of reach.
GAPS = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="1 1 0.1"/>
  <body pos="0 0 0.1025"><freejoint/><geom name="ball" size="0.1" margin="0.002" gap="0.001"/></body>
  <body pos="0.5 0 0.055" euler="0 90 0"><freejoint/>
    <geom name="pill" type="capsule" size="0.05 0.1" contype="0" conaffinity="0"/></body>
  <body pos="-0.5 0 0.15"><freejoint/><geom name="box" type="box" size="0.1 0.1 0.1"/></body>
</worldbody><contact><pair geom1="floor" geom2="pill" margin="0.004" gap="0.003"/></contact></mujoco>"""


def test_the_gap_is_c_s_a_pair_s_own_else_the_larger_geom_gap():
    m = mujoco.MjModel.from_xml_string(GAPS)
    ids = {n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("floor", "ball", "pill", "box")}
    geom = np.array([[ids["floor"], ids["ball"]], [ids["pill"], ids["floor"]], [ids["floor"], ids["box"]]])
    np.testing.assert_allclose(stages.contact_gap(m, geom), [0.001, 0.003, 0.0])


def test_mjx_s_contact_count_and_contacts_are_c_s_with_gap_zone_contacts():
    m = mujoco.MjModel.from_xml_string(GAPS)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.ncon == 3 and all(c.exclude == 1 for c in d.contact[:d.ncon])  # ball 1, capsule 2: all in the gap zone
    mx = mjx.put_model(m)
    dx = mjx.forward(mx, mjx.put_data(m, d))
    assert int(engines._contacts(mx, dx)[0]) == d.ncon
    assert ({k: len(v) for k, v in stages.contacts_mjx(m, dx).items()}
            == {k: len(v) for k, v in stages.contacts_c(m, d).items()})
    impl = engines.data_impl(dx).contact
    assert int(np.sum(np.asarray(impl.dist) < np.asarray(impl.includemargin))) == 0  # MJX's own rule: none
