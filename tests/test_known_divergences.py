"""Divergences of unmodified MJX found while widening the scenarios, each a strict xfail: it
fails (as expected) while MJX differs from C, and starts passing, turning the suite red, the
day MJX is fixed, so that the scenario it was kept out of can take it back."""

import jax
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxdiff import engines

CONTACT_SENSOR_WITH_PAIR = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 .1"/>
    <body name="a" pos="0 0 0.048"><freejoint/><geom name="a" type="sphere" size="0.05"/></body>
    <body name="b" pos="0.5 0 0.06"><freejoint/><geom name="b" type="sphere" size="0.07"/></body>
  </worldbody>
  <contact><pair geom1="b" geom2="floor"/></contact>
  <sensor><contact geom1="a" geom2="floor" num="1" data="found force dist"/></sensor>
</mujoco>"""


@pytest.mark.xfail(strict=True, reason="MJX 3.17: with an explicit <pair> in the model, a geom-matched contact "
                                       "sensor reads the pair's contact (force 49.3, dist -0.01 instead of 7.50, "
                                       "-0.002); found while adding a contact sensor to contact_parameters")
def test_contact_sensor_reads_its_own_contact_when_the_model_has_an_explicit_pair():
    m = mujoco.MjModel.from_xml_string(CONTACT_SENSOR_WITH_PAIR)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.sensordata[0] == 1 and d.sensordata[-1] < 0, "C: sphere 'a' penetrates the floor"
    dx = engines.forward(mjx.put_model(m), mjx.put_data(m, d))
    np.testing.assert_allclose(np.asarray(dx.sensordata), d.sensordata, atol=1e-9,
                               err_msg="contact sensor 'a'/'floor': found, normal force, dist")
