"""What MJX supports, refuses and gets wrong, in one place: the geom pairs it collides, the
features it refuses (and where), the flags mjxdiff may set aside for it, the features the
fuzzer leaves out and the catalogue of known MJX-vs-C divergences with their evidence.
:mod:`mjxdiff.tools.strategies` (generation), :mod:`mjxdiff.input.adjust` (what is changed so MJX can run a
model), :mod:`mjxdiff.tools.fuzz` (what is left out or set aside) and :mod:`mjxdiff.compare.known` (matching
failures to the catalogue) read it. Measured on mujoco 4.0.0 and mujoco-mjx 3.17.0.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any, NamedTuple

import mujoco

__all__ = ["CATALOGUE", "HARMLESS_ENABLE_FLAGS", "KNOWN_DIVERGENCES", "SUPPORTED_PAIRS", "UNSUPPORTED_FEATURES",
           "UNSUPPORTED_PAIRS", "Entry", "UnsupportedFeature", "model_features", "pair_supported",
           "refused_features"]


# -- geom pairs -----------------------------------------------------------------------------------

# Measured once with mujoco 4.0.0 and mujoco-mjx 3.17.0 (JAX backend): for every
# unordered pair of geom types, a model with a static geom of one type in the world
# (or a free body, for non-static types) and a free body with a geom of the other
# was compiled, then mjx.put_model, mjx.make_data and jax.eval_shape(mjx.step, ...)
# were called. Listed pairs passed; every other pair of colliding types raised
# NotImplementedError("(mjGEOM_A, mjGEOM_B) collisions not implemented.") in
# put_model. Pairs are ordered as MuJoCo orders geom types (plane < hfield < sphere
# < capsule < ellipsoid < cylinder < box < mesh); plane and hfield are static and
# never collide with each other. tests/test_strategies.py re-measures this table
# with put_model against the installed versions.
SUPPORTED_PAIRS = frozenset({
    ("plane", "sphere"), ("plane", "capsule"), ("plane", "ellipsoid"),
    ("plane", "cylinder"), ("plane", "box"), ("plane", "mesh"),
    ("hfield", "sphere"), ("hfield", "capsule"), ("hfield", "box"), ("hfield", "mesh"),
    ("sphere", "sphere"), ("sphere", "capsule"), ("sphere", "ellipsoid"),
    ("sphere", "cylinder"), ("sphere", "box"), ("sphere", "mesh"),
    ("capsule", "capsule"), ("capsule", "ellipsoid"), ("capsule", "cylinder"),
    ("capsule", "box"), ("capsule", "mesh"),
    ("ellipsoid", "ellipsoid"), ("ellipsoid", "cylinder"),
    ("cylinder", "cylinder"),
    ("box", "box"), ("box", "mesh"),
    ("mesh", "mesh"),
})
"""Geom type pairs MJX 3.17 collides, in MuJoCo's type order (measured, see the comment above)."""

UNSUPPORTED_PAIRS = (
    ("hfield", "ellipsoid"), ("hfield", "cylinder"),
    ("ellipsoid", "box"), ("ellipsoid", "mesh"),
    ("cylinder", "box"), ("cylinder", "mesh"),
)
"""Colliding geom type pairs for which ``mjx.put_model`` raises NotImplementedError."""

_TYPE_ORDER = ("plane", "hfield", "sphere", "capsule", "ellipsoid", "cylinder", "box", "mesh")


def pair_supported(a: str, b: str) -> bool:
    """Whether MJX can collide geoms of types ``a`` and ``b`` (MJCF names, any order).

    Args:
      a, b: geom type names, e.g. ``"box"``, ``"mesh"``.

    Returns:
      True when the pair is in :data:`SUPPORTED_PAIRS`.
    """
    a, b = sorted((a, b), key=_TYPE_ORDER.index)
    return (a, b) in SUPPORTED_PAIRS



# -- refused features -----------------------------------------------------------------------------

class UnsupportedFeature(NamedTuple):
    """An MJCF feature MJX rejects, measured on mujoco 4.0.0 and mujoco-mjx 3.17.0, and on every
    MuJoCo/MJX release from 3.3.0 (see :func:`refused_features`).

    Attributes:
      name: the feature, as recorded in :attr:`MjcfModel.unsupported_feature`.
      stage: where MJX 3.17 raises NotImplementedError: ``"put_model"``,
        ``"make_data"`` or ``"step"`` (when tracing ``mjx.step``).
      message: a substring of MJX 3.17's NotImplementedError message.
      since: the first MuJoCo release whose MJCF has the feature (before it, C refuses the model:
        a schema violation, which a sweep reports as unsupported, see
        :func:`mjxdiff.compat.later_feature`).
      refused_since: the first MJX release that refuses it; earlier releases accept the model
        and ignore the feature (a known divergence where that changes the physics).
    """

    name: str
    stage: str
    message: str
    since: str = "3.3.0"
    refused_since: str = "3.3.0"


