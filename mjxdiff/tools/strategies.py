"""Hypothesis strategies for differential tests of MJX against MuJoCo C.

In the style of :mod:`hypothesis.extra.numpy`: public strategies whose
arguments take either a value or a strategy, composed with ``@st.composite``
for dependent draws (draw a model, then a ``qpos`` of length ``nq``).

Everything shrinks toward the simple case: fewer bodies and geoms, hinge
joints, spheres, no optional elements, :data:`DEFAULT_OPTIONS`, ``qpos0``,
zero velocities and controls, unit parameter factors, shorter horizons.

For one compiled model, :func:`initial_states`, :func:`control_sequences` and
:func:`parameter_perturbations` always give arrays of the same shapes, so a
property over many states of one model compiles its JAX step once.

Example::

    from hypothesis import given, strategies as st
    from mjxdiff.tools.strategies import mjcf_models, initial_states

    @given(st.data())
    def test_energy_is_finite(data):
        m = data.draw(mjcf_models(max_bodies=2)).model()
        state = data.draw(initial_states(m, batch=4))
        ...
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any, NamedTuple

import mujoco
import numpy as np
from hypothesis import strategies as st
from hypothesis.errors import InvalidArgument
from hypothesis.extra import numpy as hnp

# what MJX supports lives in mjxdiff.compare.support; public here too, as before
from mjxdiff.compare.support import (SUPPORTED_PAIRS, UNSUPPORTED_FEATURES, UNSUPPORTED_PAIRS, UnsupportedFeature,  # noqa: F401
                             _TYPE_ORDER, pair_supported, refused_features)
from mjxdiff.input import joints
from mjxdiff.input.inputs import FACTOR_SHAPES, knot_every, knot_levels, sine_levels
from mjxdiff.input.joints import quat_mul, rotvec_quat

__all__ = [
    "CONTROL_FAMILIES",
    "DEFAULT_OPTIONS",
    "GEOM_TYPES",
    "JOINT_TYPES",
    "PERTURBATION_FIELDS",
    "SUPPORTED_PAIRS",
    "UNSUPPORTED_FEATURES",
    "UNSUPPORTED_PAIRS",
    "MjcfModel",
    "State",
    "UnsupportedFeature",
    "control_sequences",
    "initial_states",
    "mjcf_models",
    "pair_supported",
    "parameter_perturbations",
]

JOINT_TYPES = ("hinge", "slide", "ball", "free")
"""Joint types :func:`mjcf_models` can draw, simplest first."""

GEOM_TYPES = ("sphere", "capsule", "box", "ellipsoid", "cylinder", "mesh")
"""Body geom types :func:`mjcf_models` can draw, simplest first (plus a ground plane)."""

def _collision_masks(types: tuple[str, ...]) -> dict[str, int]:
    """contype = conaffinity bit masks under which two geoms collide iff MJX supports their pair.

    Each bit is a clique of mutually supported types (greedy cover of the
    supported pairs); two types share a bit exactly when their pair is supported.

    Args:
      types: geom type names; each must collide with its own type.

    Returns:
      type name -> bit mask.
    """
    cliques: list[set[str]] = []
    for a, b in itertools.combinations_with_replacement(types, 2):
        if not pair_supported(a, b) or any(a in c and b in c for c in cliques):
            continue
        clique = {a, b}
        for t in types:
            if pair_supported(t, t) and all(pair_supported(t, u) for u in clique):
                clique.add(t)
        cliques.append(clique)
    return {t: sum(1 << i for i, c in enumerate(cliques) if t in c) for t in types}


_MASKS = _collision_masks(("plane",) + GEOM_TYPES)
_ISOLATED_BIT = 1 << 30  # contype/conaffinity for injected geoms: they collide only with each other

DEFAULT_OPTIONS: Mapping[str, Any] = {
    "timestep": 0.002,
    "integrator": "Euler",
    "cone": "pyramidal",
    "solver": "Newton",
    "iterations": 100,
    "ls_iterations": 50,
    "tolerance": 1e-10,
}
"""``<option>`` attributes of every model unless drawn otherwise: a converged
Newton solve, so that C and MJX agree to float64 round-off (timestep in s)."""


_UNSUPPORTED_BY_NAME = {f.name: f for f in UNSUPPORTED_FEATURES}


@dataclasses.dataclass(frozen=True)
class MjcfModel:
    """A generated MJCF model.

    Attributes:
      xml: the complete MJCF document; compiles with ``mujoco.MjModel.from_xml_string``.
      nbody: bodies, not counting the world body (``m.nbody - 1``).
      ngeom: geoms, ground plane and injected geoms included (``m.ngeom``).
      features: sorted names of what the model uses, e.g. ``"ball joint"``,
        ``"fixed tendon"``, ``"elliptic cone"``.
      unsupported_feature: the name of the one :data:`UNSUPPORTED_FEATURES`
        entry used on purpose, or None.
    """

    xml: str
    nbody: int
    ngeom: int
    features: tuple[str, ...]
    unsupported_feature: str | None = None

    def model(self) -> mujoco.MjModel:
        """Compiles :attr:`xml` (a fresh ``mujoco.MjModel`` on each call)."""
        return mujoco.MjModel.from_xml_string(self.xml)

    @property
    def unsupported(self) -> UnsupportedFeature | None:
        """The :class:`UnsupportedFeature` record of :attr:`unsupported_feature`, or None."""
        return _UNSUPPORTED_BY_NAME.get(self.unsupported_feature) if self.unsupported_feature else None


class State(NamedTuple):
    """An initial state: ``(nq,)``, ``(nv,)``, ``(na,)`` arrays, or with a leading batch axis.

    Attributes:
      qpos: joint positions (m, rad, unit quaternions).
      qvel: joint velocities (m/s, rad/s).
      act: actuator activations.
    """

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray


# ---------------------------------------------------------------------------
# Model builder: a small mutable spec filled by the draws, rendered once.


def _value(draw: Callable, x: Any) -> Any:
    """``x`` itself, or a value drawn from it when it is a strategy."""
    return draw(x) if isinstance(x, st.SearchStrategy) else x


def _f(x: float) -> str:
    return format(float(x), ".10g")


def _vec(xs: Iterable[float]) -> str:
    return " ".join(_f(x) for x in xs)


def _tag(name: str, attrs: Mapping[str, Any], children: str = "") -> str:
    a = "".join(f' {k}="{v}"' for k, v in attrs.items() if v is not None)
    return f"<{name}{a}>{children}</{name}>" if children else f"<{name}{a}/>"


@dataclasses.dataclass
class _Body:
    name: str
    parent: int  # index into _Spec.bodies; -1 is the world
    pos: tuple[float, ...]
    joint: dict[str, str] | None
    geoms: list[dict[str, str]] = dataclasses.field(default_factory=list)
    sites: list[dict[str, str]] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class _Spec:
    option: dict[str, Any]
    flags: dict[str, str] = dataclasses.field(default_factory=dict)
    assets: list[str] = dataclasses.field(default_factory=list)
    world: list[str] = dataclasses.field(default_factory=list)
    world_geoms: list[dict[str, str]] = dataclasses.field(default_factory=list)
    bodies: list[_Body] = dataclasses.field(default_factory=list)
    tendon: list[str] = dataclasses.field(default_factory=list)
    equality: list[str] = dataclasses.field(default_factory=list)
    actuator: list[str] = dataclasses.field(default_factory=list)
    sensor: list[str] = dataclasses.field(default_factory=list)
    fixed_tendons: list[str] = dataclasses.field(default_factory=list)
    mocap_bodies: int = 0
    features: set[str] = dataclasses.field(default_factory=set)
    unsupported: str | None = None

    def site(self, b: int) -> str:
        """Name of body ``b``'s site, added on first use (0.05 m sphere, for touch)."""
        body = self.bodies[b]
        if not body.sites:
            body.sites.append({"name": f"s{b}", "size": "0.05"})
        return body.sites[0]["name"]

    def world_site(self) -> str:
        """A site on the world body, turned (a fixed, non-identity reference frame)."""
        if not any('name="wsite"' in w for w in self.world):
            self.world.append(_tag("site", {"name": "wsite", "pos": "0 -1 1", "euler": "0.3 0.2 0.1"}))
        return "wsite"

    def scalar_joints(self) -> tuple[str, ...]:
        return tuple(b.joint["name"] for b in self.bodies
                     if b.joint is not None and b.joint.get("type") in ("hinge", "slide"))

    def joints_of(self, *types: str) -> tuple[str, ...]:
        return tuple(b.joint["name"] for b in self.bodies if b.joint is not None and b.joint.get("type") in types)

    def world_pos(self, b: int) -> np.ndarray:
        """Body ``b``'s origin in the world at qpos0 (bodies are not rotated)."""
        pos = np.zeros(3)
        while b >= 0:
            pos += self.bodies[b].pos
            b = self.bodies[b].parent
        return pos

    def world_geom(self, attrs: dict[str, str]) -> None:
        self.world.append(_tag("geom", attrs))
        self.world_geoms.append(attrs)

    def contact_possible(self) -> bool:
        """Whether any geom pair passes MuJoCo's filters (bodies, parent-child, contype/conaffinity)."""
        geoms = [(-1, g) for g in self.world_geoms] + [(i, g) for i, b in enumerate(self.bodies) for g in b.geoms]
        for (b1, g1), (b2, g2) in itertools.combinations(geoms, 2):
            if b1 == b2 or (b1 >= 0 and b2 >= 0 and b1 in (b2, self.bodies[b2].parent)
                            or b1 >= 0 and b2 >= 0 and b2 == self.bodies[b1].parent):
                continue  # same body, or parent and child (filterparent)
            t1, c1, a1 = int(g1.get("contype", 1)), int(g1.get("conaffinity", 1)), g1["type"]
            t2, c2, a2 = int(g2.get("contype", 1)), int(g2.get("conaffinity", 1)), g2["type"]
            if (t1 & c2 or t2 & c1) and not {a1, a2} <= {"plane", "hfield"}:
                return True
        return False

    def render(self) -> str:
        children: dict[int, list[int]] = {}
        for i, b in enumerate(self.bodies):
            children.setdefault(b.parent, []).append(i)

        def body_xml(i: int, depth: int) -> str:
            b, pad = self.bodies[i], "  " * depth
            inner = [_tag("joint", b.joint)] if b.joint else []
            inner += [_tag("geom", g) for g in b.geoms] + [_tag("site", s) for s in b.sites]
            lines = [f"{pad}  {x}" for x in inner]
            lines += [body_xml(c, depth + 1) for c in children.get(i, [])]
            head = f'{pad}<body name="{b.name}" pos="{_vec(b.pos)}">'
            return "\n".join([head, *lines, f"{pad}</body>"])

        option_attrs = {k: (_f(v) if isinstance(v, float) else v) for k, v in self.option.items()}
        flags = f"\n    {_tag('flag', self.flags)}\n  " if self.flags else ""
        parts = ["<mujoco>", '  <compiler angle="radian"/>', "  " + _tag("option", option_attrs, flags)]
        if self.assets:
            parts += ["  <asset>", *(f"    {a}" for a in self.assets), "  </asset>"]
        parts.append("  <worldbody>")
        parts += [f"    {w}" for w in self.world]
        parts += [body_xml(i, 2) for i in children.get(-1, [])]
        parts.append("  </worldbody>")
        for section in ("tendon", "equality", "actuator", "sensor"):
            items = getattr(self, section)
            if items:
                parts += [f"  <{section}>", *(f"    {x}" for x in items), f"  </{section}>"]
        parts.append("</mujoco>")
        return "\n".join(parts) + "\n"


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


