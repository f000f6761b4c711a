"""The model being drawn, as data, and its MJCF text: what :mod:`mjxdiff.tools.strategies` builds.

A :class:`_Spec` is a small mutable description (bodies in a tree, geoms, assets, tendons,
actuators, equalities, sensors, options and flags) that the draws of
:mod:`mjxdiff.tools.mjcf_draws` fill and :meth:`_Spec.render` writes once as an MJCF document;
:class:`MjcfModel` is what a strategy returns. Also here: the joint and geom types the
generator knows, the default ``<option>``, the collision masks that keep colliding pairs to
those MJX supports, and the fixed parts (a helper body, an isolated pair of geoms) that an
unsupported feature is added with. Nothing here draws.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable, Mapping
from typing import Any

import mujoco
import numpy as np

from mjxdiff.compare.support import UNSUPPORTED_FEATURES, UnsupportedFeature, pair_supported

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


# ---------------------------------------------------------------------------
# Model builder: a small mutable spec filled by the draws, rendered once.


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


def _mesh_vertices(scale: float, extra: np.ndarray) -> np.ndarray:
    """A regular tetrahedron of half-width ``scale`` plus ``extra`` points in its box (m)."""
    tetra = scale * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    return np.concatenate([tetra, scale * extra.reshape(-1, 3)])


# ---------------------------------------------------------------------------
# Fixed parts that an unsupported feature is added with, away from the base model.


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