UNSUPPORTED_FEATURES: tuple[UnsupportedFeature, ...] = (
    UnsupportedFeature("energy flag", "put_model", "mjENBL_ENERGY"),
    UnsupportedFeature("override flag", "put_model", "mjENBL_OVERRIDE"),
    UnsupportedFeature("fwdinv flag", "put_model", "mjENBL_FWDINV"),
    UnsupportedFeature("diagexact flag", "put_model", "mjENBL_DIAGEXACT", since="3.9.0", refused_since="3.9.0"),
    UnsupportedFeature("speculative flag", "put_model", "mjENBL_SPECULATIVE", since="4.0.0", refused_since="3.17.0"),
    UnsupportedFeature("PGS solver", "put_model", "mjSOL_PGS"),
    UnsupportedFeature("implicit integrator", "put_model", "mjINT_IMPLICIT"),
    UnsupportedFeature("discrete integrator", "step", "integrator", since="3.13.0", refused_since="3.13.0"),
    UnsupportedFeature("fluid drag with implicitfast", "put_model", "fluid drag"),
    UnsupportedFeature("unsupported geom pair", "put_model", "collisions not implemented"),
    UnsupportedFeature("mesh margin", "put_model", "margin/gap not implemented"),
    UnsupportedFeature("condim 1 with elliptic cone", "make_data", "condim=1"),
    UnsupportedFeature("flex", "put_model", "Flex not implemented", refused_since="3.3.5"),
    UnsupportedFeature("adhesion actuator", "put_model", "mjTRN_BODY"),
    UnsupportedFeature("slider-crank actuator", "put_model", "mjTRN_SLIDERCRANK"),
    UnsupportedFeature("dcmotor actuator", "put_model", "DCMOTOR", since="3.7.0", refused_since="3.7.0"),
    UnsupportedFeature("pid actuator", "put_model", "PID", since="3.12.0", refused_since="3.12.0"),
    UnsupportedFeature("geom distance sensor", "put_model", "mjSENS_GEOMDIST"),
    UnsupportedFeature("potential energy sensor", "put_model", "mjSENS_E_POTENTIAL"),
    UnsupportedFeature("kinetic energy sensor", "put_model", "mjSENS_E_KINETIC"),
    UnsupportedFeature("insidesite sensor", "put_model", "mjSENS_INSIDESITE", since="3.3.5",
                        refused_since="3.3.5"),
    UnsupportedFeature("joint limit sensor", "put_model", "mjSENS_JOINTLIMITPOS"),
    UnsupportedFeature("contact sensor with body matching", "put_model", "body matching", since="3.3.5",
                        refused_since="3.3.5"),
    UnsupportedFeature("contact sensor with site matching", "put_model", "site matching", since="3.3.5",
                        refused_since="3.3.5"),
)
"""Features ``mjcf_models(unsupported=True)`` injects, one per model. Each was
measured as :data:`SUPPORTED_PAIRS` was: the model compiles and steps in C, and
MJX raises NotImplementedError at ``stage`` with ``message`` in its text.
(Found but left out: a rangefinder sensor in a model without any ``<material>``
fails to trace in MJX with a TypeError, not NotImplementedError, so generated
models with a rangefinder carry a dummy material.)

``since`` and ``refused_since`` were measured on all 23 releases from 3.3.0 to 4.0.0 (MuJoCo
with its MJX; 2026-11-26): each feature's minimal generated model compiled in C or not, then
``put_model``, ``make_data`` and a traced ``mjx.step``. What changed: MJX 3.3.0-3.3.4 accept a
flex and make no flex contacts (catalogue entry ``flex-ignored-3.3``); the insidesite and
contact sensors arrive in 3.3.5, dcmotor in 3.7.0, diagexact in 3.9.0, pid in 3.12.0, the
discrete integrator in 3.13.0 (where MJX 3.13 refuses it in put_model, "mjINT_DISCRETE"),
speculative in 4.0.0. Every other feature is refused by every release in the range."""


def refused_features(mjx_version: str | None = None) -> tuple[UnsupportedFeature, ...]:
    """The :data:`UNSUPPORTED_FEATURES` an MJX release refuses and its MuJoCo can express.

    Args:
      mjx_version: an MJX release, e.g. ``"3.9.0"`` (default: the installed one). Its MuJoCo
        is the same release, except MJX 3.17 with MuJoCo 4.0.

    Returns:
      The features with ``refused_since`` <= the release and ``since`` <= its MuJoCo, in table order.
    """
    from mjxdiff.compat import _release, installed, matching_mujoco

    release = _release(mjx_version or installed()["mujoco-mjx"])
    return tuple(f for f in UNSUPPORTED_FEATURES
                 if _release(f.refused_since) <= release and _release(f.since) <= matching_mujoco(release))


# -- set aside for MJX (mjxdiff.input.adjust) -----------------------------------------------------------

#: Enable flags MJX refuses and C's compared quantities do not depend on, with the label reported.
HARMLESS_ENABLE_FLAGS: dict[int, str] = {
    int(mujoco.mjtEnableBit.mjENBL_ENERGY): "energy flag",
    int(mujoco.mjtEnableBit.mjENBL_FWDINV): "fwdinv flag",
}


# -- left out of generated models (mjxdiff.tools.fuzz) ---------------------------------------------------

