"""Checks the catalogue of ``tests/combination_bugs.py``: every bug shows WITH its combination
and is bit-invisible WITHOUT it (either condition absent).

Not a pytest test (its name does not start with ``test_``); run it by hand::

    JAX_ENABLE_X64=1 python tests/check_combination_bugs.py [bug_id ...]

For every bug it steps tiny models in MJX, unpatched and patched (the same state and ctrl), and
prints the largest |difference| of qpos, qvel, act and sensordata over the rollout: the case WITH
the combination must exceed 1e-6, each case WITHOUT it (one of the two conditions absent) must be
below 1e-12 (it is exactly 0 for all of them).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

os.environ.setdefault("JAX_ENABLE_X64", "1")

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from combination_bugs import BUGS, COMBINATIONS

NSTEPS = 20
WITH_MIN = 1e-6
WITHOUT_MAX = 1e-12


@dataclasses.dataclass(frozen=True)
class Case:
    label: str
    xml: str
    qpos: tuple = ()
    qvel: tuple = ()
    ctrl: tuple = ()
    act: tuple = ()


# -- model templates ---------------------------------------------------------------------------

# a capsule arm on a hinge about y (horizontal at qpos 0), with room for joint attributes,
# options, extra world bodies and the sections after the worldbody
PEND = """
<mujoco>
  <compiler angle="radian"/>
  <option timestep="0.005" {option}>{flags}</option>
  <worldbody>
    <body name="arm" pos="0 0 1" {bodyattr}>
      <joint name="hinge" type="hinge" axis="0 1 0" {jattr}/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1"/>
    </body>
    {world}
  </worldbody>
  {after}
</mujoco>
"""


def pend(option="", flags="", bodyattr="", jattr="", world="", after=""):
    return PEND.format(option=option, flags=flags, bodyattr=bodyattr, jattr=jattr, world=world, after=after)


# an arm turning about z (no gravity torque), with sites on it and in the world, for frame sensors
FRAMES = """
<mujoco>
  <compiler angle="radian"/>
  <option timestep="0.005"/>
  <worldbody>
    <site name="target" pos="0.6 0.3 0.2"/>
    <site name="wref" pos="0.1 0 0"/>
    <body name="arm">
      <joint name="hz" type="hinge" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.04" mass="1"/>
      <site name="aref" pos="0.2 0 0" euler="0 0.3 0"/>
      <site name="tip" pos="0.4 0 0"/>
    </body>
  </worldbody>
  <sensor>{sensor}</sensor>
</mujoco>
"""


def frames(sensor):
    return FRAMES.format(sensor=sensor)


# a box sliding on a plane (4 contacts), for cones and solvers
SLIDE = """
<mujoco>
  <option timestep="0.005" {option}/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body name="box" pos="0 0 0.1">
      <freejoint/>
      <geom type="box" size="0.1 0.1 0.1" mass="1" friction="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""
SLIDE_QPOS = (0, 0, 0.099, 1, 0, 0, 0)
SLIDE_QVEL = (3, 1, 0, 0, 0, 0)


def slide(option):
    return SLIDE.format(option=option)


# a free box held by an equality to the world
EQ = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="b" pos="0 0 1">
      <freejoint/>
      <geom type="box" size="0.1 0.05 0.02" mass="1"/>
    </body>
  </worldbody>
  <equality>{eq}</equality>
</mujoco>
"""

# a slider along x with a tendon spring on it
TENDON_SPRING = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="slider">
      <joint name="s" type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.05" mass="1"/>
    </body>
  </worldbody>
  <tendon>
    <fixed name="ts" springlength="{springlength}" stiffness="100"><joint joint="s" coef="1"/></fixed>
  </tendon>
</mujoco>
"""

MOTOR = '<actuator><motor joint="hinge" {attr}/></actuator>'

# -- cases per bug: (with, [without, ...]) -------------------------------------------------------

