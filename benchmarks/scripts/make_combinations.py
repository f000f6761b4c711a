"""Writes scenarios/models/combinations*.xml: models whose elements form pairwise covering arrays of
the conditions MJX branches on (mjxdiff.tools.interactions.GROUPS). Run from the repository root:

    python benchmarks/scripts/make_combinations.py

Each actuator, frame sensor, tendon, equality and joint is one row of a covering array: e.g. the
15 general actuators hold every gaintype x dyntype pair once, with biastype = (gain + dyn) mod 3
(a Latin square: every gain x bias and bias x dyn pair too), and the frame sensors every sensor
type x reference type pair. The two models differ in their options (integrator, cone, solver,
impratio, flags), so that option x element pairs are covered too.
"""

from __future__ import annotations

from pathlib import Path

GAINS = ("fixed", "affine", "muscle")
BIASES = ("none", "affine", "muscle")
DYNS = ("none", "integrator", "filter", "filterexact", "muscle")
FRAME_TYPES = ("framepos", "framequat", "framexaxis", "framelinvel", "frameangvel")
ACC_TYPES = ("framelinacc", "frameangacc")
OBJTYPES = ("body", "xbody", "geom", "site")
REFTYPES = ("none", "body", "xbody", "geom", "site")
NPEND = 6
FRICTIONLOSS = ' frictionloss="0.005"'


def _gainprm(gain: str) -> str:
    return {"fixed": "0.4", "affine": "0.4 0 -0.02", "muscle": "0.75 1.05 2 200 0.5 1.6 1.5 1.3 1.2"}[gain]


def _biasprm(bias: str) -> str:
    # a muscle bias is the passive force, which acts above optimal length (1): this range puts the
    # pendulums' middle positions there
    return {"none": "0", "affine": "0 -0.3 -0.03", "muscle": "0.8 1.5 0.5 200 0.5 1.6 1.5 1.3 1.2"}[bias]


def _dynprm(dyn: str) -> str:
    return {"none": "1", "integrator": "1", "filter": "0.05", "filterexact": "0.03", "muscle": "0.01 0.04"}[dyn]


def actuators() -> list[str]:
    out = []
    k = 0
    for g, gain in enumerate(GAINS):
        for d, dyn in enumerate(DYNS):
            bias = BIASES[(g + d) % 3]
            # no actearly: MJX 3.17 ignores it (known divergence, tests/test_known_divergences.py)
            muscle = "muscle" in (gain, bias, dyn)
            attrs = [f'name="a{k}_{gain}_{bias}_{dyn}"', f'joint="p{k % NPEND}"', f'gaintype="{gain}"',
                     f'biastype="{bias}"', f'dyntype="{dyn}"', f'gainprm="{_gainprm(gain)}"',
                     f'biasprm="{_biasprm(bias)}"', f'dynprm="{_dynprm(dyn)}"']
            # ctrl range: muscles' activations live in [0, 1]; every third non-muscle actuator is unlimited
            if muscle:
                attrs.append('ctrlrange="0 1" lengthrange="-1.2 1.2"')
            elif k % 3 != 1:
                attrs.append('ctrlrange="-1 1"')
            if k % 2 == 0:
                attrs.append('forcerange="-0.25 0.25"')
            if dyn in ("integrator", "filter", "filterexact") and k % 3 != 2:
                attrs.append('actlimited="true" actrange="-0.4 0.4"')
            out.append("    <general " + " ".join(attrs) + "/>")
            k += 1
    return out


def limit_actuators() -> list[str]:
    """ctrllimited x forcelimited x actlimited rows for the model without the clamp (clampctrl
    disabled): the element pairs are the large bank's, these add the option's."""
    return ['    <general name="b0_limited_forced" joint="p0" gainprm="0.4" ctrlrange="-1 1" '
            'forcerange="-0.25 0.25"/>',
            '    <general name="b1_integrator_actlimited" joint="p1" dyntype="integrator" gainprm="0.4" '
            'actlimited="true" actrange="-0.4 0.4"/>',
            '    <general name="b2_filter_limited" joint="p2" dyntype="filter" dynprm="0.05" gainprm="0.4" '
            'ctrlrange="-1 1"/>',
            # no forcerange on a velocity-dependent actuator under implicitfast: C 4.0 drops a clamped
            # force's velocity derivative, MJX 3.17 does not (known divergence, test_known_divergences)
            '    <general name="b3_affine_unlimited" joint="p3" gainprm="0.4" biastype="affine" '
            'biasprm="0 -0.3 -0.03"/>',
            '    <general name="b4_forced" joint="p4" gainprm="0.4" forcerange="-0.25 0.25"/>']