#: Features left out by default because C 4.0.0 and MJX 3.17.0 are known to differ on them.
KNOWN_DIVERGENCES = {
    "connect/weld equality": "efc_aref of equality rows differs (scenarios/equality.toml notes)",
    "RK4, implicitfast": "free/ball rotation and RK4 sensordata differ (scenarios/integrator_*.toml notes)",
    "box and mesh geoms": "box-box contact points differ (scenarios/box_stack.toml notes)",
    "acceleration sensors without constraints": "MJX's forward skips sensor_acc when the model has no "
                                                "constraint rows: accelerometer, force, torque, framelinacc "
                                                "and frameangacc read 0 (tests/test_known_divergences.py)",
    "contact tangent frames": "MJX's plane-capsule contact has the fixed tangent frame (0, 1, 0, ...) where "
                              "C's first tangent follows the capsule's axis; with a pyramidal cone or anisotropic "
                              "friction the friction pyramid turns and the contact forces differ "
                              "(tests/test_known_divergences.py)",
    "tendon wrap sidesite": "C 4.0 picks a wrap's side by the winding of the path end0 -> sidesite -> end1 "
                            "around the wrap geom (as MuJoCo Warp 4.0 does); MJX 3.17 by the older rule, the arc "
                            "whose middle is nearest the sidesite's direction: near the sidesite's symmetry plane "
                            "they wrap opposite sides (catalogue tendon-wrap-sidesite and its bundle)",
    "spring or damper flag alone": "MJX 3.17's passive() drops all passive forces (and gravcomp) when either "
                                   "flag is disabled, C 4.0 only the one disabled; with the damper disabled "
                                   "MJX's Euler step still damps implicitly (tests/test_known_divergences.py)",
    "actearly": "MJX 3.17 ignores actearly: its force uses the current activation, C's the next one "
                "(tests/test_known_divergences.py)",
    "tendon armature across trees": "a tendon with armature coupling two kinematic trees: C 4.0's mass matrix "
                                    "keeps the trees' sparsity, MJX 3.17's differs (catalogue "
                                    "tendon-armature-trees and its bundle)",
    "damped tendons across trees under implicitfast": "C 4.0 keeps qDeriv within the mass matrix's sparsity, "
                                                      "MJX 3.17 adds the cross-tree terms "
                                                      "(tests/test_known_divergences.py)",
    "plane-cylinder far cap": "C adds a contact on a cylinder's far cap when it is within the margin (a cylinder "
                              "lying on its side, or sunk); MJX's plane_cylinder returns the near cap's three "
                              "only (tests/test_known_divergences.py)",
    "convex pairs by SDF descent": "MJX 3.17 collides a sphere, capsule, ellipsoid or cylinder with an ellipsoid or "
                                   "cylinder by 10 steps of gradient descent on an SDF clearance (collision_sdf.py), "
                                   "C 4.0 analytically or by GJK/EPA: depth, point, normal and contact count differ "
                                   "(an ellipsoid-cylinder contact 2.882 mm deep in C, 1.354 mm in MJX, normals "
                                   "0.037 rad apart, qacc 99 apart; tests/data/fuzz_ellipsoid_cylinder_contact.json); "
                                   "set aside only where MJX given C's contacts reproduces C (tests/test_fuzz.py)",
    "capsule segment solves": "MJX 3.17 adds 1e-6 to the denominators of its closest-point solves on segments "
                              "(sphere-capsule, capsule-capsule; mjx/_src/math.py), C 4.0 solves them exactly: "
                              "points and normals part by about 1e-6 / (1 - cos^2 of the axes' angle), and a deep "
                              "contact's qacc by 1e-5 relative at step 0 (fuzz seed 1 in CI: normal 4.3e-6 apart, "
                              "qvel 0.0036; tests/data/fuzz_capsule_capsule_contact.json); set aside only where "
                              "MJX's contact is its formulas with the 1e-6 and C's the same without, to 1e-9 "
                              "(mjxdiff/compare/segments.py), and MJX given C's contacts reproduces C "
                              "(tests/test_fuzz.py)",
}


# -- the known-divergence catalogue (mjxdiff.compare.known) -------------------------------------------------

def _mjx_version() -> str:
    from mjxdiff.compat import installed

    return installed()["mujoco-mjx"]


#: The MJX release the catalogue was first measured on (with MuJoCo 4.0.0).
MEASURED_ON = "3.17.0"