CASES: dict[str, tuple[Case, list[Case]]] = {
    "ctrl_clamp_upper": (
        Case("ctrllimited, ctrl 2 > 1", pend(after=MOTOR.format(attr='ctrllimited="true" ctrlrange="-1 1"')),
             ctrl=(2.0,)),
        [Case("ctrllimited, ctrl 0.5 inside", pend(after=MOTOR.format(attr='ctrllimited="true" ctrlrange="-1 1"')),
              ctrl=(0.5,)),
         Case("not ctrllimited, ctrl 2", pend(after=MOTOR.format(attr='ctrllimited="false" ctrlrange="-1 1"')),
              ctrl=(2.0,))]),
    "force_clamp_lower": (
        Case("forcelimited, force -2 < -0.5",
             pend(after=MOTOR.format(attr='forcelimited="true" forcerange="-0.5 0.5"')), ctrl=(-2.0,)),
        [Case("forcelimited, force -0.3 inside",
              pend(after=MOTOR.format(attr='forcelimited="true" forcerange="-0.5 0.5"')), ctrl=(-0.3,)),
         Case("not forcelimited, force -2",
              pend(after=MOTOR.format(attr='forcelimited="false" forcerange="-0.5 0.5"')), ctrl=(-2.0,))]),
    "act_clamp_upper": (
        Case("actlimited integrator, act 0.95 driven up",
             pend(after='<actuator><general joint="hinge" dyntype="integrator" actlimited="true" '
                        'actrange="0 1"/></actuator>'), ctrl=(5.0,), act=(0.95,)),
        [Case("actlimited integrator, act 0.2 stays inside",
              pend(after='<actuator><general joint="hinge" dyntype="integrator" actlimited="true" '
                         'actrange="0 1"/></actuator>'), ctrl=(1.0,), act=(0.2,)),
         Case("not actlimited, act 0.95 driven up",
              pend(after='<actuator><general joint="hinge" dyntype="integrator" actlimited="false" '
                         'actrange="0 1"/></actuator>'), ctrl=(5.0,), act=(0.95,))]),
    "filterexact_as_euler": (
        Case("filterexact, act 0 -> ctrl 1",
             pend(after='<actuator><general joint="hinge" dyntype="filterexact" dynprm="0.05"/></actuator>'),
             ctrl=(1.0,), act=(0.0,)),
        [Case("filter, act 0 -> ctrl 1",
              pend(after='<actuator><general joint="hinge" dyntype="filter" dynprm="0.05"/></actuator>'),
              ctrl=(1.0,), act=(0.0,)),
         Case("filterexact, act = ctrl = 0.3",
              pend(after='<actuator><general joint="hinge" dyntype="filterexact" dynprm="0.05"/></actuator>'),
              ctrl=(0.3,), act=(0.3,))]),
    "tendon_actfrc_lower": (
        Case("tendon actfrclimited, total -1 < -0.3",
             pend(after='<tendon><fixed name="t" actuatorfrclimited="true" actuatorfrcrange="-0.3 0.3">'
                        '<joint joint="hinge" coef="1"/></fixed></tendon>'
                        '<actuator><motor tendon="t"/></actuator>'), ctrl=(-1.0,)),
        [Case("tendon actfrclimited, total -0.1 inside",
              pend(after='<tendon><fixed name="t" actuatorfrclimited="true" actuatorfrcrange="-0.3 0.3">'
                         '<joint joint="hinge" coef="1"/></fixed></tendon>'
                         '<actuator><motor tendon="t"/></actuator>'), ctrl=(-0.1,)),
         Case("tendon not actfrclimited, total -1",
              pend(after='<tendon><fixed name="t" actuatorfrclimited="false" actuatorfrcrange="-0.3 0.3">'
                         '<joint joint="hinge" coef="1"/></fixed></tendon>'
                         '<actuator><motor tendon="t"/></actuator>'), ctrl=(-1.0,))]),
    "actgravcomp_after_clamp": (
        Case("actuatorgravcomp + actfrclimited (saturated)",
             pend(bodyattr='gravcomp="1"',
                  jattr='actuatorgravcomp="true" actuatorfrclimited="true" actuatorfrcrange="-0.5 0.5"',
                  after=MOTOR.format(attr="")), ctrl=(0.1,)),
        [Case("passive gravcomp + actfrclimited",
              pend(bodyattr='gravcomp="1"',
                   jattr='actuatorgravcomp="false" actuatorfrclimited="true" actuatorfrcrange="-0.5 0.5"',
                   after=MOTOR.format(attr="")), ctrl=(0.1,)),
         Case("actuatorgravcomp, not actfrclimited",
              pend(bodyattr='gravcomp="1"', jattr='actuatorgravcomp="true"', after=MOTOR.format(attr="")),
              ctrl=(0.1,))]),
    "tendon_deadband_upper": (
        Case("deadband 0.1..0.3, length 0.5 above", TENDON_SPRING.format(springlength="0.1 0.3"), qpos=(0.5,)),
        [Case("deadband 0.1..0.3, length 0.05 below", TENDON_SPRING.format(springlength="0.1 0.3"),
              qpos=(0.05,)),
         Case("no deadband (0.3 0.3), length 0.5 above", TENDON_SPRING.format(springlength="0.3 0.3"),
              qpos=(0.5,))]),
    "framepos_ref_untransposed": (
        Case("framepos, ref on turning arm",
             frames('<framepos objtype="site" objname="target" reftype="site" refname="aref"/>'),
             qpos=(0.7,), qvel=(2.0,)),
        [Case("framepos, unrotated world ref",
              frames('<framepos objtype="site" objname="tip" reftype="site" refname="wref"/>'),
              qpos=(0.7,), qvel=(2.0,)),
         Case("framepos, no ref", frames('<framepos objtype="site" objname="tip"/>'),
              qpos=(0.7,), qvel=(2.0,))]),
    "framequat_ref_uninverted": (
        Case("framequat, ref on turning arm",
             frames('<framequat objtype="site" objname="target" reftype="site" refname="aref"/>'),
             qpos=(0.7,), qvel=(2.0,)),
        [Case("framequat, unrotated world ref",
              frames('<framequat objtype="site" objname="tip" reftype="site" refname="wref"/>'),
              qpos=(0.7,), qvel=(2.0,)),
         Case("framequat, no ref", frames('<framequat objtype="site" objname="tip"/>'),
              qpos=(0.7,), qvel=(2.0,))]),
    "framelinvel_ref_spin_sign": (
        Case("framelinvel, ref on turning arm",
             frames('<framelinvel objtype="site" objname="target" reftype="site" refname="aref"/>'),
             qpos=(0.7,), qvel=(2.0,)),
        [Case("framelinvel, non-rotating world ref",
              frames('<framelinvel objtype="site" objname="tip" reftype="site" refname="wref"/>'),
              qpos=(0.7,), qvel=(2.0,)),
         Case("framelinvel, no ref", frames('<framelinvel objtype="site" objname="tip"/>'),
              qpos=(0.7,), qvel=(2.0,))]),
    "eulerdamp_flag_ignored": (
        Case("eulerdamp disabled, damping 0.5",
             pend(flags='<flag eulerdamp="disable"/>', jattr='damping="0.5"'), qvel=(1.0,)),
        [Case("eulerdamp enabled, damping 0.5", pend(jattr='damping="0.5"'), qvel=(1.0,)),
         Case("eulerdamp disabled, no damping", pend(flags='<flag eulerdamp="disable"/>'), qvel=(1.0,))]),
    "implicit_actuator_vel": (
        Case("implicitfast, velocity servo",
             pend(option='integrator="implicitfast"',
                  after='<actuator><velocity joint="hinge" kv="2"/></actuator>'), ctrl=(1.0,), qvel=(0.5,)),
        [Case("Euler, velocity servo",
              pend(after='<actuator><velocity joint="hinge" kv="2"/></actuator>'), ctrl=(1.0,), qvel=(0.5,)),
         Case("implicitfast, motor",
              pend(option='integrator="implicitfast"', after=MOTOR.format(attr="")), ctrl=(1.0,),
              qvel=(0.5,))]),
    "elliptic_impratio_nosqrt": (
        Case("elliptic, impratio 3", slide('cone="elliptic" impratio="3"'), qpos=SLIDE_QPOS, qvel=SLIDE_QVEL),
        [Case("pyramidal, impratio 3", slide('cone="pyramidal" impratio="3"'), qpos=SLIDE_QPOS,
              qvel=SLIDE_QVEL),
         Case("elliptic, impratio 1", slide('cone="elliptic" impratio="1"'), qpos=SLIDE_QPOS, qvel=SLIDE_QVEL)]),
    "newton_cone_hessian_sign": (
        Case("Newton, elliptic", slide('solver="Newton" cone="elliptic"'), qpos=SLIDE_QPOS, qvel=SLIDE_QVEL),
        [Case("CG, elliptic", slide('solver="CG" cone="elliptic"'), qpos=SLIDE_QPOS, qvel=SLIDE_QVEL),
         Case("Newton, pyramidal", slide('solver="Newton" cone="pyramidal"'), qpos=SLIDE_QPOS,
              qvel=SLIDE_QVEL)]),
    "weld_relpose_conjugate": (
        Case("weld, rotated relpose", EQ.format(eq='<weld body1="b" relpose="0 0 0 0.9 0.3 0.2 0.1"/>')),
        [Case("weld, identity relpose", EQ.format(eq='<weld body1="b" relpose="0 0 0 1 0 0 0"/>')),
         Case("connect instead of weld", EQ.format(eq='<connect body1="b" anchor="0 0 0"/>'))]),
    "joint_limit_upper": (
        Case("limited, driven into the upper end",
             pend(option='gravity="0 0 0"', jattr='limited="true" range="-0.5 0.5"'), qpos=(0.45,), qvel=(3.0,)),
        [Case("limited, driven into the lower end only",
              pend(option='gravity="0 0 0"', jattr='limited="true" range="-0.5 0.5"'), qpos=(-0.45,),
              qvel=(-3.0,)),
         Case("not limited, passing the upper end",
              pend(option='gravity="0 0 0"', jattr='limited="false" range="-0.5 0.5"'), qpos=(0.45,),
              qvel=(3.0,))]),
}