def frame_sensors() -> list[str]:
    """Every frame type x reference type once, objects and frames chosen so that every pair of the
    group is held (identity references: the world body, a static body, the floor, a world site)."""
    obj = {"body": "p{}", "xbody": "p{}", "geom": "g{}", "site": "tip{}"}
    ref = {("body", "identity"): "anchor", ("body", "rotated"): "p{}", ("xbody", "identity"): "anchor",
           ("xbody", "rotated"): "anchor_rot", ("geom", "identity"): "floor", ("geom", "rotated"): "g{}",
           ("site", "identity"): "w_id", ("site", "rotated"): "w_rot"}
    out = []
    n = 0
    for t, kind in enumerate(FRAME_TYPES):
        for r, reftype in enumerate(REFTYPES):
            objtype = OBJTYPES[(t + r) % 4]
            frame = ("identity", "rotated")[(t + r // 2 + (r == 4)) % 2]
            attrs = [f'name="s{n}_{kind}"', f'objtype="{objtype}"',
                     f'objname="{obj[objtype].format(n % NPEND)}"']
            if reftype != "none":
                attrs += [f'reftype="{reftype}"', f'refname="{ref[reftype, frame].format((n + 1) % NPEND)}"']
            out.append(f"    <{kind} " + " ".join(attrs) + "/>")
            n += 1
    for kind in ACC_TYPES:
        for objtype in OBJTYPES:
            out.append(f'    <{kind} name="s{n}_{kind}" objtype="{objtype}"'
                       f' objname="{obj[objtype].format(n % NPEND)}"/>')
            n += 1
    return out


def pendulums(implicit: bool) -> list[str]:
    out = []
    for k in range(NPEND):
        damping = 0 if k == 5 else 0.03
        stiff = ' stiffness="0.4"' if k in (1, 3) else ""
        fl = ' frictionloss="0.005"' if k == 2 else ""
        margin = ' margin="0.02"' if k in (0, 4) else ""
        solref = {0: "", 1: ' solreflimit="0.01 1"', 2: ' solreflimit="0.0035 1"'}[k % 3]
        grav = ' gravcomp="1"' if implicit and k % 2 else ""
        out.append(f'    <body name="p{k}" pos="{0.5 * k:g} 0 1.5"{grav}>\n'
                   f'      <joint name="p{k}" axis="0 1 0" range="-1.2 1.2"'
                   f' damping="{damping}"{stiff}{fl}{margin}{solref}/>\n'
                   f'      <geom name="g{k}" fromto="0 0 0 0.05 0 -0.3" size="0.02" mass="0.2"/>\n'
                   f'      <site name="mid{k}" pos="0 0 -0.15" size="0.01"/>\n'
                   f'      <site name="tip{k}" pos="0.05 0 -0.3" size="0.01"/>\n'
                   f'    </body>')
    return out


def model(name: str, option: str, implicit: bool) -> str:
    free = "" if implicit else """    <body name="ball" pos="0.3 -0.6 0.35">
      <freejoint/>
      <geom type="sphere" size="0.05" mass="0.1" contype="1" conaffinity="1"/>
    </body>
    <body name="wobble" pos="-0.6 0 1.2">
      <joint name="wobble" type="ball" range="0 0.8" damping="0.01"/>
      <geom fromto="0 0 0 0.1 0 -0.3" size="0.02" mass="0.2"/>
    </body>
"""
    # implicitfast integrates free/ball rotation differently in C 4.0 and MJX 3.17 (known): slides only
    puck = """    <body name="puck" pos="0.3 -0.6 0.048">
      <joint name="puck_x" type="slide" axis="1 0 0"/>
      <joint name="puck_z" type="slide" axis="0 0 1" range="-0.1 0.3" margin="0.01"/>
      <geom type="sphere" size="0.05" mass="0.1" contype="1" conaffinity="1"/>
    </body>
""" if implicit else ""
    # implicitfast: C 4.0 keeps qDeriv within M's sparsity, MJX 3.17 adds a damped tendon's cross-tree
    # terms (known divergence, test_known_divergences): damped tendons couple one tree only there
    couple_damping = "" if implicit else ' damping="0.05"'
    # frame sensors and the actuator-dynamics bank pair with no option: the Euler model holds them
    sensors = "" if implicit else "  <sensor>\n" + "\n".join(frame_sensors()) + "\n  </sensor>"
    push = ('    <motor name="press" joint="puck_z" gear="-2" ctrlrange="0 1"/>\n'
            '    <motor name="shove" joint="puck_x" ctrlrange="-0.3 0.3"/>\n') if implicit else ""
    return f"""<mujoco model="{name}">
  <!-- Generated by benchmarks/scripts/make_combinations.py: covering arrays of the conditions MJX branches on
       (mjxdiff.tools.interactions.GROUPS). Do not edit by hand. -->
  {option}
  <default><geom type="capsule" contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" contype="1" conaffinity="1"/>
    <site name="w_id" pos="0 0.5 2" size="0.01"/>
    <site name="w_rot" pos="0.3 0.5 2" euler="30 20 10" size="0.01"/>
    <body name="anchor" pos="-0.5 0.5 2"><geom type="box" size="0.02 0.02 0.02"/></body>
    <body name="anchor_rot" pos="-0.8 0.5 2" euler="10 40 0"><geom type="box" size="0.02 0.03 0.04"/></body>
{chr(10).join(pendulums(implicit))}
    <body name="slider" pos="-0.3 0 1.0">
      <joint name="slider" type="slide" axis="0 0 1" range="-0.1 0.1" margin="0.005" damping="0.2"/>
      <geom type="box" size="0.03 0.03 0.03" mass="0.2"/>
    </body>
{free}{puck}  </worldbody>
  <tendon>
    <fixed name="t_point" stiffness="0.5"{couple_damping}><joint joint="p0" coef="1"/><joint joint="p1" coef="-1"/></fixed>
    <fixed name="t_range" stiffness="0.5" springlength="-0.15 0.15" limited="true" range="-1.2 1.2"><joint joint="p2" coef="1"/><joint joint="p3" coef="0.5"/></fixed>
    <fixed name="t_plain" limited="true" range="-0.8 0.8" damping="0.05"><joint joint="p4" coef="1"/></fixed>
    <spatial name="s_range" stiffness="2" springlength="0.55 0.7" damping="0.1"><site site="w_id"/><site site="tip3"/></spatial>
    <spatial name="s_point" stiffness="2" limited="true" range="0.3 1.2"><site site="mid4"/><site site="mid5"/></spatial>
    <spatial name="s_plain"{couple_damping}><site site="mid0"/><site site="tip1"/></spatial>
    <fixed name="t_bare" limited="true" range="-0.9 0.9"><joint joint="p5" coef="1"/></fixed>
  </tendon>
  <equality>
    <joint name="e_joint" joint1="p2" joint2="p3" polycoef="0 -0.5 0 0 0"/>
    <joint name="e_joint_custom" joint1="slider" polycoef="0 0 0 0 0" solref="0.05 1"/>
    <joint name="e_joint_unsafe" joint1="p5" joint2="p4" polycoef="0 0.3 0 0 0" solref="0.0035 1"/>
    <tendon name="e_tendon" tendon1="t_plain" tendon2="s_plain" polycoef="0 0.2 0 0 0"/>
    <tendon name="e_tendon_custom" tendon1="s_point" polycoef="0 0 0 0 0" solref="0.04 0.8"/>
    <tendon name="e_tendon_unsafe" tendon1="t_point" tendon2="t_range" polycoef="0 0.1 0 0 0" solref="0.0035 1"/>
  </equality>
  <actuator>
{chr(10).join(limit_actuators() if implicit else actuators())}
    <position name="servo" joint="slider" kp="20" kv="1" ctrlrange="-0.15 0.15"/>
{push}  </actuator>
{sensors}
</mujoco>
"""  # noqa: E501 - the generated XML, line for line


def small(name: str, option: str, damping: float, rk4: bool) -> str:
    """Three pendulums, a slide limit and a puck pressed onto the floor (gravity may be off), with
    unlimited actuators of every kind: option x passive-term pairs the two large models cannot
    hold. No sensors, no free or ball joint (RK4 differs on both: integrator_rk4 notes)."""
    joints = "\n".join(
        f'    <body name="p{k}" pos="{0.5 * k:g} 0 1.5">\n'
        f'      <joint name="p{k}" axis="0 1 0" range="-1.2 1.2" damping="{damping:g}" stiffness="{0.3 * (k != 1):g}"'
        f'{FRICTIONLOSS if k == 1 else ""}/>\n'
        f'      <geom fromto="0 0 0 0.05 0 -0.3" size="0.02" mass="0.2"/>\n    </body>' for k in range(3))
    return f"""<mujoco model="{name}">
  <!-- Generated by benchmarks/scripts/make_combinations.py. Do not edit by hand. -->
  {option}
  <default><geom type="capsule" contype="0" conaffinity="0"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="3 3 0.1" contype="1" conaffinity="1"/>
{joints}
    <body name="slider" pos="-0.3 0 1.0">
      <joint name="slider" type="slide" axis="0 0 1" range="-0.1 0.1" margin="0.005" solreflimit="0.0035 1"/>
      <geom type="box" size="0.03 0.03 0.03" mass="0.2"/>
    </body>
    <body name="puck" pos="0.3 -0.6 0.048">
      <joint name="puck_x" type="slide" axis="1 0 0"/>
      <joint name="puck_z" type="slide" axis="0 0 1" range="-0.1 0.3"/>
      <geom type="sphere" size="0.05" mass="0.1" contype="1" conaffinity="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="press" joint="puck_z" gear="-2" ctrlrange="0 1"/>
    <motor name="shove" joint="puck_x" forcerange="-0.2 0.2"/>
    <general name="integrate" joint="p0" dyntype="integrator" gainprm="0.3" biastype="affine" biasprm="0 -0.3 0"/>
    <general name="filter" joint="p1" dyntype="filter" dynprm="0.05" gainprm="0.3"/>
    <velocity name="damp" joint="p2" kv="0.05" forcerange="-0.3 0.3"/>
    <position name="servo" joint="slider" kp="20" kv="1"/>
  </actuator>
</mujoco>
"""


def main() -> None:
    root = Path(__file__).resolve().parents[2] / "scenarios" / "models"
    # both Newton models converge: at tolerance 1e-10 MJX and C stopped at different points on some
    # draws (combinations seed 51: 0.068 of a sensor's tolerance; combinations_implicit seed 55: 0.020
    # of qvel's, where the median seed is 1e-8 of it)
    converged = ('<!-- Solver converged (tolerance 1e-14, 100 iterations and line-search steps): at 1e-10 MJX\n'
                 "       and C stopped at different points on some draws. A bundled scenario's pass must be sharp."
                 ' -->\n  ')
    explicit = (converged + '<option timestep="0.002" integrator="Euler" cone="elliptic" solver="Newton" impratio="2" '
                'iterations="100" tolerance="1e-14" ls_iterations="100">\n'
                '    <flag eulerdamp="disable" warmstart="disable"/>\n  </option>')
    implicit = (converged + '<option timestep="0.002" integrator="implicitfast" cone="pyramidal" solver="Newton" '
                'impratio="1.5" iterations="100" tolerance="1e-14" ls_iterations="100">\n'
                '    <flag refsafe="disable" clampctrl="disable" gravity="disable"/>\n  </option>')
    (root / "combinations.xml").write_text(model("combinations", explicit, implicit=False))
    (root / "combinations_implicit.xml").write_text(model("combinations_implicit", implicit, implicit=True))
    undamped = ('<option timestep="0.002" integrator="Euler" cone="elliptic" solver="CG" impratio="1.5" '
                'iterations="100" tolerance="1e-12" ls_iterations="30">\n'
                '    <flag eulerdamp="disable" spring="disable" damper="disable" warmstart="disable"'
                ' gravity="disable"/>\n  </option>')
    (root / "combinations_undamped.xml").write_text(small("combinations_undamped", undamped, 0.0, rk4=False))


if __name__ == "__main__":
    main()