@dataclasses.dataclass(frozen=True)
class Entry:
    """One known divergence: what it is, the evidence, what a failing scenario must show to
    match it (stage, field, pair and part, element, pattern, cause, integrator, scenario: all
    given must hold), whether it is accepted (``--fail-on new`` lets it pass), and ``versions``,
    the MJX releases it was seen in (``mjxdiff versions`` sweeps; a match on another release is
    labelled all the same, and the report says where it was seen)."""

    id: str
    title: str
    evidence: str
    stage: str | None = None
    field: str | None = None
    pattern: str | None = None
    cause: str | None = None
    integrator: tuple[str, ...] = ()
    scenario: str | None = None
    accepted: bool = False
    versions: tuple[str, ...] = (MEASURED_ON,)
    #: MJX release prefixes (``"3.3."``) this entry is about; it matches nothing on others.
    #: Empty: any release (what the entry describes is not tied to one).
    only_on: tuple[str, ...] = ()
    #: ``approximation`` (MJX computes it another way on purpose, or a setting parts them), ``bug``
    #: (MJX computes it wrong in the release measured), ``fixed`` (a bug of older releases only).
    kind: str = "approximation"
    #: A bug's minimal reproducer, made by ``mjxdiff shrink --bundle``: a directory of the
    #: repository (model.xml, state.json, repro.py, signature.json, README.md); else why none.
    bundle: str = ""
    #: Whether a sweep's failure can be labelled with it. False where the report names nothing
    #: that tells this divergence from a bug of the same stage (a tendon's armature shows as a
    #: joint's qM): the entry is evidence and a bundle, never a label.
    labels: bool = True
    #: What the user can do about it: the setting or modelling change that removes or reduces the
    #: gap, or the release that fixed it. :func:`advice` adds what ``--fail-on new`` does with it and,
    #: for a bug with a bundle, where to report it.
    remedy: str = ""
    #: A regular expression the geom-type pair of a differing contact must match in full
    #: (``plane-mesh``, ``box-box``; types sorted, a flex is ``flex``), in any drill-down of the
    #: failure (:func:`contacts_shown`): read from the drill-down's data, never from its text.
    pair: str | None = None
    #: A regular expression what of that pair's contacts differs most must match in full: ``count``,
    #: ``dist``, ``position``, ``friction``, ``normal`` or ``tangent frame``
    #: (:func:`mjxdiff.compare.diagnose.contact_detail`).
    part: str | None = None
    #: A regular expression an element the failure names, as ``kind:type``, must match in full
    #: (``sensor:accelerometer``, ``joint:free``, ``tendon:spatial-sidesite``): the first
    #: divergence's (:func:`mjxdiff.compare.verdict.component_elements`) or a drill-down's first differing
    #: field's (:func:`elements_shown`).
    element: str | None = None
    #: The implementations under test this entry is about (a report's ``info.impl``: ``mjx`` for
    #: MJX's JAX implementation, ``warp`` for MuJoCo Warp, ``mjx.warp`` for MJX's warp
    #: implementation); empty: any. The catalogue's entries about MJX's own code say ``mjx``:
    #: MuJoCo Warp computes those stages with other code, so the label and its advice would mislead.
    impl: tuple[str, ...] = ()
    #: A regular expression one of the model's features (:func:`model_features`, ``info.features``)
    #: must match in full: what a divergence needs in the model that no drill-down shows.
    feature: str | None = None
    #: What known formula must account in full for that pair's contacts' difference
    #: (:func:`mjxdiff.compare.diagnose.contact_detail`'s ``explained``), read from the drill-down's data.
    explained: str | None = None

    def _element_fits(self, s: dict[str, Any]) -> bool:
        if self.element is None:
            return True
        return any(isinstance(e, dict) and re.fullmatch(self.element, f"{e.get('kind')}:{e.get('type')}") is not None
                   for e in elements_shown(s))

    def _contact_fits(self, s: dict[str, Any]) -> bool:
        if self.pair is None and self.part is None and self.explained is None:
            return True
        return not contacts_ruled_out(s) and any(
            (self.pair is None or re.fullmatch(self.pair, c.get("pair", "")) is not None)
            and (self.part is None or re.fullmatch(self.part, c.get("part") or "") is not None)
            and (self.explained is None or c.get("explained") == self.explained)
            for c in contacts_shown(s))

    def matches(self, s: dict[str, Any]) -> bool:
        """Whether a failing scenario (a report's scenario dict) fits this entry."""
        if not self.labels:
            return False
        diag = s.get("diagnosis") or {}
        drill = diag.get("drill_down") or {}
        first = s.get("first_divergence") or {}
        one = (s.get("info") or {}).get("onestep") or {}  # the one-step check's drill-down, where it failed
        text = " ".join(str(x) for x in (s.get("message", ""), drill.get("object", ""), drill.get("first_field", ""),
                                         one.get("stage_object", "")))
        checks = [
            not self.only_on or any(_mjx_version().startswith(v) for v in self.only_on),
            not self.impl or (s.get("info") or {}).get("impl", "mjx") in self.impl,
            self.feature is None or any(re.fullmatch(self.feature, f) is not None
                                        for f in (s.get("info") or {}).get("features", ())),
            self.stage is None or self.stage in (drill.get("first_stage"), one.get("first_stage")),
            self.field is None or first.get("field") == self.field,
            self._contact_fits(s),
            self._element_fits(s),
            self.pattern is None or re.search(self.pattern, text) is not None,
            self.cause is None or (diag.get("cause") or {}).get("cause") == self.cause,
            not self.integrator or (s.get("info") or {}).get("integrator") in self.integrator,
            self.scenario is None or re.fullmatch(self.scenario, s.get("name", "")) is not None,
        ]
        return all(checks)


def model_features(m: mujoco.MjModel) -> tuple[str, ...]:
    """What a catalogue entry may need of the model that no drill-down shows (:attr:`Entry.feature`):

    * ``contact:direct-solref-under-priority``: a geom with a direct (negative) solref, and a geom
      of higher priority (C then takes the higher-priority geom's solref alone).
    * ``actuator:affine-gain-velocity-clamped-ctrl``: an actuator without activation dynamics whose
      affine gain has a velocity term (``gainprm[2]``) and whose control is clamped
      (``ctrllimited``, clampctrl enabled): what implicitfast differentiates at the clamped control.
    """
    found = []
    direct = m.geom_solref[:, 0] < 0
    if direct.any() and (m.geom_priority > m.geom_priority[direct].min()).any():
        found.append("contact:direct-solref-under-priority")
    affine_velocity = ((m.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_AFFINE)) & (m.actuator_gainprm[:, 2] != 0)
                       & (m.actuator_ctrllimited != 0) & (m.actuator_dyntype == int(mujoco.mjtDyn.mjDYN_NONE)))
    if affine_velocity.any() and not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CLAMPCTRL):
        found.append("actuator:affine-gain-velocity-clamped-ctrl")
    return tuple(found)


