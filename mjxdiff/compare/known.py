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
    pair = "box-box"                 # regex on the geom types of a differing contact pair
    scenario = "gripper_.*"          # optional regex on the scenario name
    accepted = true                  # counts as accepted by the baseline

Matching (every given condition must hold): ``stage`` equals the first stage of the rollout's
drill-down or of the one-step check's (``collision``, ``sensors``, ``constraint``,
``integration``, ...), ``field`` equals the
first divergent field (``qpos``, ``qvel``, ``sensordata``, ``transfer``, ...), ``pair``
matches in full the geom types of a contact pair that a drill-down found differing
(``plane-mesh``, ``box-box``: sorted as MuJoCo numbers them, plane first, a flex ``flex``) and
``part`` matches in full what differs there (``count``; else the geometry first: ``dist``,
``position``, ``normal``; else ``friction``, ``tangent frame``), ``explained`` equals what known
formula accounts for that pair's difference in full (``segment regularisation``), ``element``
matches in full an element the failure names as ``kind:type`` (``sensor:accelerometer``,
``joint:free``, ``tendon:spatial-sidesite``: the first divergence's, or a drill-down's first
differing field's), all three read from the report's data; ``pattern`` is found in the message plus
the drill-down's object (text, for what has no field of its own: a reworded message can change the
label, so the catalogue uses none, and loading an entry that has one warns once), ``cause`` equals
the attributed cause (``--diagnose full``), ``integrator`` is among the model's integrators,
``scenario`` matches the scenario's name, ``impl`` lists the implementations under test the entry is
about (``mjx``, ``warp``, ``mjx.warp``; ``info.impl``; left out, any: the catalogue's entries about
MJX's code say ``mjx``). An entry with ``pair`` or ``part`` needs the contacts to be the whole
story: it matches no failure that stays with
contacts disabled (:func:`mjxdiff.compare.support.contacts_ruled_out`) and no drill-down in which a stage
that reads no contact differs too (``beside_contacts``).
"""

from __future__ import annotations

import re
import tomllib
import warnings
from pathlib import Path
from typing import Any

# the catalogue and its Entry live in mjxdiff.compare.support; public here too, as before
from mjxdiff.compare.support import CATALOGUE, WARP_UPSTREAM, Entry

__all__ = ["Entry", "CATALOGUE", "advice", "entries", "load_entries", "match", "KnownError"]

#: Where MJX bugs are reported (MJX lives in the MuJoCo repository).
UPSTREAM = "https://github.com/google-deepmind/mujoco/issues"


class KnownError(ValueError):
    """An entries file that cannot be read; one line."""


def load_entries(path: str | Path) -> tuple[Entry, ...]:
    """Entries from a TOML file of ``[[known]]`` tables (see the module docstring)."""
    try:
        data = tomllib.loads(Path(path).read_text())
        entries = []
        for t in data.get("known", []):
            t = dict(t)
            t["integrator"] = tuple(t.get("integrator", ()))
            for key in ("versions", "only_on", "impl"):
                if key in t:
                    t[key] = tuple(t[key])
            entries.append(Entry(**t))
        for e in entries:
            for regex in (e.pattern, e.pair, e.element, e.feature):
                if regex:
                    re.compile(regex)
        worded = [e.id for e in entries if e.pattern]
        if worded:
            warnings.warn(f"{path}: {', '.join(worded)} match the message's wording (pattern), which a new "
                          "mjxdiff may reword; prefer stage, field, pair, part, element or cause", stacklevel=2)
        return tuple(entries)
    except (OSError, tomllib.TOMLDecodeError, TypeError, re.error) as e:
        raise KnownError(f"{path}: not a known-divergences file ({type(e).__name__}: {' '.join(str(e).split())}); "
                         "give [[known]] tables with id, title, evidence and match keys") from None


def entries(path: str | Path | None = None) -> tuple[Entry, ...]:
    """What a sweep tries, in order: the user's entries from ``path`` (if given), then the catalogue."""
    return (load_entries(path) if path else ()) + CATALOGUE


def match(s: dict[str, Any], entries: tuple[Entry, ...] = CATALOGUE) -> Entry | None:
    """The first entry a failing scenario (a report's scenario dict) matches, or None.

    >>> contact = {"pair": "box-box", "geoms": ["pad", "box"], "c": 2, "mjx": 4, "part": "count"}
    >>> failure = {"status": "fail", "name": "my_gripper", "message": "... first field to differ: contact "
    ...            "(collision, geoms pad / box (box-box: C 2, MJX 4 contacts))",
    ...            "diagnosis": {"drill_down": {"first_stage": "collision", "contact": contact}}}
    >>> match(failure).id
    'box-box-manifold'
    >>> match({"status": "pass"}) is None
    True
    """
    if s.get("status") != "fail":
        return None
    return next((e for e in entries if e.matches(s)), None)


def advice(entry: Entry) -> str:
    """What to do about a failure labelled ``entry``, in one line: its remedy, what
    ``--fail-on new`` does with it and, for a bug with a bundle, where to report it.

    >>> advice(CATALOGUE[0]).endswith("--fail-on new accepts it, a baseline or not")
    True
    """
    parts = [entry.remedy] if entry.remedy else []
    if entry.accepted:
        parts.append("--fail-on new accepts it, a baseline or not")
    else:
        parts.append("to fail only on what is new, sweep with --baseline REF --fail-on new (or accept it: "
                     "accepted = true in your --known file)")
    if entry.kind == "bug" and entry.bundle.startswith("tests/") and "::" in entry.bundle:
        parts.append(f"a MuJoCo Warp bug: report it at {WARP_UPSTREAM} with the reproducer {entry.bundle} of "
                     "mjxdiff's repository (a strict xfail while MuJoCo Warp and C differ)")
    elif entry.kind == "bug" and entry.bundle.startswith("tests/"):
        parts.append(f"an MJX bug: report it at {UPSTREAM} with the reproducer in {entry.bundle} of mjxdiff's "
                     "repository, or your own from mjxdiff shrink --bundle")
    return "; ".join(parts)