# -- running -------------------------------------------------------------------------------------

_MODELS: dict[str, tuple[mujoco.MjModel, object]] = {}
_BASE: dict[Case, np.ndarray] = {}
_BASE_STEP = jax.jit(lambda mx, dx: mjx.step(mx, dx))  # traced outside every patch


def _model(xml):
    if xml not in _MODELS:
        m = mujoco.MjModel.from_xml_string(xml)
        _MODELS[xml] = (m, mjx.put_model(m))
    return _MODELS[xml]


def _rollout(case: Case, step) -> np.ndarray:
    m, mx = _model(case.xml)
    d = mujoco.MjData(m)
    for name in ("qpos", "qvel", "ctrl", "act"):
        values = getattr(case, name)
        if values:
            getattr(d, name)[: len(values)] = values
    dx = mjx.put_data(m, d)
    out = []
    for _ in range(NSTEPS):
        dx = step(mx, dx)
        out.append(jnp.concatenate([dx.qpos, dx.qvel, dx.act, dx.sensordata]))
    out = np.asarray(jnp.stack(out))
    if not np.all(np.isfinite(out)):
        raise FloatingPointError(f"non-finite rollout for {case.label}")
    return out


def _base(case: Case) -> np.ndarray:
    if case not in _BASE:
        _BASE[case] = _rollout(case, _BASE_STEP)
    return _BASE[case]