def contacts_shown(s: dict[str, Any]) -> list[dict[str, Any]]:
    """The differing contacts (:func:`mjxdiff.compare.diagnose.contact_detail`) that a failing scenario's
    drill-downs found: the diagnosis's, the solver floor's, the one-step check's, the twin's;
    not those of a drill-down where a stage that reads no contact differs too
    (:attr:`mjxdiff.compare.diagnose.DrillDown.beside_contacts`)."""
    info = s.get("info") or {}
    drills = [(s.get("diagnosis") or {}).get("drill_down") or {}]
    drills += [info.get(check) or {} for check in ("solver_floor", "onestep", "twin")]
    return [d["contact"] for d in drills if isinstance(d.get("contact"), dict) and not d.get("beside_contacts")]


def elements_shown(s: dict[str, Any]) -> list[dict[str, Any]]:
    """The elements a failing scenario names as data: its first divergence's
    (:func:`mjxdiff.compare.verdict.component_elements`) and those of the first differing field of its
    drill-downs (:attr:`mjxdiff.compare.diagnose.DrillDown.element`: a tendon's ``spatial-sidesite``, ...)."""
    info = s.get("info") or {}
    found = [(s.get("first_divergence") or {}).get("element"),
             ((s.get("diagnosis") or {}).get("drill_down") or {}).get("element"),
             (info.get("solver_floor") or {}).get("element")]
    found += [(info.get(check) or {}).get("stage_element") for check in ("onestep", "twin")]
    return [e for e in found if isinstance(e, dict)]


#: The label of the cause ablation that disables contacts (:data:`mjxdiff.compare.diagnose.ABLATIONS`):
#: its record in a cause's ``tried`` is data :func:`contacts_ruled_out` reads.
NO_CONTACTS = "contacts disabled"


def contacts_ruled_out(s: dict[str, Any]) -> bool:
    """Whether a cause attribution of the failure (the rollout's, the one-step check's) ran with
    contacts disabled and still failed: the engines part without contacts, so no contact
    divergence of the catalogue explains it."""
    info = s.get("info") or {}
    causes = [(s.get("diagnosis") or {}).get("cause") or {}, (info.get("onestep") or {}).get("cause") or {}]
    return any(t.get("ablation") == NO_CONTACTS and t.get("passed") is False and not t.get("error")
               for c in causes for t in c.get("tried") or ())


def _releases_before(minor: int) -> tuple[str, ...]:
    """``only_on`` prefixes of the supported MJX releases 3.3 to 3.``minor - 1``."""
    return tuple(f"3.{m}." for m in range(3, minor))


#: Why a fixed bug has no bundle.
FIXED_SINCE = "none: fixed in later releases, so the installed MJX cannot show it; the versions sweep is its evidence"

#: The catalogue's entries about any implementation under test (the solver settings part MJX, MuJoCo
#: Warp and C alike); every other entry is about MJX's JAX code (``impl=("mjx",)``).
ANY_IMPL = ("solver-truncation", "truncated-solver")

