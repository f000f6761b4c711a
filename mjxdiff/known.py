"""A catalogue of known MJX-vs-C approximations, each with its evidence, and matching of a
failing scenario's diagnosis against it.

A failure whose diagnosis matches an entry is labelled ``known: <id>`` in text, JSON and
HTML instead of being left as an unexplained discrepancy. It still counts as a divergence
(exit 1) unless the user's baseline accepts it (``sweep --baseline ... --fail-on new``:
only new failures that no *accepted* entry explains fail the run). Users add entries in a
TOML file (``--known FILE``)::

    [[known]]
    id = "our-gripper-pads"
    title = "soft pads: MJX's box-box manifold"
    evidence = "ticket 123; C 2 contacts, MJX 4"
    pattern = "\\\\(box-box:"          # regex searched in the failure's message and diagnosis
    scenario = "gripper_.*"          # optional regex on the scenario name
    accepted = true                  # counts as accepted by the baseline

Matching (every given condition must hold): ``stage`` equals the first stage of the rollout's
drill-down or of the one-step check's (``collision``, ``sensors``, ``constraint``,
``integration``, ...), ``field`` equals the
first divergent field (``qpos``, ``qvel``, ``sensordata``, ``transfer``, ...), ``pattern``
is found in the message plus the drill-down's object, ``cause`` equals the attributed cause
(``--diagnose full``), ``integrator`` is among the model's integrators, ``scenario``
matches the scenario's name.
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from pathlib import Path
from typing import Any

__all__ = ["Entry", "CATALOGUE", "load_entries", "match", "KnownError"]


class KnownError(ValueError):
    """An entries file that cannot be read; one line."""


@dataclasses.dataclass(frozen=True)
class Entry:
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

    def matches(self, s: dict[str, Any]) -> bool:
        """Whether a failing scenario (a report's scenario dict) fits this entry."""
        diag = s.get("diagnosis") or {}
        drill = diag.get("drill_down") or {}
        first = s.get("first_divergence") or {}
        one = (s.get("info") or {}).get("onestep") or {}  # the one-step check's drill-down, where it failed
        text = " ".join(str(x) for x in (s.get("message", ""), drill.get("object", ""), drill.get("first_field", ""),
                                         one.get("stage_object", "")))
        checks = [
            self.stage is None or self.stage in (drill.get("first_stage"), one.get("first_stage")),
            self.field is None or first.get("field") == self.field,
            self.pattern is None or re.search(self.pattern, text) is not None,
            self.cause is None or (diag.get("cause") or {}).get("cause") == self.cause,
            not self.integrator or (s.get("info") or {}).get("integrator") in self.integrator,
            self.scenario is None or re.fullmatch(self.scenario, s.get("name", "")) is not None,
        ]
        return all(checks)


#: What mjxdiff has measured of MJX 3.17 against MuJoCo 4.0 (README, "Known C/MJX divergences";
#: scenario notes). Approximations by design first, then bugs; the first matching entry wins.
CATALOGUE: tuple[Entry, ...] = (
    Entry("solver-truncation", "solver settings capped short of convergence: MJX and C part where each stops",
          "tests/test_solver_floor.py: a 1-iteration quadruped parts by radians over 200 steps; with a converged "
          "solver (the twin) and one step from C's states the engines agree to rounding", cause="solver truncation",
          accepted=True),
    Entry("plane-box-corners", "plane-box/mesh: MJX keeps only corners within 1 mm of the deepest",
          "primitives_on_plane notes: a box that lands on a corner or rocks (> 1 mm depth spread) diverges ~1e-3; "
          "a tipped cube in sensing: C 4 corners, MJX 3", stage="collision", pattern=r"\(plane-(box|mesh):"),
    Entry("plane-cylinder-rim", "plane-cylinder: MJX adds the second rim point only near parallel",
          "primitives_on_plane notes: the second rim point only when the axis is within ~1e-3 of parallel; a "
          "cylinder sunk into a plane: C 4 contacts, MJX 3", stage="collision", pattern=r"\(plane-cylinder:"),
    Entry("contact-tangent-frame", "contact tangent frames: MJX's plane-capsule (and other) frames differ from C's, "
          "which turns a pyramidal friction cone",
          "tests/test_known_divergences.py: a plane-capsule contact's first tangent is (0, 1, 0) in MJX, along the "
          "capsule's axis in C; Unitree H1 (playground scene_mjx_feetonly.xml, pyramidal): one step from the same "
          "state with converged solvers, qfrc_constraint 52 apart, same contacts, other efc_aref",
          stage="collision", pattern=r"tangent frame differs"),
    Entry("box-box-manifold", "box-box: MJX pads the manifold and places points on a surface",
          "primitive_pairs / box_stack notes: edge-first landings C 2, MJX 4 contacts; contact points on a surface "
          "(C halfway): friction arms differ by dist/2", pattern=r"\(box-box:"),
    Entry("ellipsoid-cylinder-pairs", "sphere/capsule/ellipsoid/cylinder against ellipsoid/cylinder: MJX's "
          "10-step SDF descent vs C's exact collision",
          "tests/data/fuzz_ellipsoid_cylinder_contact.json: at its first contact an ellipsoid-cylinder pair is "
          "2.882 mm deep in C (GJK/EPA; 2.883 mm exactly), 1.354 mm in MJX (collision_sdf.py), normals 0.037 rad "
          "and points 9.7 mm apart, qacc 99 apart; MJX given C's contacts agrees to 7e-13 (tests/test_fuzz.py); "
          "scenarios/wip/sdf_pairs.toml notes", stage="collision",
          pattern=r"\(((sphere|capsule|ellipsoid)-(ellipsoid|cylinder)|cylinder-cylinder):"),
    Entry("capsule-regularisation", "capsule pairs: MJX's +1e-6 segment regularisation tilts normals",
          "primitive_pairs notes: closest_segment_point divides by |ab|^2 + 1e-6; a sphere rolling along a 1 m "
          "capsule rail drifts 2e-3 qvel in 300 steps", pattern=r"\((sphere-capsule|capsule-capsule|capsule-\w+):"),
    Entry("heightfield-pairs", "heightfield pairs: MJX keeps other contacts than C",
          "tests/test_known_divergences.py: a sphere across a valley C 2, MJX 1 contact (qacc 16.4 apart); a box "
          "on a slope C 3, MJX 4", pattern=r"\(hfield-\w+:"),
    Entry("rk4-sensor-stage", "RK4: MJX's sensordata is from the last Runge-Kutta stage",
          "integrator_rk4 notes: after an RK4 step MJX's sensordata is from the last stage, C's from the state "
          "before the step", field="sensordata", integrator=("rk4",)),
    Entry("implicit-clamped-actuator", "implicit/implicitfast: C leaves a clamped actuator's velocity derivative "
          "out of the implicit update, MJX 3.17 keeps it",
          "Unitree G1 (menagerie scene_mjx.xml: position servos with kv, joint actuatorfrcrange, implicitfast): one "
          "step from the same state 13 rad/s apart in qvel, 1e-13 with the joint clamps removed, with Euler or with "
          "kv = 0; MuJoCo C commit b466829, mirrored in mujoco_warp PR #1149", cause="actuator force clamping",
          integrator=("implicitfast", "implicit")),
    Entry("rotation-integration", "implicitfast/RK4: free-body rotation integrated differently (grows like ω²)",
          "integrator_* notes: fast-spinning free bodies", integrator=("implicitfast", "rk4"),
          pattern=r"integration|free"),
    Entry("acceleration-sensors-without-constraints", "MJX skips sensor_acc in a model without constraint rows",
          "tests/test_known_divergences.py: a spring-loaded slider's accelerometer C -0.0234 m/s², MJX 0",
          field="sensordata", pattern=r"\((accelerometer|force|torque|framelinacc|frameangacc)\)"),
    Entry("contact-sensor-explicit-pair", "contact sensor reads the explicit pair's contact",
          "tests/test_known_divergences.py: with a <pair>, a geom-matched contact sensor reads the pair's force",
          field="sensordata", pattern=r"\(contact\)"),
    Entry("truncated-solver", "a solver capped at few iterations: the engines stop at different points",
          "ant at 1000 steps: 4 of 64 members jump 1e-11 -> 5e-6 qvel at a contact; gone with 100 iterations",
          cause="solver convergence"),
    Entry("equality-aref", "connect/weld: other efc_aref (anchor off the body origin, spinning)",
          "equality notes: same efc_pos/efc_J/efc_KBIP, qvel 0.4 rad/s apart after one step; connect off-origin "
          "on a spinning body z 1.8018 C, 1.7658 MJX", stage="constraint", pattern=r"equality|connect|weld"),
    Entry("get-data-margin-contacts", "get_data drops contacts inside the margin (dist > 0)",
          "tests/test_known_divergences.py: a sphere 2 mm above the floor, margin 5 mm: C 1 contact, get_data 0",
          field="transfer", pattern=r"contact"),
)


def load_entries(path: str | Path) -> tuple[Entry, ...]:
    """Entries from a TOML file of ``[[known]]`` tables (see the module docstring)."""
    try:
        data = tomllib.loads(Path(path).read_text())
        entries = []
        for t in data.get("known", []):
            t = dict(t)
            t["integrator"] = tuple(t.get("integrator", ()))
            entries.append(Entry(**t))
        for e in entries:
            if e.pattern:
                re.compile(e.pattern)
        return tuple(entries)
    except (OSError, tomllib.TOMLDecodeError, TypeError, re.error) as e:
        raise KnownError(f"{path}: not a known-divergences file ({type(e).__name__}: {' '.join(str(e).split())}); "
                         "give [[known]] tables with id, title, evidence and match keys") from None


def match(s: dict[str, Any], entries: tuple[Entry, ...] = CATALOGUE) -> Entry | None:
    """The first entry a failing scenario (a report's scenario dict) matches, or None."""
    if s.get("status") != "fail":
        return None
    return next((e for e in entries if e.matches(s)), None)