def check(bug) -> bool:
    with_case, without_cases = CASES[bug.id]
    cases = [with_case, *without_cases]
    bases = [_base(c) for c in cases]  # before patching
    with pytest.MonkeyPatch.context() as mp:
        bug.patch(mp)
        step = jax.jit(lambda mx, dx: mjx.step(mx, dx))  # fresh function: traces the patched code
        patched = [_rollout(c, step) for c in cases]
    diffs = [float(np.max(np.abs(p - b))) for p, b in zip(patched, bases)]
    ok = diffs[0] > WITH_MIN and all(x < WITHOUT_MAX for x in diffs[1:])
    a, b = COMBINATIONS[bug.id]
    print(f"{'OK  ' if ok else 'FAIL'} {bug.id}  [{a}] x [{b}]")
    print(f"       with    {diffs[0]:10.3e}  ({with_case.label})")
    for c, x in zip(without_cases, diffs[1:]):
        print(f"       without {x:10.3e}  ({c.label})")
    sys.stdout.flush()
    return ok


def main(argv: list[str]) -> int:
    assert set(CASES) == {b.id for b in BUGS}, set(CASES) ^ {b.id for b in BUGS}
    chosen = [b for b in BUGS if not argv or b.id in argv]
    t0 = time.time()
    results = {b.id: check(b) for b in chosen}
    bad = [k for k, v in results.items() if not v]
    print(f"{len(results) - len(bad)}/{len(results)} bugs show only with their combination"
          f" ({time.time() - t0:.0f} s)" + (f"; failing: {', '.join(bad)}" if bad else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