#: What mjxdiff has measured of MJX 3.17 against MuJoCo 4.0 (README, "Known C/MJX divergences";
#: scenario notes). Approximations by design first, then bugs; the first matching entry wins.
_MEASURED: tuple[Entry, ...] = (
    Entry("solver-truncation", "solver settings capped short of convergence: MJX and C part where each stops",
          "tests/test_solver_floor.py: a 1-iteration quadruped parts by radians over 200 steps; with a converged "
          "solver (the twin) and one step from C's states the engines agree to rounding", cause="solver truncation",
          accepted=True, versions=(MEASURED_ON, "3.3.5", "3.9.0"),
          remedy="raise the solver's iterations and ls_iterations (with a tolerance of 1e-8 or below) "
                 "until the converged twin's verdict and the rollout's agree; keeping your settings is a choice: "
                 "MJX and C then part by the amount the verdict prints, which a policy trained in MJX meets as "
                 "model error"),
    Entry("plane-mesh-before-3.14", "MJX before 3.14: a plane-mesh manifold of more contacts than C's",
          "mjxdiff versions (2026-11-26), primitives_on_plane at step 0, geoms floor / mesh: C 3, MJX 4 contacts on "
          "3.3.7 and 3.9.0; C 2, MJX 4 on 3.10.0 and 3.12.0 (the one-step check from C's state shows the same); "
          "passes on 3.14.0 to 3.17.0 (3.13 not swept)", stage="collision", pair="plane-mesh",
          versions=("3.3.5", "3.3.7", "3.9.0", "3.10.0", "3.12.0"), only_on=_releases_before(14),
          kind="fixed", bundle=FIXED_SINCE,
          remedy="upgrade mujoco-mjx to 3.14 or later, where it is fixed"),
    Entry("capsule-mesh-before-3.15", "MJX before 3.15: capsule-mesh contacts other than C's",
          "mjxdiff versions (2026-11-26), primitive_pairs at step 0, geoms slab / cap_slab: C 1, MJX 2 contacts on "
          "3.3.7; C 2, MJX 2 with normals 1e-3 apart on 3.9.0, 3.10.0, 3.12.0 and 3.14.0 (the one-step check shows "
          "the same); passes on 3.15.0 to 3.17.0", stage="collision", pair="capsule-mesh",
          versions=("3.3.5", "3.3.7", "3.9.0", "3.10.0", "3.12.0", "3.14.0"), only_on=_releases_before(15),
          kind="fixed", bundle=FIXED_SINCE,
          remedy="upgrade mujoco-mjx to 3.15 or later, where it is fixed"),
    Entry("plane-box-corners", "plane-box/mesh: MJX keeps only corners within 1 mm of the deepest",
          "primitives_on_plane notes: a box that lands on a corner or rocks (> 1 mm depth spread) diverges ~1e-3; "
          "a tipped cube in sensing: C 4 corners, MJX 3", stage="collision", pair="plane-(box|mesh)",
          versions=(MEASURED_ON, "3.3.5", "3.3.0", "3.9.0"),
          remedy="nothing to set: MJX drops corners more than 1 mm above the deepest; where contact forces on a "
                 "tipping box or mesh foot matter, use sphere or capsule collision geoms, or judge the task's "
                 "behaviour (mjxdiff closedloop) instead of the trajectory"),
    Entry("plane-cylinder-rim", "plane-cylinder: MJX adds the second rim point only near parallel",
          "primitives_on_plane notes: the second rim point only when the axis is within ~1e-3 of parallel; a "
          "cylinder sunk into a plane: C 4 contacts, MJX 3. A rim point missing, not one misplaced: a count",
          stage="collision", pair="plane-cylinder", part="count",
          remedy="use a capsule (or a sphere) for a cylinder's collision geom where its shape allows; a tilted "
                 "cylinder on a plane otherwise gets other contact forces"),
    Entry("contact-tangent-frame", "contact tangent frames: MJX's plane-capsule (and other) frames differ from C's, "
          "which turns a pyramidal friction cone",
          "tests/test_known_divergences.py: a plane-capsule contact's first tangent is (0, 1, 0) in MJX, along the "
          "capsule's axis in C; Unitree H1 (playground scene_mjx_feetonly.xml, pyramidal): one step from the same "
          "state with converged solvers, qfrc_constraint 52 apart, same contacts, other efc_aref",
          stage="collision", part="tangent frame",
          remedy="use the elliptic friction cone (<option cone=\"elliptic\"/>): with isotropic friction its forces "
                 "do not depend on the tangent frame; a pyramidal cone turns with the frame"),
    Entry("box-box-manifold", "box-box: MJX pads the manifold and places points on a surface",
          "primitive_pairs / box_stack notes: edge-first landings C 2, MJX 4 contacts; contact points on a surface "
          "(C halfway): friction arms differ by dist/2", pair="box-box",
          versions=(MEASURED_ON, "3.3.5", "3.3.0"),
          remedy="nothing to set: MJX's box-box contacts differ at edge landings by design; where stacking or "
                 "grasping boxes matters, judge the task's behaviour (mjxdiff closedloop) instead of the "
                 "trajectory"),
    Entry("ellipsoid-cylinder-pairs", "sphere/capsule/ellipsoid/cylinder against ellipsoid/cylinder: MJX's "
          "10-step SDF descent vs C's exact collision",
          "tests/data/fuzz_ellipsoid_cylinder_contact.json: at its first contact an ellipsoid-cylinder pair is "
          "2.882 mm deep in C (GJK/EPA; 2.883 mm exactly), 1.354 mm in MJX (collision_sdf.py), normals 0.037 rad "
          "and points 9.7 mm apart, qacc 99 apart; MJX given C's contacts agrees to 7e-13 (tests/test_fuzz.py); "
          "scenarios/wip/sdf_pairs.toml notes", stage="collision",
          pair="(sphere|capsule|ellipsoid)-(ellipsoid|cylinder)|cylinder-cylinder",
          remedy="use sphere, capsule or box collision geoms for these pairs (MJX collides them exactly); MJX's "
                 "SDF descent for ellipsoids and cylinders gives other depths and normals"),
    Entry("capsule-regularisation", "capsule pairs: MJX's +1e-6 segment regularisation tilts normals",
          "primitive_pairs notes: closest_segment_point divides by |ab|^2 + 1e-6; a sphere rolling along a 1 m "
          "capsule rail drifts 2e-3 qvel in 300 steps. The regularisation moves a contact; it makes or drops "
          "none, so a count that differs is not it (a capsule-capsule radius slip of MJX, C 1 and MJX 0 contacts, "
          "was labelled so); labelled only where the segment formulas with and without the 1e-6 give each "
          "engine's contact (mjxdiff.compare.segments), so that a slip in MJX's segment solve is not it",
          pair=r"sphere-capsule|capsule-\w+", part=r"dist|position|normal|tangent frame|friction",
          explained="segment regularisation",
          versions=(MEASURED_ON, "3.3.5", "3.9.0"),
          remedy="split long capsules into shorter ones (the tilt grows with the contact's distance from the "
                 "segment's origin), or use sphere geoms for rolling contacts along a capsule"),
    Entry("heightfield-pairs", "heightfield pairs: MJX keeps other contacts than C",
          "tests/test_known_divergences.py: a sphere across a valley C 2, MJX 1 contact (qacc 16.4 apart); a box "
          "on a slope C 3, MJX 4", pair=r"hfield-\w+",
          remedy="nothing to set: MJX keeps other heightfield contacts; for terrain, judge the task's behaviour "
                 "(mjxdiff closedloop), or use a mesh or boxes where the terrain allows"),
    Entry("rk4-sensor-stage", "RK4: MJX's sensordata is from the last Runge-Kutta stage",
          "integrator_rk4 notes: after an RK4 step MJX's sensordata is from the last stage, C's from the state "
          "before the step", field="sensordata", integrator=("rk4",),
          kind="bug", bundle="tests/data/bundles/rk4-sensor-stage",
          remedy="use the Euler or implicitfast integrator where you read sensors, or recompute sensordata with "
                 "mjx.forward after mjx.step"),
    Entry("implicit-clamped-actuator", "implicit/implicitfast: C leaves a clamped actuator's velocity derivative "
          "out of the implicit update, MJX 3.17 keeps it",
          "Unitree G1 (menagerie scene_mjx.xml: position servos with kv, joint actuatorfrcrange, implicitfast): one "
          "step from the same state 13 rad/s apart in qvel, 1e-13 with the joint clamps removed, with Euler or with "
          "kv = 0; MuJoCo C commit b466829, mirrored in mujoco_warp PR #1149", cause="actuator force clamping",
          integrator=("implicitfast", "implicit"),
          kind="bug", bundle="tests/data/bundles/implicit-clamped-actuator",
          remedy="use the Euler integrator, or remove actuatorfrcrange (the joint's force clamp) on actuated "
                 "joints, or set the actuators' kv to 0: each removes the gap (13 rad/s -> 1e-13 on the G1)"),
    Entry("implicit-affine-ctrl-clamp", "implicitfast: MJX differentiates an affine gain's velocity term at the "
          "raw control, C at the clamped one",
          "tests/data/known/implicit-affine-ctrl-clamp.xml (a slide driven by gainprm=\"2 0 -1.5\", ctrlrange -1 1, "
          "ctrl 2): one step from the same state qvel 2.6e-4 apart, agreeing to the last bit with ctrl inside the "
          "range or ctrllimited=\"false\"; MJX 3.17's derivative.deriv_smooth_vel reads d.ctrl, C's "
          "mjd_actuator_vel the clamped control. Found when a source-mutation audit gave integrator_implicitfast "
          "such an actuator", integrator=("implicitfast",), stage="integration",
          feature="actuator:affine-gain-velocity-clamped-ctrl",
          kind="bug", bundle="tests/data/bundles/implicit-affine-ctrl-clamp",
          remedy="clip the controls to ctrlrange yourself before mjx.step (MJX and C then agree), or use the Euler "
                 "integrator for affine actuators with a velocity gain"),
    Entry("rotation-integration", "implicitfast/RK4: free-body rotation integrated differently (grows like ω²)",
          "integrator_* notes: fast-spinning free bodies; tests/data/known/rotation-integration.xml (a ball "
          "joint under RK4): every forward stage agrees, the update does not (drill-down stage integration), and "
          "the first divergence is the ball joint's qpos", integrator=("implicitfast", "rk4"),
          stage="integration", element=r"joint:(free|ball)",
          kind="bug", bundle="tests/data/bundles/rotation-integration",
          remedy="use the Euler integrator for fast-spinning free bodies, or a smaller timestep (the gap grows "
                 "like the angular velocity squared times the timestep)"),
    Entry("acceleration-sensors-without-constraints", "MJX skips sensor_acc in a model without constraint rows",
          "the bundle: a spring-loaded slider's accelerometer C -0.0234 m/s², MJX 0",
          field="sensordata", element="sensor:(accelerometer|force|torque|framelinacc|frameangacc)",
          kind="bug", bundle="tests/data/bundles/acceleration-sensors-without-constraints",
          remedy="compute accelerations from qacc yourself, or give the model a constraint (a joint limit or "
                 "contact) so that MJX evaluates sensor_acc"),
    Entry("contact-sensor-explicit-pair", "contact sensor reads the explicit pair's contact",
          "the bundle: with a <pair>, a geom-matched contact sensor reads the pair's force",
          field="sensordata", element="sensor:contact",
          kind="bug", bundle="tests/data/bundles/contact-sensor-explicit-pair",
          remedy="match the contact sensor by body or site rather than by geom, or drop the explicit <pair> for "
                 "those geoms"),
    Entry("tendon-wrap-sidesite", "a spatial tendon wraps a cylinder on the other side of its sidesite",
          "fuzz seed 3 (tests/data/fuzz_wrap_sidesite.json), shrunk to one free body, a wrap cylinder and one "
          "tendon: ten_length C 1.438173, MJX 1.441468 at step 0. C 4.0 picks the side by the winding of end0 -> "
          "sidesite -> end1 around the wrap geom (MuJoCo Warp 4.0 too), MJX 3.17 by the older rule (the arc "
          "whose middle is nearest the sidesite's direction): near the sidesite's symmetry plane they part",
          stage="tendons", element="tendon:spatial-sidesite",
          kind="bug", bundle="tests/data/bundles/tendon-wrap-sidesite",
          remedy="move the tendon's sidesite away from the plane of symmetry between the tendon's ends (the "
                 "engines agree away from it)"),
    Entry("tendon-armature-trees", "a fixed tendon with armature coupling two kinematic trees, or two branches of "
          "one: another qM",
          "fuzz seed 0 (tests/data/fuzz_tendon_armature_trees.json), shrunk to two bodies with a hinge each and "
          "one fixed tendon (armature 0.003): qM 0.0044 apart (scaled) at step 0; C 4.0 keeps the trees' "
          "sparsity, MJX 3.17's mass matrix differs. Two sibling hinges of one body under a tendon with armature "
          "0.01: qM between them C 0, MJX 0.01; a hinge and its child's: equal (2026-11-29, after a generated "
          "model's energy differed). A sweep names the joint, not the tendon, so the entry labels nothing (an "
          "armature bug shows the same way)", stage="inertia",
          kind="bug", bundle="tests/data/bundles/tendon-armature-trees", labels=False,
          remedy="set the tendon's armature to 0, or give a tendon with armature only joints on one chain of bodies "
                 "(each an ancestor of the next): C leaves the coupling between branches out of its sparse mass "
                 "matrix, MJX keeps it"),
    Entry("truncated-solver", "a solver capped at few iterations: the engines stop at different points",
          "ant at 1000 steps: 4 of 64 members jump 1e-11 -> 5e-6 qvel at a contact; gone with 100 iterations",
          cause="solver convergence",
          remedy="raise the solver's iterations (the bundled ant passes with 100 where 4 of 64 members parted at "
                 "1000 steps)"),
    Entry("equality-aref", "connect/weld: other efc_aref (anchor off the body origin, spinning)",
          "equality notes: same efc_pos/efc_J/efc_KBIP, qvel 0.4 rad/s apart after one step; connect off-origin "
          "on a spinning body z 1.8018 C, 1.7658 MJX", stage="constraint", cause="equality constraints",
          kind="bug", bundle="tests/data/bundles/equality-aref",
          remedy="put connect and weld anchors at the body's origin where you can (the off-origin anchor on a "
                 "spinning body is where the engines part)"),
    Entry("mesh-mesh-contacts-3.3", "MJX 3.3: mesh-mesh contacts other than C's",
          "mjxdiff versions 3.3.5/0.7.0 (2026-11-26): convex_mesh at step 0, geoms slab / frustum_slab: C 1, MJX 4 "
          "contacts (passes contacts disabled); the same scenario passes on MJX 3.9.0 and 3.17.0", stage="collision",
          pair="mesh-mesh", versions=("3.3.5",), only_on=("3.3.",),
          kind="fixed", bundle=FIXED_SINCE,
          remedy="upgrade mujoco-mjx to 3.9 or later, where it is fixed"),
    Entry("flex-ignored-3.3", "MJX 3.3.0-3.3.4 accept a flex and make none of its contacts",
          "tests/data/flex_cloth.xml (a 4x4 cloth falling onto a plane), swept on MJX 3.3.0 (2026-11-26): FAIL at "
          "step 0, first field contact, flex 'cloth' / flex 'cloth' C 2, MJX 0 contacts (C 9 at the one-step "
          "check); likely cause contact generation. MJX 3.3.5 and later refuse the model (put_model: 'Flex not "
          "implemented for JAX backend.', unsupported); support.UNSUPPORTED_FEATURES 'flex' refused_since 3.3.5 "
          "(tests/test_supported_versions.py)", stage="collision", pair=r"flex-\w+",
          versions=("3.3.0",), only_on=("3.3.0", "3.3.1", "3.3.2", "3.3.3", "3.3.4"),
          kind="fixed", bundle=FIXED_SINCE,
          remedy="upgrade mujoco-mjx to 3.3.5 or later, which refuses flex (MJX has no flex contacts); test flex "
                 "models in MuJoCo C or MuJoCo Warp"),
    Entry("get-data-margin-contacts", "get_data drops contacts inside the margin (dist > 0)",
          "the bundle: a sphere 2 mm above the floor, margin 5 mm: C 1 contact, get_data 0. A sweep's host-interface "
          "check compares penetrating contacts only (mjxdiff.compare.transfer.CONTACTS_COMPARED), so it never "
          "shows this one, and a contact it does show is another bug: the entry labels nothing",
          field="transfer", labels=False,
          kind="bug", bundle="tests/data/bundles/get-data-margin-contacts",
          remedy="read contacts from MJX's own data (dx._impl.contact, dist < includemargin) rather than "
                 "mjx.get_data where geoms have a margin"),
)
#: Where MuJoCo Warp's bugs are reported.
WARP_UPSTREAM = "https://github.com/google-deepmind/mujoco_warp/issues"

