"""Hypothesis draws of each part of a model, into a :class:`~mjxdiff.tools.mjcf_spec._Spec`.

One function per part, each ``(draw, spec, ...)`` and each shrinking to the simple case:
``<option>`` values, the kinematic tree and its joints, geoms and their contact parameters,
tendons (fixed, spatial, wrapping), actuators, equality constraints, sensors, a disable flag,
and the injectors that add exactly one feature MJX does not support. The public strategy that
calls them in order is :func:`mjxdiff.tools.strategies.mjcf_models`.
"""

from __future__ import annotations

import functools
import itertools
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mjxdiff.compare.support import UNSUPPORTED_PAIRS, pair_supported
from mjxdiff.tools.mjcf_spec import (_MASKS, _UNSUPPORTED_BY_NAME, DEFAULT_OPTIONS, GEOM_TYPES, _Body, _f,
                                     _helper_body, _isolated_pair, _mesh_vertices, _shape, _Spec, _tag, _vec)


def _value(draw: Callable, x: Any) -> Any:
    """``x`` itself, or a value drawn from it when it is a strategy."""
    return draw(x) if isinstance(x, st.SearchStrategy) else x


@functools.cache  # strategies are built once: Hypothesis validates each new one on first draw
def _floats(lo: float, hi: float) -> st.SearchStrategy:
    """Finite floats in [lo, hi] without subnormals (which only clutter the XML)."""
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False, allow_subnormal=False)


@functools.cache
def _maybe(default: Any, alternative: st.SearchStrategy) -> st.SearchStrategy:
    """``default`` first (what shrinking reaches), else a value from ``alternative``."""
    return st.one_of(st.just(default), alternative)


@functools.cache
def _ints(lo: int, hi: int) -> st.SearchStrategy:
    return st.integers(lo, hi)


@functools.cache
def _sampled(values: tuple) -> st.SearchStrategy:
    return st.sampled_from(values)


@functools.cache
def _box(*bounds: tuple[float, float]) -> st.SearchStrategy:
    """Tuples of floats, the i-th in ``bounds[i] = (lo, hi)``."""
    return st.tuples(*(_floats(lo, hi) for lo, hi in bounds))


@functools.cache
def _optional(strategy: st.SearchStrategy) -> st.SearchStrategy:
    """None first (what shrinking reaches), else a value from ``strategy``."""
    return st.none() | strategy