def _mesh_vertices(scale: float, extra: np.ndarray) -> np.ndarray:
    """A regular tetrahedron of half-width ``scale`` plus ``extra`` points in its box (m)."""
    tetra = scale * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    return np.concatenate([tetra, scale * extra.reshape(-1, 3)])


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


# ---------------------------------------------------------------------------
# Unsupported features: each injector adds exactly one, away from the base model.


def _helper_body(spec: _Spec) -> int:
    """Index of a body ``ub`` 10 m away: a limited hinge ``uj``, a non-colliding geom ``ug``, a site ``us``."""
    for i, b in enumerate(spec.bodies):
        if b.name == "ub":
            return i
    spec.bodies.append(_Body(
        name="ub", parent=-1, pos=(10.0, 0.0, 1.0),
        joint={"name": "uj", "type": "hinge", "axis": "0 0 1", "limited": "true", "range": "-1 1"},
        geoms=[{"name": "ug", "type": "sphere", "size": "0.05", "contype": "0", "conaffinity": "0"}],
        sites=[{"name": "us", "size": "0.05"}]))
    return len(spec.bodies) - 1


def _isolated_pair(spec: _Spec, static: dict[str, str], moving: dict[str, str]) -> None:
    """A static world geom and a free body 0.3 m above it, colliding only with each other."""
    bit = str(_ISOLATED_BIT)
    spec.world_geom({**static, "pos": "20 0 0.2", "contype": bit, "conaffinity": bit})
    spec.bodies.append(_Body(name="upair", parent=-1, pos=(20.0, 0.0, 0.5),
                             joint={"name": "upair_free", "type": "free"},
                             geoms=[{**moving, "contype": bit, "conaffinity": bit}]))