#: What mjxdiff has measured of MuJoCo Warp 4.0 (``--impl warp``) and of MJX 3.17's vendored copy of
#: it (``--impl mjx.warp``) against MuJoCo C 4.0 (docs/findings.md, "MuJoCo Warp").
_MEASURED_WARP: tuple[Entry, ...] = (
    Entry("warp-solref-priority", "MuJoCo Warp: a direct solref on the lower-priority geom overrides the "
          "higher-priority geom's",
          "tests/test_mjwarp.py: a sphere 9.5 mm into a priority-1 floor, one step's qvel 0.066 apart (0.0028 at "
          "0.5 mm), 2e-8 with positive solrefs; contact_parameters fails at step 0 under --impl warp and --impl "
          "mjx.warp (MJX's vendored copy shares it); the drill-down names the contact at collision, floor / puck, "
          "solref differs by 2e+03 (2026-11-29)",
          stage="collision", part="solref", feature="contact:direct-solref-under-priority", impl=("warp", "mjx.warp"),
          kind="bug", bundle="tests/test_mjwarp.py::test_the_higher_priority_geom_s_solref_wins_over_a_direct_one",
          remedy="give a geom that meets a higher-priority geom a positive solref (timeconst, dampratio), or none: "
                 "C takes the higher-priority geom's solref, MuJoCo Warp the direct one"),
)

CATALOGUE: tuple[Entry, ...] = tuple(e if e.id in ANY_IMPL else dataclasses.replace(e, impl=("mjx",))
                                     for e in _MEASURED) + _MEASURED_WARP
