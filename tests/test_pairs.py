"""mjxdiff.engine.pairs: contacts by geom pair in two hash sums per step, the same bits on the host
and inside a trace, decoded back to the pairs that differ; grazing contacts left out."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from mjxdiff.engine import engines, pairs
from mjxdiff.engine.c import _pair_sums
from mjxdiff.compat import Batch
from test_stages import GAPS

SCENE = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 1"/>
<geom name="decoy" type="box" size=".1 .1 .1" pos="3 0 0"/>
<body><freejoint/><geom name="ball" size=".1"/></body></worldbody></mujoco>"""


def test_a_pairs_hashes_ignore_its_order_and_match_inside_a_trace_in_either_precision():
    key = np.array([[0, 2], [2, 0], [1, 2], [-1, 2]])
    h = pairs.hashes(key)
    assert h.dtype == np.uint32 and (h[0] == h[1]).all() and len({tuple(r) for r in h[[0, 2, 3]]}) == 3
    for x64 in (True, False):
        with jax.enable_x64(x64):
            np.testing.assert_array_equal(np.asarray(jax.jit(lambda k: pairs.hashes(k, jnp))(jnp.asarray(key))), h)


def test_the_difference_of_two_sums_names_the_pairs():
    m = mujoco.MjModel.from_xml_string(SCENE)
    h = pairs.hashes(np.array([[0, 2], [1, 2]]))
    with np.errstate(over="ignore"):
        assert pairs.decode(m, h[1] - h[0]) == [((1, 2), 1), ((0, 2), -1)]
        assert pairs.decode(m, np.uint32(0) - np.uint32(2) * h[0]) == [((0, 2), -2)]
        assert pairs.decode(m, h[0] + h[1]) == []  # two more in one engine, in two pairs: not one of the forms
    assert pairs.describe_pairs(m, [((1, 2), 1), ((0, 2), -1)]) == (
        "pair 'decoy'/'ball' (1 more in MJX), 'floor'/'ball' (1 more in C)")


@pytest.mark.parametrize("dist, firm", [(-1e-3, True), (-2e-5, True), (-5e-6, False), (0.0, False), (5e-6, False)])
def test_a_contact_within_the_grazing_distance_of_its_threshold_is_not_firm(dist, firm):
    assert bool(pairs.firm(np.array([dist]), np.array([0.0]), np.array([0.0]))[0]) is firm
    # and the same around the gap zone's top, includemargin + gap
    assert bool(pairs.firm(np.array([0.003 + dist]), np.array([0.0]), np.array([0.003]))[0]) is firm


def test_mjx_and_c_record_the_same_sums_for_gap_zone_contacts_and_a_wrong_pair_differs():
    """The GAPS scene's ball and capsule lie in their gap zones (C keeps them, inactive): MJX's
    in-trace sums and C's, read from a persistent batch, agree bit for bit."""
    m = mujoco.MjModel.from_xml_string(GAPS)
    b = Batch(m, 1, persistent=True)
    out = b.rollout(1, record=("ncon",))
    c = _pair_sums((m,), True, b, np.arange(1), out["ncon"][:, 0], mujoco.MjData(m))[0]
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    mx = mjx.put_model(m)
    ncon, sums = engines._contacts(mx, mjx.forward(mx, mjx.put_data(m, d)))
    assert int(ncon) == out["ncon"][0, 0] == 3
    np.testing.assert_array_equal(np.asarray(sums), c)
    assert c.any(), "the gap-zone contacts are firm: 0.5 mm and 1 mm from their thresholds"


def test_members_with_their_own_gaps_are_summed_each_with_its_own():
    """A randomized gap: C's per-step read sums each member's contacts with its own model's gap
    (the ball's gap-zone contact is firm at a gap of 1 mm, past the zone's top at 0.2 mm)."""
    m = mujoco.MjModel.from_xml_string(GAPS)
    narrow = mujoco.MjModel.from_xml_string(GAPS)
    narrow.geom_gap[:] = np.minimum(narrow.geom_gap, 0.0002)
    models = (m, narrow)
    b = Batch(m, 2, persistent=True)
    b.set_models(list(models))
    out = b.rollout(1, record=("ncon",))
    got = _pair_sums(models, False, b, np.arange(2), out["ncon"][:, 0], mujoco.MjData(m))
    for i, mi in enumerate(models):
        d = b.get_data(i, mujoco.MjData(mi))
        np.testing.assert_array_equal(got[i], pairs.of_data(mi, d), err_msg=str(i))
    assert not np.array_equal(got[0], got[1]), "the gaps decide which contacts are firm"