_SHAPES = {"sphere": "0.1", "ellipsoid": "0.1 0.08 0.06", "cylinder": "0.05 0.1", "box": "0.1 0.1 0.1"}


def _shape(spec: _Spec, gtype: str, name: str) -> dict[str, str]:
    """Attributes of a fixed-size geom of ``gtype`` (adds mesh/hfield assets as needed)."""
    if gtype == "mesh":
        spec.assets.append(_tag("mesh", {"name": f"mesh_{name}",
                                         "vertex": _vec(_mesh_vertices(0.1, np.zeros((0, 3))).ravel())}))
        return {"name": name, "type": "mesh", "mesh": f"mesh_{name}"}
    if gtype == "hfield":
        spec.assets.append(_tag("hfield", {"name": f"hf_{name}", "nrow": "3", "ncol": "3",
                                           "size": "0.5 0.5 0.1 0.1", "elevation": " ".join(["0"] * 9)}))
        return {"name": name, "type": "hfield", "hfield": f"hf_{name}"}
    return {"name": name, "type": gtype, "size": _SHAPES[gtype]}


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


def _unsupported_names(unsupported: Any) -> tuple[str, ...]:
    refused = tuple(f.name for f in refused_features())  # the installed MJX's, which its MuJoCo can express
    if unsupported is True:
        return refused
    names = (unsupported,) if isinstance(unsupported, str) else tuple(unsupported)
    unknown = [n for n in names if n not in _UNSUPPORTED_BY_NAME]
    if unknown or not names:
        raise InvalidArgument(f"unsupported={unsupported!r}: expected a bool or names from UNSUPPORTED_FEATURES")
    if set(names) - set(refused):
        raise InvalidArgument(f"unsupported={unsupported!r}: the installed MuJoCo/MJX "
                              f"cannot express or does not refuse {sorted(set(names) - set(refused))} "
                              "(support.refused_features)")
    return names


