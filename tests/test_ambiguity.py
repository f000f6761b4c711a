"""mjxdiff.compare.ambiguity: a contact mismatch where C itself cannot decide its contacts (MuJoCo's
parity method's perturbations change them) is ambiguous, not judged; elsewhere it stands."""

import mujoco
import numpy as np

from mjxdiff.compare import ambiguity
from mjxdiff.compare.ambiguity import CcdAmbiguity
from mjxdiff.engine import pairs

#: Two boxes stacked face to face, exactly aligned, on a floor: each box pair touches at corners a
#: turn of 1e-6 rad (a ccd_tolerance) picks; both penetrate (no contact grazes its threshold).
STACK = """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 .1"/>
<body pos="0 0 0.0995"><freejoint/><geom name="a" type="box" size=".1 .1 .1"/></body>
<body pos="0 0 0.2994"><freejoint/><geom name="b" type="box" size=".1 .1 .1"/></body></worldbody></mujoco>"""


def test_an_aligned_stack_is_ambiguous_and_a_box_alone_on_the_floor_is_not():
    m = mujoco.MjModel.from_xml_string(STACK)
    check = CcdAmbiguity((m,), m.qpos0[None])
    assert check.ambiguous(0, m.qpos0.copy())
    alone = m.qpos0.copy()
    alone[9] = 0.5  # b lifted away: box a on the floor, its four corners 0.5 mm deep
    assert not check.ambiguous(0, alone)
    assert check.found.tolist() == [1]


def test_only_ambiguous_steps_are_cleared_and_at_most_so_many_are_checked():
    m = mujoco.MjModel.from_xml_string(STACK)
    alone = m.qpos0.copy()
    alone[9] = 0.5
    T = ambiguity.CHECKS_PER_MEMBER + 8
    before = np.tile(m.qpos0, (1, T, 1))
    before[0, 1] = alone  # step 1: not ambiguous
    differ = np.ones((1, T), bool)
    check = CcdAmbiguity((m,), m.qpos0[None])
    kept = check.filter(differ, before, np.arange(1))
    n = ambiguity.CHECKS_PER_MEMBER
    assert kept[0, 1], "C's contacts at that state hold under every perturbation: the mismatch stands"
    # whether a turn of up to 1e-6 rad moves the stack's corners is chance (the moves are drawn
    # per step: measured 16 of 32 steps, 21 of 40)
    assert (~kept[0, :n]).sum() >= n // 4, kept[0, :n]
    assert kept[0, n:].all() and check.checked.tolist() == [n], "after CHECKS_PER_MEMBER checks, mismatches stand"


def test_the_positions_before_each_step_carry_over_pieces():
    m = mujoco.MjModel.from_xml_string(STACK)
    check = CcdAmbiguity((m, m), np.zeros((2, m.nq)))
    piece = np.arange(2 * 3 * m.nq, dtype=float).reshape(2, 3, m.nq)
    got = check.before(piece, np.arange(2))
    np.testing.assert_array_equal(got[:, 0], 0.0)
    np.testing.assert_array_equal(got[:, 1:], piece[:, :2])
    np.testing.assert_array_equal(check.before(piece[1:], np.array([1]))[0, 0], piece[1, -1])


def test_a_mismatch_is_explained_by_the_state_only_where_c_there_makes_the_tested_engine_s_pairs():
    """Once the states part by rounding, a box lands a step earlier in one engine: C's collision at
    the tested engine's own state makes the tested engine's pairs, so the mismatch is the state's
    (the state fields judge it). A contact C would not make at that state is not explained."""
    m = mujoco.MjModel.from_xml_string(STACK)
    d = mujoco.MjData(m)
    landed, lifted = m.qpos0.copy(), m.qpos0.copy()
    landed[9] = 0.5  # box a alone on the floor (not ambiguous: the test above), b in the air
    lifted[2] = lifted[9] = 0.5  # both boxes up in the air: no contact at all
    sums = {}
    for name, qpos in (("landed", landed), ("lifted", lifted)):
        d.qpos[:] = qpos
        mujoco.mj_fwdPosition(m, d)
        sums[name] = pairs.of_data(m, d)
    assert not np.array_equal(sums["landed"], sums["lifted"])
    check = CcdAmbiguity((m,), m.qpos0[None])
    assert check.state_explains(0, lifted, sums["lifted"])
    assert not check.state_explains(0, lifted, sums["landed"]), "contacts C would not make there"
    assert not check.state_explains(0, np.full(m.nq, np.nan), sums["lifted"]), "a blown-up state explains nothing"
    assert check.explained.tolist() == [1]
    # in a piece: C's states stay landed, the tested engine's lift off at step 1 (its sums say so)
    # and at step 2 claim no contact while landed; only step 1 is cleared, and without a perturbation
    before_c = np.tile(landed, (1, 3, 1))
    before_mjx = before_c.copy()
    before_mjx[0, 1] = lifted
    tested_sums = np.tile(sums["landed"], (1, 3, 1))
    tested_sums[0, 1:] = sums["lifted"]
    differ = np.array([[False, True, True]])
    kept = check.filter(differ, before_c, np.arange(1), tested=(before_mjx, tested_sums))
    assert kept.tolist() == [[False, False, True]] and check.explained.tolist() == [2]
    assert check.checked.tolist() == [1], "only the unexplained step was perturbed"