_AXES = ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.0, 1.0, 1.0))
_CHILD_OFFSETS = ((0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (0.0, 0.0, -0.3), (0.2, 0.2, 0.0))
_SIZE = _floats(0.02, 0.3)  # m
_SIZE2 = st.tuples(_maybe(0.05, _SIZE), _maybe(0.1, _SIZE))
_SIZE3 = st.tuples(_maybe(0.1, _SIZE), _maybe(0.1, _SIZE), _maybe(0.1, _SIZE))


def _options(draw: Callable, options: Any, mjx_only: bool) -> dict[str, Any]:
    """``<option>`` attributes: :data:`DEFAULT_OPTIONS`, overridden or drawn."""
    options = _value(draw, options)
    opt = dict(DEFAULT_OPTIONS)
    if isinstance(options, Mapping):
        opt.update(options)
        return opt
    if not options:
        return opt
    opt["timestep"] = draw(_maybe(0.002, _floats(0.002, 0.01)))
    opt["integrator"] = draw(_sampled(("Euler", "RK4", "implicitfast") + (() if mjx_only else ("implicit",))))
    opt["cone"] = draw(_sampled(("pyramidal", "elliptic")))
    opt["solver"] = draw(_sampled(("Newton", "CG") + (() if mjx_only else ("PGS",))))
    opt["iterations"] = draw(_maybe(100, _ints(20, 200)))
    opt["ls_iterations"] = draw(_maybe(50, _ints(10, 100)))
    opt["tolerance"] = draw(_maybe(1e-10, _sampled((1e-8, 1e-9, 1e-12))))
    if opt["cone"] == "elliptic":
        opt["impratio"] = draw(_maybe(1.0, _floats(1.0, 5.0)))
    if opt["integrator"] != "implicitfast":  # MJX: no fluid forces under implicitfast
        opt["density"] = draw(_maybe(0.0, _floats(0.5, 1.5)))
        opt["viscosity"] = draw(_maybe(0.0, _floats(1e-4, 1e-2)))
    return opt


def _option_features(opt: Mapping[str, Any]) -> set[str]:
    out = set()
    if opt["integrator"] != "Euler":
        out.add(f"{opt['integrator']} integrator")
    if opt["cone"] != "pyramidal":
        out.add(f"{opt['cone']} cone")
    if opt["solver"] != "Newton":
        out.add(f"{opt['solver']} solver")
    if opt["timestep"] != DEFAULT_OPTIONS["timestep"]:
        out.add("timestep")
    for k in ("iterations", "ls_iterations", "tolerance"):
        if opt[k] != DEFAULT_OPTIONS[k]:
            out.add(f"solver {k}")
    if opt.get("impratio", 1.0) != 1.0:
        out.add("impratio")
    if opt.get("density", 0.0) or opt.get("viscosity", 0.0):
        out.add("fluid drag")
    return out


def _joint(draw: Callable, name: str, jtype: str) -> tuple[dict[str, str], set[str]]:
    """A joint's attributes and the features it uses (hinge/slide ranges contain 0)."""
    attrs: dict[str, str] = {"name": name, "type": jtype}
    features = {f"{jtype} joint"}
    if jtype in ("hinge", "slide"):
        attrs["axis"] = _vec(draw(_sampled(_AXES)))
    for key, lo, hi in (("damping", 0.01, 2.0), ("stiffness", 0.1, 10.0),
                        ("armature", 0.001, 0.1), ("frictionloss", 0.001, 0.5)):
        v = draw(_maybe(0.0, _floats(lo, hi)))
        if v:
            attrs[key] = _f(v)
            features.add(f"joint {key}")
    if jtype in ("hinge", "slide"):
        span = 1.5 if jtype == "hinge" else 0.3  # rad or m
        if "stiffness" in attrs:
            springref = draw(_maybe(0.0, _floats(-0.5 * span, 0.5 * span)))
            if springref:
                attrs["springref"] = _f(springref)
                features.add("joint springref")
        rng = draw(_optional(_box((-span, -0.1 * span), (0.1 * span, span))))
        if rng is not None:
            attrs["limited"], attrs["range"] = "true", _vec(rng)
            features.add("joint limit")
            solref = draw(_optional(_box((0.01, 0.05), (0.5, 1.5))))
            if solref is not None:
                attrs["solreflimit"] = _vec(solref)
                features.add("limit solref")
            solimp = draw(_optional(_box((0.8, 0.9), (0.92, 0.99), (0.001, 0.01))))
            if solimp is not None:
                attrs["solimplimit"] = _vec(solimp)
                features.add("limit solimp")
            # below half the narrower side: with both sides inside the margin C adds two rows, MJX one
            margin = draw(_maybe(0.0, _floats(0.0, 0.4 * min(-rng[0], rng[1]))))
            if margin:
                attrs["margin"] = _f(margin)
                features.add("limit margin")
    return attrs, features


def _geom(draw: Callable, spec: _Spec, name: str, gtype: str, first: bool) -> dict[str, str]:
    """A body geom's shape attributes (sizes in m); a mesh adds its asset to ``spec``."""
    attrs: dict[str, str] = {"name": name, "type": gtype}
    if gtype == "sphere":
        attrs["size"] = _f(draw(_maybe(0.1, _SIZE)))
    elif gtype in ("capsule", "cylinder"):
        attrs["size"] = _vec(draw(_SIZE2))
    elif gtype in ("box", "ellipsoid"):
        attrs["size"] = _vec(draw(_SIZE3))
    else:
        scale = draw(_maybe(0.1, _floats(0.02, 0.2)))
        nextra = draw(_ints(0, 4))
        extra = draw(hnp.arrays(np.float64, (nextra, 3), elements=_floats(-1, 1)))
        spec.assets.append(_tag("mesh", {"name": f"mesh_{name}", "vertex": _vec(_mesh_vertices(scale, extra).ravel())}))
        attrs["mesh"] = f"mesh_{name}"
    if not first:
        attrs["pos"] = _vec(draw(_box(*[(-0.1, 0.1)] * 3)))
    if gtype != "sphere":
        euler = draw(_optional(_box(*[(-3.14, 3.14)] * 3)))
        if euler is not None:
            attrs["euler"] = _vec(euler)
            spec.features.add("geom orientation")
    return attrs


def _contact_attrs(draw: Callable, spec: _Spec, geom: dict[str, str], mjx_only: bool, allow_margin: bool) -> None:
    """Adds drawn contact parameters (condim, friction, solref, solimp, margin) to ``geom``."""
    condims = (3, 1, 4, 6)
    if mjx_only and spec.option["cone"] == "elliptic":
        condims = (3, 4, 6)  # MJX: condim 1 with an elliptic cone raises in make_data
    condim = draw(_sampled(condims))
    if condim != 3:
        geom["condim"] = str(condim)
        spec.features.add(f"condim {condim}")
    friction = draw(_optional(_box((0.1, 1.5), (1e-3, 1e-2), (1e-5, 1e-3))))
    if friction is not None:
        geom["friction"] = _vec(friction)
        spec.features.add("geom friction")
    # time constants >= 2 * the largest timestep, so no solref clamping
    solref = draw(_optional(_box((0.02, 0.1), (0.5, 2.0))))
    if solref is not None:
        geom["solref"] = _vec(solref)
        spec.features.add("geom solref")
    solimp = draw(_optional(_box((0.5, 0.9), (0.9, 0.999), (5e-4, 1e-2))))
    if solimp is not None:
        geom["solimp"] = _vec(solimp)
        spec.features.add("geom solimp")
    if allow_margin:
        margin = draw(_maybe(0.0, _floats(1e-3, 1e-2)))
        if margin:
            geom["margin"] = _f(margin)
            spec.features.add("contact margin")


def _tree(draw: Callable, spec: _Spec, max_bodies: int, joint_types: tuple[str, ...]) -> None:
    """Bodies (each with one joint) in a tree; free joints only on children of the world."""
    n = draw(_ints(1, max_bodies))
    nroots = 0
    for i in range(n):
        allowed = tuple(t for t in joint_types if t != "free")
        parent = draw(_ints(0, i)) - 1 if allowed else -1  # 0 draws the world
        if parent < 0:
            allowed = joint_types
            pos = (1.0 * nroots, 0.0, 0.5)  # roots 1 m apart, 0.5 m above the ground
            nroots += 1
        else:
            # lengths grow with i, so no two bodies start exactly on top of each other
            pos = tuple(x * (1 + 0.1 * i) for x in draw(_sampled(_CHILD_OFFSETS)))
        jtype = draw(_sampled(allowed))
        joint, features = _joint(draw, f"j{i}", jtype)
        spec.features |= features
        spec.bodies.append(_Body(name=f"b{i}", parent=parent, pos=pos, joint=joint))
    nchildren = [sum(b.parent == i for b in spec.bodies) for i in range(n)]
    if max(nchildren) > 1:
        spec.features.add("branching tree")
    if max(nchildren) > 0:
        spec.features.add("nested bodies")


def _geoms(draw: Callable, spec: _Spec, max_geoms: int, geom_types: tuple[str, ...],
           contacts: bool, mjx_only: bool) -> None:
    """Geoms on every body, an optional ground plane, and their contact parameters."""
    for i, body in enumerate(spec.bodies):
        for k in range(draw(_ints(1, max_geoms))):
            gtype = draw(_sampled(geom_types))
            body.geoms.append(_geom(draw, spec, f"g{i}_{k}", gtype, first=k == 0))
            spec.features.add(f"{gtype} geom")
    plane = draw(st.booleans())
    if plane:
        spec.features.add("ground plane")
    geoms = [g for b in spec.bodies for g in b.geoms]
    masked = False
    if not contacts:
        for g in geoms:
            g["contype"] = g["conaffinity"] = "0"
        spec.features.add("no contacts")
    else:
        # MJX: no margin on any pair involving a mesh
        allow_margin = not (mjx_only and any(g["type"] == "mesh" for g in geoms))
        # MJX: only supported pairs may collide; masks only when some present pair is not
        present = {g["type"] for g in geoms} | ({"plane"} if plane else set())
        masked = mjx_only and not all(pair_supported(a, b) for a, b in itertools.combinations(present, 2))
        for g in geoms:
            _contact_attrs(draw, spec, g, mjx_only, allow_margin)
            if masked:
                g["contype"] = g["conaffinity"] = str(_MASKS[g["type"]])
        if masked:
            spec.features.add("collision masks")
    if plane:
        floor = {"name": "floor", "type": "plane", "size": "0 0 1"}
        if not contacts:
            floor["contype"] = floor["conaffinity"] = "0"
        elif masked:
            floor["contype"] = floor["conaffinity"] = str(_MASKS["plane"])
        spec.world_geom(floor)


def _other_body(draw: Callable, a: int, nbody: int) -> int:
    """A body index other than ``a`` among ``nbody`` bodies, or -1 for the world (drawn first)."""
    k = draw(_ints(0, nbody - 1)) - 1
    return k + (k >= a) if k >= 0 else -1


def _tendons(draw: Callable, spec: _Spec, geom_types: tuple[str, ...] = GEOM_TYPES) -> None:
    """Fixed tendons on hinge/slide joints and spatial tendons between sites."""
    joints = spec.scalar_joints()
    for k in range(draw(_ints(1, 2))):
        kind = draw(_sampled(("fixed", "spatial") if joints else ("spatial",)))
        attrs: dict[str, str] = {"name": f"t{k}"}
        for key, lo, hi in (("stiffness", 0.1, 10.0), ("damping", 0.01, 1.0), ("frictionloss", 0.001, 0.1),
                            ("armature", 0.001, 0.05)):
            v = draw(_maybe(0.0, _floats(lo, hi)))
            if v:
                attrs[key] = _f(v)
                spec.features.add(f"tendon {key}")
        if kind == "fixed":
            limit = draw(_optional(_box((-1.0, -0.2), (0.2, 1.0))))
            if limit is not None:  # qpos0 (every joint at 0) is inside it
                attrs["limited"], attrs["range"] = "true", _vec(limit)
                spec.features.add("tendon limit")
            names = draw(st.lists(_sampled(joints), min_size=1, max_size=min(3, len(joints)), unique=True))
            coefs = [draw(_maybe(1.0, _floats(0.1, 2.0))) * draw(_sampled((1, -1))) for _ in names]
            inner = "".join(_tag("joint", {"joint": j, "coef": _f(c)}) for j, c in zip(names, coefs))
            spec.fixed_tendons.append(attrs["name"])
        else:
            a = draw(_ints(0, len(spec.bodies) - 1))
            b = _other_body(draw, a, len(spec.bodies))
            if b < 0:
                if not any('name="anchor"' in w for w in spec.world):
                    spec.world.append(_tag("site", {"name": "anchor", "pos": "0 1 1.5"}))
                other = "anchor"
            else:
                other = spec.site(b)
            inner = _tag("site", {"site": spec.site(a)})
            # MuJoCo: tendon armature does not work with geom wrapping
            shapes = tuple(t for t in ("sphere", "cylinder") if t in geom_types)
            wrap = None if "armature" in attrs or not shapes else draw(_optional(_sampled(shapes)))
            if wrap is not None:
                inner += _wrap_geom(draw, spec, a, k, wrap)
            inner += _tag("site", {"site": other})
            divisor = draw(_optional(_floats(1.5, 3.0)))
            if divisor is not None:  # a second branch from a world site to the same body
                name = f"pulley{k}"
                spec.world.append(_tag("site", {"name": name, "pos": _vec(spec.world_pos(a) + (0.2, 0.0, 1.0))}))
                inner += _tag("pulley", {"divisor": _f(divisor)}) + _tag("site", {"site": name})
                inner += _tag("site", {"site": spec.site(a)})
                spec.features.add("tendon pulley")
        spec.tendon.append(_tag(kind, attrs, inner))
        spec.features.add(f"{kind} tendon")


def _wrap_geom(draw: Callable, spec: _Spec, a: int, k: int, shape: str) -> str:
    """A non-colliding sphere or cylinder on body ``a``, 0.1 m above its site, for a spatial
    tendon to wrap around (``<geom>`` element of the tendon), with a side site or not."""
    name = f"wrap{k}"
    radius = draw(_floats(0.02, 0.05))
    geom = {"name": name, "type": shape, "pos": "0 0 0.1", "mass": "0.01", "contype": "0", "conaffinity": "0",
            "size": _f(radius) if shape == "sphere" else f"{_f(radius)} 0.05"}
    if shape == "cylinder":
        geom["zaxis"] = "0 1 0"
    spec.bodies[a].geoms.append(geom)
    spec.features.add("tendon geom wrap")
    attrs = {"geom": name}
    if draw(st.booleans()):
        side = f"side{k}"
        spec.bodies[a].sites.append({"name": side, "pos": f"0 0 {_f(0.12 + radius)}", "size": "0.01"})
        attrs["sidesite"] = side
        spec.features.add("tendon wrap sidesite")
    return _tag("geom", attrs)


def _actuators(draw: Callable, spec: _Spec) -> None:
    """Motor/position/velocity/general actuators on hinge/slide joints and fixed tendons."""
    targets = tuple(("joint", j) for j in spec.scalar_joints()) + tuple(("tendon", t) for t in spec.fixed_tendons)
    targets += tuple(("ball", j) for j in spec.joints_of("ball")) + tuple(("free", j) for j in spec.joints_of("free"))
    if not targets:
        return
    for n in range(draw(_ints(1, 3))):
        trn, target = draw(_sampled(targets))
        if trn in ("ball", "free"):
            spec.actuator.append(_rotational_actuator(draw, spec, f"a{n}", trn, target))
            continue
        kind = draw(_sampled(("motor", "position", "velocity", "general")))
        attrs: dict[str, str] = {"name": f"a{n}", trn: target}
        gear = draw(_maybe(1.0, _floats(0.5, 5.0)))
        if gear != 1.0:
            attrs["gear"] = _f(gear)
            spec.features.add("actuator gear")
        ctrlrange = draw(_maybe((-1.0, 1.0), _optional(_box((-2, -0.1), (0.1, 2)))))
        if ctrlrange is not None:
            attrs["ctrllimited"], attrs["ctrlrange"] = "true", _vec(ctrlrange)
        forcerange = draw(_optional(_box((-2.0, -0.05), (0.05, 2.0))))
        if forcerange is not None:
            attrs["forcelimited"], attrs["forcerange"] = "true", _vec(forcerange)
            spec.features.add("actuator force limit")
        if kind == "position":
            attrs["kp"] = _f(draw(_maybe(10.0, _floats(1.0, 50.0))))
        elif kind == "velocity":
            attrs["kv"] = _f(draw(_maybe(1.0, _floats(0.1, 5.0))))
        elif kind == "general":
            dyntype = draw(_sampled(("none", "filter", "filterexact", "integrator")))
            attrs["dyntype"] = dyntype
            if dyntype in ("filter", "filterexact"):
                attrs["dynprm"] = _f(draw(_floats(0.02, 0.2)))  # time constant (s)
            if dyntype != "none":
                spec.features.add(f"{dyntype} dynamics")
                actrange = draw(_optional(_box((-1.0, -0.1), (0.1, 1.0))))
                if actrange is not None:
                    attrs["actlimited"], attrs["actrange"] = "true", _vec(actrange)
                    spec.features.add("activation limit")
            gain = [draw(_maybe(1.0, _floats(0.1, 10.0)))]
            if draw(st.booleans()):  # affine gain: gain + gain_length * length + gain_velocity * velocity
                attrs["gaintype"] = "affine"
                gain += [draw(_maybe(0.0, _floats(-2.0, 2.0))), draw(_maybe(0.0, _floats(-1.0, 0.0)))]
                spec.features.add("affine gain")
            attrs["gainprm"] = _vec(gain)
            if draw(st.booleans()):  # affine bias: a spring-damper towards a drawn offset
                attrs["biastype"] = "affine"
                attrs["biasprm"] = _vec((draw(_floats(-1.0, 1.0)), -draw(_floats(0.0, 5.0)),
                                         -draw(_floats(0.0, 0.5))))
                spec.features.add("affine bias")
        spec.actuator.append(_tag(kind, attrs))
        spec.features.add(f"{kind} actuator")
        if trn == "tendon":
            spec.features.add("tendon actuator")


def _rotational_actuator(draw: Callable, spec: _Spec, name: str, jtype: str, joint: str) -> str:
    """A motor on a ball joint (gear: a rotation axis) or a free joint (gear: force and torque),
    acting in the joint's frame or its parent's (``jointinparent``)."""
    trn = draw(_sampled(("joint", "jointinparent")))
    width = 3 if jtype == "ball" else 6
    gear = np.zeros(width)
    gear[draw(_ints(0, width - 1))] = draw(_floats(0.2, 1.0))
    spec.features.add(f"{jtype} joint actuator")
    if trn == "jointinparent":
        spec.features.add("jointinparent actuator")
    return _tag("motor", {"name": name, trn: joint, "gear": _vec(gear), "ctrllimited": "true", "ctrlrange": "-1 1"})


def _equalities(draw: Callable, spec: _Spec) -> None:
    """connect/weld between distinct bodies (or the world), joint between hinge/slide joints."""
    joints = spec.scalar_joints()
    nb = len(spec.bodies)
    for _ in range(draw(_ints(1, 2))):
        kind = draw(_sampled(("connect", "weld", "joint", "mocap") if joints else ("connect", "weld", "mocap")))
        if kind == "mocap":  # a static mocap body where body a starts, turned by a drawn angle
            a = draw(_ints(0, nb - 1))
            name = f"mocap{len(spec.equality)}"
            angle = draw(_floats(0.0, 1.0))
            quat = (np.cos(angle / 2), 0.0, np.sin(angle / 2), 0.0)
            spec.world.append(_tag("body", {"name": name, "mocap": "true", "pos": _vec(spec.world_pos(a)),
                                            "quat": _vec(quat)}))
            spec.mocap_bodies += 1
            spec.equality.append(_tag(draw(_sampled(("connect", "weld"))),
                                      {"body1": f"b{a}", "body2": name, "anchor": "0 0 0"}))
            spec.features.add("mocap body")
            continue
        if kind == "joint":
            i1 = draw(_ints(0, len(joints) - 1))
            i2 = draw(_optional(_ints(0, len(joints) - 2))) if len(joints) > 1 else None
            j2 = None if i2 is None else joints[i2 + (i2 >= i1)]  # any joint but the first
            attrs = {"joint1": joints[i1], "joint2": j2}
            poly = draw(_optional(st.tuples(_floats(-0.2, 0.2), _floats(0.5, 1.5), _floats(-0.3, 0.3))))
            if poly is not None:
                attrs["polycoef"] = _vec((*poly, 0.0, 0.0))
                spec.features.add("joint equality polycoef")
        else:
            a = draw(_ints(0, nb - 1))
            b = _other_body(draw, a, nb)
            attrs = {"body1": f"b{a}", "body2": "world" if b < 0 else f"b{b}"}
            if kind == "connect":
                attrs["anchor"] = "0 0 0"
        spec.equality.append(_tag(kind, attrs))
        spec.features.add(f"{kind} equality")


_SITE_SENSORS = ("accelerometer", "gyro", "velocimeter", "touch", "rangefinder")
_BODY_SENSORS = ("framepos", "framequat", "subtreecom", "framexaxis", "framelinvel", "frameangvel")
#: Frame sensors MJCF lets measure relative to another object's frame (reftype/refname).
_REFERENCED = ("framepos", "framequat", "framexaxis", "framelinvel", "frameangvel")


def _sensors(draw: Callable, spec: _Spec, touch: bool) -> None:
    """Joint, frame, subtree and site sensors on existing objects (touch only when ``touch``)."""
    joints, balls = spec.scalar_joints(), spec.joints_of("ball")
    actuators = [a for a in (re.search(r'name="(a\d+)"', x) for x in spec.actuator) if a]
    site_sensors = tuple(k for k in _SITE_SENSORS if touch or k != "touch")
    kinds = (("jointpos", "jointvel") if joints else ()) + _BODY_SENSORS + site_sensors + ("clock",)
    kinds += ("ballquat", "ballangvel") if balls else ()
    kinds += ("actuatorpos", "actuatorvel", "actuatorfrc") if actuators else ()
    for _ in range(draw(_ints(1, 4))):
        kind = draw(_sampled(kinds))
        if kind == "clock":
            attrs = {}
        elif kind in ("ballquat", "ballangvel"):
            attrs = {"joint": draw(_sampled(balls))}
        elif kind.startswith("actuator"):
            attrs = {"actuator": draw(_sampled(tuple(a.group(1) for a in actuators)))}
        elif kind in ("jointpos", "jointvel"):
            attrs = {"joint": draw(_sampled(joints))}
        else:
            b = draw(_ints(0, len(spec.bodies) - 1))
            if kind == "subtreecom":
                attrs = {"body": f"b{b}"}
            elif kind in _BODY_SENSORS:
                objtype = draw(_sampled(("body", "xbody", "site")))
                attrs = {"objtype": objtype, "objname": spec.site(b) if objtype == "site" else f"b{b}"}
                if kind in _REFERENCED:
                    ref = draw(_optional(st.tuples(_sampled(("body", "xbody", "site")),
                                                   _ints(-1, len(spec.bodies) - 1))))
                    if ref is not None:  # body -1: the world (an identity frame)
                        reftype, r = ref
                        attrs["reftype"] = reftype
                        attrs["refname"] = ("world" if r < 0 else f"b{r}") if reftype != "site" else (
                            spec.site(r) if r >= 0 else spec.world_site())
                        spec.features.add(f"{kind} reference frame")
            else:
                attrs = {"site": spec.site(b)}
        if kind == "rangefinder" and '<material name="mat0"/>' not in spec.assets:
            spec.assets.append('<material name="mat0"/>')  # MJX traces ray() only with nmat > 0
        spec.sensor.append(_tag(kind, attrs))
        spec.features.add(f"{kind} sensor")


#: Disable flags the generator draws: each switches an MJX code path without removing the
#: model's point. "passive" disables springs and dampers together (alone, either is a known
#: divergence: tests/test_known_divergences.py), and only with eulerdamp disabled too (MJX's
#: Euler step damps implicitly whatever the damper flag says: a known divergence as well).
DISABLE_FLAGS = ("eulerdamp", "clampctrl", "warmstart", "refsafe", "gravity", "filterparent", "passive")


def _disable_flags(draw: Callable, spec: _Spec) -> None:
    """At most one of :data:`DISABLE_FLAGS`, shrinking to none."""
    flag = draw(_optional(_sampled(DISABLE_FLAGS)))
    if flag is not None:
        for name in ("spring", "damper", "eulerdamp") if flag == "passive" else (flag,):
            spec.flags[name] = "disable"
        spec.features.add(f"{flag} disabled")


# ---------------------------------------------------------------------------
# Unsupported features: each injector adds exactly one, away from the base model.


def _inject_flag(flag: str) -> Callable:
    def inject(draw: Callable, spec: _Spec) -> None:
        spec.flags[flag] = "enable"
    return inject


def _inject_option(**values: Any) -> Callable:
    def inject(draw: Callable, spec: _Spec) -> None:
        spec.option.update(values)
    return inject


def _inject_pair(draw: Callable, spec: _Spec) -> None:
    a, b = draw(_sampled(UNSUPPORTED_PAIRS))
    _isolated_pair(spec, _shape(spec, a, "upair_a"), _shape(spec, b, "upair_b"))
    spec.features.add(f"{a}-{b} pair")


def _inject_mesh_margin(draw: Callable, spec: _Spec) -> None:
    mesh = _shape(spec, "mesh", "upair_b")
    mesh["margin"] = _f(draw(_floats(1e-3, 1e-2)))
    _isolated_pair(spec, _shape(spec, "box", "upair_a"), mesh)


def _inject_condim1(draw: Callable, spec: _Spec) -> None:
    spec.option["cone"] = "elliptic"
    _isolated_pair(spec, {**_shape(spec, "box", "upair_a"), "condim": "1"},
                   {**_shape(spec, "sphere", "upair_b"), "condim": "1"})


def _inject_flex(draw: Callable, spec: _Spec) -> None:
    spec.world.append(_tag("flexcomp", {"name": "uflex", "type": "grid", "count": "2 2 1", "spacing": "0.1 0.1 0.1",
                                        "pos": "30 0 1", "dim": "2", "rigid": "true"}))


def _inject_element(section: str, xml: Callable[[_Spec], str]) -> Callable:
    """An injector appending ``xml(spec)`` (which may add the helper body) to ``section``."""
    def inject(draw: Callable, spec: _Spec) -> None:
        getattr(spec, section).append(xml(spec))
    return inject


def _with_helper(fmt: str) -> Callable[[_Spec], str]:
    def xml(spec: _Spec) -> str:
        _helper_body(spec)
        return fmt
    return xml


def _slider_crank(spec: _Spec) -> str:
    _helper_body(spec)
    spec.world.append(_tag("site", {"name": "uslider", "pos": "10 0.3 1"}))
    return '<general cranksite="us" slidersite="uslider" cranklength="0.05"/>'


_INJECTORS: dict[str, Callable[[Callable, _Spec], None]] = {
    "energy flag": _inject_flag("energy"),
    "override flag": _inject_flag("override"),
    "fwdinv flag": _inject_flag("fwdinv"),
    "diagexact flag": _inject_flag("diagexact"),
    "speculative flag": _inject_flag("speculative"),
    "PGS solver": _inject_option(solver="PGS"),
    "implicit integrator": _inject_option(integrator="implicit"),
    "discrete integrator": _inject_option(integrator="discrete"),
    "fluid drag with implicitfast": _inject_option(integrator="implicitfast", density=1.2, viscosity=1.8e-5),
    "unsupported geom pair": _inject_pair,
    "mesh margin": _inject_mesh_margin,
    "condim 1 with elliptic cone": _inject_condim1,
    "flex": _inject_flex,
    "adhesion actuator": _inject_element("actuator", _with_helper('<adhesion body="ub" ctrlrange="0 1"/>')),
    "slider-crank actuator": _inject_element("actuator", _slider_crank),
    "dcmotor actuator": _inject_element("actuator",
                                        _with_helper('<dcmotor joint="uj" motorconst="1" resistance="1"/>')),
    "pid actuator": _inject_element("actuator", _with_helper('<pid joint="uj" kp="1"/>')),
    "geom distance sensor": _inject_element("sensor", _with_helper('<distance geom1="ug" body2="b0"/>')),
    "potential energy sensor": _inject_element("sensor", lambda spec: "<e_potential/>"),
    "kinetic energy sensor": _inject_element("sensor", lambda spec: "<e_kinetic/>"),
    "insidesite sensor": _inject_element("sensor", _with_helper('<insidesite site="us" objtype="body" objname="b0"/>')),
    "joint limit sensor": _inject_element("sensor", _with_helper('<jointlimitpos joint="uj"/>')),
    "contact sensor with body matching": _inject_element("sensor", _with_helper('<contact body1="ub"/>')),
    "contact sensor with site matching": _inject_element("sensor", _with_helper('<contact site="us"/>')),
}
assert set(_INJECTORS) == set(_UNSUPPORTED_BY_NAME)