def _check_subset(name: str, values: Iterable[str], allowed: tuple[str, ...]) -> tuple[str, ...]:
    values = tuple(values)
    if not values or set(values) - set(allowed):
        raise InvalidArgument(f"{name}={values!r}: expected a non-empty subset of {allowed}")
    return tuple(v for v in allowed if v in values)  # simplest first, whatever the caller's order


@st.composite
def mjcf_models(draw: Callable, *, max_bodies: Any = 4, max_geoms_per_body: Any = 2,
                joint_types: Any = JOINT_TYPES, geom_types: Any = None, actuators: Any = True,
                tendons: Any = True, equality: Any = True, sensors: Any = True, contacts: Any = True,
                mjx_only: Any = True, unsupported: Any = False, options: Any = True, flags: Any = True) -> MjcfModel:
    """Random MJCF models: a kinematic tree of bodies with joints, geoms, and optional extras.

    Each body has one joint (free only on children of the world; hinge and
    slide ranges, when drawn, contain 0) and 1 to ``max_geoms_per_body``
    geoms (sizes 0.02-0.3 m). A ground plane, contact parameters, actuators,
    tendons, equality constraints, sensors and non-default options are each
    drawn when allowed; all shrink away. The minimal model is one body with
    a hinge and a sphere, and :data:`DEFAULT_OPTIONS`. Angles in the XML are
    radians. Every argument accepts a value or a strategy.

    With ``mjx_only``, a model in which no geom pair can collide gets the
    pyramidal cone and no touch sensor, whatever was drawn: MJX 3.17 fails
    to trace ``mjx.step`` (a TypeError or ValueError, not NotImplementedError)
    for an elliptic cone or a touch sensor when there are constraints but no
    possible contacts; without contacts the cone changes nothing in C.

    Args:
      max_bodies: at most this many bodies (at least 1), world excluded.
      max_geoms_per_body: at most this many geoms per body (at least 1).
      joint_types: joint types to draw from, a subset of :data:`JOINT_TYPES`.
      geom_types: geom types to draw from, a subset of :data:`GEOM_TYPES`
        (None: all of them).
      actuators: whether actuators may be drawn (on hinge/slide joints and fixed tendons).
      tendons: whether fixed and spatial tendons may be drawn.
      equality: whether connect, weld and joint equality constraints may be drawn.
      sensors: whether sensors may be drawn.
      contacts: whether geoms collide; False sets every contype/conaffinity to 0.
      mjx_only: use only what MJX supports: colliding geom pairs limited to
        :data:`SUPPORTED_PAIRS` through contype/conaffinity masks, no margin
        when there are meshes, no condim 1 under an elliptic cone, no PGS
        solver or implicit integrator. False also draws those.
      unsupported: False; True to add one feature drawn from those of
        :data:`UNSUPPORTED_FEATURES` the installed MJX refuses
        (:func:`~mjxdiff.compare.support.refused_features`) to an otherwise MJX-only model;
        or a name (or names) from them to add that one. Requires ``mjx_only=True``.
      options: True to draw ``<option>`` values, False for
        :data:`DEFAULT_OPTIONS`, or a mapping of ``<option>`` attributes
        overriding them (not checked against ``mjx_only``).
      flags: whether a disable flag may be drawn (one of :data:`DISABLE_FLAGS`, shrinking to
        none; springs and dampers only together: MJX 3.17 drops both when either is off).

    Returns:
      A strategy of :class:`MjcfModel`.
    """
    max_bodies = _value(draw, max_bodies)
    max_geoms = _value(draw, max_geoms_per_body)
    if max_bodies < 1 or max_geoms < 1:
        raise InvalidArgument(f"max_bodies={max_bodies}, max_geoms_per_body={max_geoms}: both must be >= 1")
    joint_types = _check_subset("joint_types", _value(draw, joint_types), JOINT_TYPES)
    geom_types = _check_subset("geom_types", _value(draw, geom_types) or GEOM_TYPES, GEOM_TYPES)
    mjx_only, unsupported = _value(draw, mjx_only), _value(draw, unsupported)
    if unsupported is not False and unsupported is not None and not mjx_only:
        raise InvalidArgument("unsupported requires mjx_only=True: the model must use exactly one unsupported feature")

    spec = _Spec(option=_options(draw, options, bool(mjx_only)))
    spec.features |= _option_features(spec.option)
    _tree(draw, spec, max_bodies, joint_types)
    _geoms(draw, spec, max_geoms, geom_types, bool(_value(draw, contacts)), bool(mjx_only))
    touch = True
    if mjx_only and not spec.contact_possible():  # see the docstring: MJX 3.17 trace failures
        spec.option["cone"] = "pyramidal"
        spec.features.discard("elliptic cone")
        touch = False
    if _value(draw, tendons) and draw(st.booleans()):
        _tendons(draw, spec, geom_types)
    if _value(draw, actuators) and draw(st.booleans()):
        _actuators(draw, spec)
    if _value(draw, equality) and draw(st.booleans()):
        _equalities(draw, spec)
    if _value(draw, sensors) and draw(st.booleans()):
        _sensors(draw, spec, touch)
    if _value(draw, flags):
        _disable_flags(draw, spec)
    if unsupported:
        name = draw(_sampled(_unsupported_names(unsupported)))
        _INJECTORS[name](draw, spec)
        spec.unsupported = name
        spec.features.add(name)
    ngeom = len(spec.world_geoms) + sum(len(b.geoms) for b in spec.bodies)
    return MjcfModel(xml=spec.render(), nbody=len(spec.bodies) + spec.mocap_bodies, ngeom=ngeom,
                     features=tuple(sorted(spec.features)), unsupported_feature=spec.unsupported)


# ---------------------------------------------------------------------------
# States, controls, parameter factors for one compiled model (fixed shapes).


def _unit_floats() -> st.SearchStrategy:
    return _floats(-1.0, 1.0)


@functools.cache
def _unit_array(shape: tuple[int, ...]) -> st.SearchStrategy:
    """float64 arrays of ``shape`` with elements in [-1, 1], shrinking to zeros."""
    return hnp.arrays(np.float64, shape, elements=_unit_floats())


def _perturbed_qpos(m: mujoco.MjModel, noise: np.ndarray, scale: float, within_limits: bool) -> np.ndarray:
    """``qpos0`` moved by ``scale * noise``: ``(B, nv)`` noise in [-1, 1] to ``(B, nq)`` qpos.

    Scalars and free-joint positions move by the noise (m or rad); quaternions
    are rotated by the noise as a rotation vector (rad) and renormalised.
    """
    qpos = np.tile(m.qpos0, (noise.shape[0], 1))
    limited = m.jnt_limited.astype(bool)
    for p in joints.parts(m):
        j, q, v = p.joint, p.qpos_adr, p.dof_adr
        if p.kind == "translation":
            qpos[:, p.qpos] += scale * noise[:, p.dof]
        elif p.kind == "rotation":
            rotvec = scale * noise[:, p.dof]
            if within_limits and limited[j] and m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                # ball limit: rotation angle (from qpos0, usually identity) below range[1]
                top = (1 - 1e-3) * m.jnt_range[j, 1]
                angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
                rotvec = rotvec * np.minimum(1.0, top / np.maximum(angle, 1e-300))
            quat = quat_mul(qpos[:, p.qpos], rotvec_quat(rotvec))
            qpos[:, p.qpos] = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
        else:
            qpos[:, q] += scale * noise[:, v]
            if within_limits and limited[j]:
                lo, hi = m.jnt_range[j]
                margin = 1e-3 * (hi - lo)  # strictly inside: a start on the limit is a grazing contact
                qpos[:, q] = np.clip(qpos[:, q], lo + margin, hi - margin)
    return qpos


def _check_batch(batch: Any) -> int:
    if batch is not None and (isinstance(batch, st.SearchStrategy) or int(batch) < 1):
        raise InvalidArgument(f"batch={batch!r}: expected None or a positive int (shapes stay fixed)")
    return 1 if batch is None else int(batch)


@st.composite
def initial_states(draw: Callable, m: mujoco.MjModel, *, batch: int | None = None,
                   qpos_scale: Any = _floats(0, 0.5), qvel_scale: Any = _floats(0, 1.0),
                   act_scale: Any = _floats(0, 1.0), within_limits: bool = True) -> State:
    """Initial states near ``qpos0``, shrinking to ``qpos0`` and zero velocities and activations.

    Args:
      m: a compiled model.
      batch: None for ``(nq,)``, ``(nv,)``, ``(na,)`` arrays; an int B for ``(B, ...)``.
      qpos_scale: largest displacement from ``qpos0`` per coordinate (m or
        rad; rotation-vector components for quaternions). Value or strategy.
      qvel_scale: largest joint velocity (m/s or rad/s). Value or strategy.
      act_scale: largest activation magnitude (clipped to ``actrange`` where limited).
      within_limits: keep limited hinge/slide joints strictly inside their
        range and limited ball joints below their angle.

    Returns:
      A strategy of :class:`State`; quaternions have unit norm.
    """
    nbatch = _check_batch(batch)
    qpos_scale, qvel_scale, act_scale = (float(_value(draw, s)) for s in (qpos_scale, qvel_scale, act_scale))
    qpos = _perturbed_qpos(m, draw(_unit_array((nbatch, m.nv))), qpos_scale, within_limits)
    qvel = qvel_scale * draw(_unit_array((nbatch, m.nv)))
    act = act_scale * draw(_unit_array((nbatch, m.na)))
    if m.na:
        adr = m.actuator_actadr
        for i in np.flatnonzero((adr >= 0) & m.actuator_actlimited.astype(bool)):
            a = slice(adr[i], adr[i] + m.actuator_actnum[i])
            act[:, a] = np.clip(act[:, a], *m.actuator_actrange[i])
    state = State(qpos=qpos, qvel=qvel + 0.0, act=act + 0.0)  # + 0.0 turns -0.0 into 0.0
    return state if batch is not None else State(*(x[0] for x in state))


CONTROL_FAMILIES = ("zero", "constant", "step", "smooth", "sinusoid", "noise")
"""Control families of :func:`control_sequences`, simplest first."""

def _ctrl_bounds(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """(nu,) lower and upper control bounds; [-1, 1] where unlimited."""
    limited = m.actuator_ctrllimited.astype(bool)
    return (np.where(limited, m.actuator_ctrlrange[:, 0], -1.0),
            np.where(limited, m.actuator_ctrlrange[:, 1], 1.0))


def _levels_to_ctrl(level: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Levels in [-1, 1] to controls in [lo, hi]: 0 is the control closest to 0, +-1 the bounds."""
    z = np.clip(0.0, lo, hi)
    ctrl = np.where(level >= 0, z + level * (hi - z), z + level * (z - lo))
    return np.clip(ctrl, lo, hi)


@st.composite
def control_sequences(draw: Callable, m: mujoco.MjModel, steps: Any, *, batch: int | None = None,
                      family: Any = None) -> np.ndarray:
    """Control sequences within ``ctrlrange``, shrinking to zeros (the in-range value nearest 0).

    Families (one per draw, parameters per batch member), with levels in [-1, 1]
    mapped onto ``ctrlrange`` ([-1, 1] where unlimited): ``zero``; ``constant``;
    ``step`` (a new level every ~0.1 s of simulated time); ``smooth`` (those
    knots interpolated linearly); ``sinusoid`` (amplitude in [-1, 1], 0.5-2 Hz,
    any phase); ``noise`` (a new level every step).

    Args:
      m: a compiled model; its timestep sets the knot spacing.
      steps: number of steps T, an int or a strategy (shorter shrinks first).
      batch: None for ``(T, nu)``; an int B for ``(B, T, nu)``.
      family: None for any of :data:`CONTROL_FAMILIES`, a name, or a strategy of names.

    Returns:
      A strategy of float64 arrays.
    """
    nbatch = _check_batch(batch)
    steps = int(_value(draw, steps))
    if steps < 1:
        raise InvalidArgument(f"steps={steps}: expected >= 1")
    family = draw(st.sampled_from(CONTROL_FAMILIES)) if family is None else _value(draw, family)
    if family not in CONTROL_FAMILIES:
        raise InvalidArgument(f"family={family!r}: expected one of {CONTROL_FAMILIES}")
    nu = m.nu
    t = np.arange(steps) * m.opt.timestep
    every = knot_every(m.opt.timestep)
    if family == "zero" or nu == 0:
        level = np.zeros((nbatch, steps, nu))
    elif family == "constant":
        level = np.broadcast_to(draw(_unit_array((nbatch, 1, nu))), (nbatch, steps, nu))
    elif family in ("step", "smooth"):
        level = knot_levels(draw(_unit_array((nbatch, steps // every + 2, nu))), steps, every, family)
    elif family == "sinusoid":
        amp = draw(_unit_array((nbatch, 1, nu)))
        freq = draw(hnp.arrays(np.float64, (nbatch, 1, nu), elements=_floats(0.5, 2.0)))  # Hz
        phase = draw(hnp.arrays(np.float64, (nbatch, 1, nu), elements=_floats(0.0, 2 * np.pi)))
        level = amp * sine_levels(freq, phase, t)
    else:
        level = draw(_unit_array((nbatch, steps, nu)))
    lo, hi = _ctrl_bounds(m)
    ctrl = _levels_to_ctrl(level, lo, hi) + 0.0
    return ctrl if batch is not None else ctrl[0]


PERTURBATION_FIELDS = FACTOR_SHAPES
"""Parameter name -> factor shape for a model, as :mod:`mjxdiff.input.inputs` scales them."""


@st.composite
def parameter_perturbations(draw: Callable, m: mujoco.MjModel, *, max_relative: Any = 0.2,
                            batch: int | None = None, fields: Iterable[str] | None = None
                            ) -> dict[str, np.ndarray]:
    """Multiplicative parameter factors in ``[1 - max_relative, 1 + max_relative]``, shrinking to ones.

    Args:
      m: a compiled model (sets the shapes).
      max_relative: largest relative change, in [0, 1); a value or a strategy.
      batch: None for the shapes of :data:`PERTURBATION_FIELDS`; an int B
        prepends a batch axis (the layout of ``BatchedInputs.factors``).
      fields: which of :data:`PERTURBATION_FIELDS` to draw (None: all).

    Returns:
      A strategy of dicts name -> float64 array (0-d for ``gravity`` and ``timestep``).
    """
    nbatch = _check_batch(batch)
    max_relative = float(_value(draw, max_relative))
    if not 0 <= max_relative < 1:
        raise InvalidArgument(f"max_relative={max_relative}: expected 0 <= max_relative < 1")
    names = tuple(PERTURBATION_FIELDS) if fields is None else tuple(fields)
    unknown = set(names) - set(PERTURBATION_FIELDS)
    if unknown:
        raise InvalidArgument(f"fields: unknown {sorted(unknown)}; expected names from {tuple(PERTURBATION_FIELDS)}")
    out = {}
    for name in names:
        shape = PERTURBATION_FIELDS[name](m)
        u = draw(_unit_array((nbatch, *shape)))
        factor = 1.0 + max_relative * u
        out[name] = factor if batch is not None else factor[0]
    return out
