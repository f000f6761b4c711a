"""A bug bundle: a shrunk divergence (:mod:`mjxdiff.tools.shrink`) as a directory an MJX maintainer
can run with only ``mujoco`` and ``mujoco-mjx`` installed.

``model.xml`` (the minimal MJCF, with any mesh files beside it), ``state.json`` (the one C
state), ``repro.py`` (standalone, at most 40 lines: load, set the state, step or forward both
engines, print both values and the difference; exit 1 while they differ), ``signature.json``
(the signature, the numbers, the sizes before and after, the versions and the MJX code digest)
and ``README.md`` (what differs, where, the magnitude against C's own rounding, and the
ablations that did or did not remove it).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from mjxdiff.files import atomic_write
from mjxdiff.tools.shrink import STEP_RTOL, Shrunk, Signature, State, probe

__all__ = ["FILES", "SCRIPT", "ablations", "magnitude", "write", "write_model"]

#: What a bundle holds.
FILES = ("model.xml", "state.json", "repro.py", "signature.json", "README.md")

#: The standalone script (``repro.py``); ``{check}``, ``{field}``, ``{rtol}`` and ``{title}`` are filled in.
SCRIPT = '''"""{title}. Needs only mujoco and mujoco-mjx: python repro.py (exit 1 while they differ)."""
import json, pathlib
import jax
jax.config.update("jax_enable_x64", True)
import mujoco, numpy as np
from mujoco import mjx

HERE, CHECK, FIELD, RTOL = pathlib.Path(__file__).parent, "{check}", "{field}", {rtol}
m = mujoco.MjModel.from_xml_path(str(HERE / "model.xml"))
s, d = json.loads((HERE / "state.json").read_text()), mujoco.MjData(m)
d.qpos[:], d.qvel[:], d.ctrl[:], d.act[:], d.time = s["qpos"], s["qvel"], s["ctrl"], s["act"], s["time"]
# both solvers converged: what differs is not where each stopped
m.opt.iterations, m.opt.ls_iterations, m.opt.tolerance = 200, 100, 1e-14
mx, dx = mjx.put_model(m), mjx.put_data(m, d)
if CHECK == "transfer":  # C's data into MJX and back: are C's contacts still there?
    mujoco.mj_forward(m, d); back = mjx.get_data(m, mjx.put_data(m, d))
    print("C contacts:", d.ncon, " after put_data and get_data:", back.ncon); raise SystemExit(int(back.ncon != d.ncon))
if CHECK == "step":
    mujoco.mj_step(m, d); dx = jax.jit(mjx.step)(mx, dx)
else:
    mujoco.mj_forward(m, d); dx = jax.jit(mjx.forward)(mx, dx)
if FIELD == "contact":  # active contacts by geom pair (C's, MJX's with dist below the margin): dist, pos, frame
    cx = getattr(dx, "_impl", dx).contact
    on = np.asarray(cx.dist) < np.asarray(cx.includemargin)
    def rows(g, x, p, f): return sorted((tuple(sorted(a)), [b, *c, *e]) for a, b, c, e in zip(g, x, p, f.reshape(-1, 9)))
    c = rows(d.contact.geom[:d.ncon].tolist(), d.contact.dist[:d.ncon], d.contact.pos[:d.ncon], d.contact.frame[:d.ncon])
    x = rows(np.asarray(cx.geom)[on].tolist(), *(np.asarray(getattr(cx, k))[on] for k in ("dist", "pos", "frame")))
    print("C   contacts (geom pair, [dist, pos, frame]):", c); print("MJX contacts (geom pair, [dist, pos, frame]):", x)
    same = [p for p, _ in c] == [p for p, _ in x]
    err = max((float(np.max(np.abs(np.subtract(a[1], b[1])))) for a, b in zip(c, x)), default=0.0) if same else np.inf
else:
    if FIELD == "qM":
        c = np.zeros((m.nv, m.nv)); x = np.asarray(mjx.full_m(mx, dx))  # mj_fullM: (m, d, dst) from MuJoCo 3.4
        mujoco.mj_fullM(m, c, d.qM) if hasattr(d, "qM") else mujoco.mj_fullM(m, d, c)
    else:
        c, x = np.ravel(getattr(d, FIELD)), np.ravel(np.asarray(getattr(dx, FIELD)))
    print(f"C   {{FIELD}}:", c); print(f"MJX {{FIELD}}:", x); print("difference:", x - c)
    err = float(np.max(np.abs(x - c)) / (1 + np.max(np.abs(c))))
print(f"scaled difference {{err:.3g}} (differs above {{RTOL:g}})")
raise SystemExit(1 if err > RTOL else 0)
'''  # noqa: E501 - the script's own lines (a standalone file, not this module's code)


#: What each check of a signature runs, for the README.
CHECKS = {"forward": "one mj_forward", "step": "one mj_step",
          "transfer": "C's data after one mj_forward, through mjx.put_data and back through mjx.get_data,"}


def _rtol(sig: Signature) -> float:
    from mjxdiff.compare.diagnose import STAGE_RTOL

    if sig.check == "step":
        return STEP_RTOL
    return 1e3 * STAGE_RTOL["float64"] if sig.field == "contact" else STAGE_RTOL["float64"]


def magnitude(m: mujoco.MjModel, state: State, sig: Signature) -> dict[str, Any]:
    """The divergence's size at ``state`` against C's own rounding: C and MJX's scaled
    difference in the signature's field, and C against C from ``qpos`` and ``qvel`` moved by 4
    units in the last place (what rounding alone changes). Contacts: each engine's count."""
    from mjxdiff.compare import diagnose
    from mjxdiff.tools import shrink
    from mjxdiff.compare.noise import converge_solver

    m = copy.copy(m)
    converge_solver(m)
    d = state.data(m)
    if sig.check == "transfer":
        c, back = shrink.transfer_contacts(m, state)
        return dict(error=float(abs(c - back)), object=f"C {c} contacts, get_data {back}", rounding=0.0)
    if sig.check == "step":
        errors = shrink.step_errors(m, state)
        a, b = state.data(m), state.data(m)
        b.qpos[:] = b.qpos + 4 * np.spacing(b.qpos)
        b.qvel[:] = b.qvel + 4 * np.spacing(b.qvel)
        mujoco.mj_step(m, a)
        mujoco.mj_step(m, b)
        rounding = shrink.scaled_error(getattr(a, sig.field), getattr(b, sig.field))
        return dict(error=errors[sig.field], rounding=rounding)
    dd = diagnose.drill_down(m, d.qpos, d.qvel, d.act, d.ctrl, float(d.time))
    diff = next(f for f in dd.fields if f.field == sig.field)
    a, b = state.data(m), state.data(m)
    b.qpos[:] = b.qpos + 4 * np.spacing(b.qpos)
    b.qvel[:] = b.qvel + 4 * np.spacing(b.qvel)
    mujoco.mj_forward(m, a)
    mujoco.mj_forward(m, b)
    rounding = (0.0 if sig.field in ("contact", "qM")
                else shrink.scaled_error(getattr(a, sig.field), getattr(b, sig.field)))
    return dict(error=diff.error, object=diff.object, rounding=rounding)


def ablations(shrunk: Shrunk) -> list[dict[str, Any]]:
    """Each remaining element dropped alone and each option changed from its default reset, on
    the minimal model: whether the divergence stays, goes (``None``) or turns into another."""
    from mjxdiff.tools.shrink import KINDS, SINGULAR, changed_options, drop, element_names

    out = []
    m = shrunk.spec.compile()
    for kind in KINDS:
        for name in element_names(shrunk.spec, kind):
            candidate = drop(shrunk.spec, kind, [name], m, shrunk.state)
            out.append(dict(edit=f"drop {SINGULAR[kind]} '{name}'",
                            **_outcome(candidate, shrunk)))
    default = mujoco.MjSpec().option
    for o in changed_options(shrunk.spec):
        candidate = shrunk.spec.copy()
        setattr(candidate.option, o, getattr(default, o))
        out.append(dict(edit=f"option {o} to its default", **_outcome(candidate, shrunk)))
    return out


def _outcome(candidate: mujoco.MjSpec, shrunk: Shrunk) -> dict[str, Any]:
    try:
        sig = probe(candidate.compile(), shrunk.state)
    except Exception as e:  # noqa: BLE001 - the edit leaves no model both engines run
        return dict(result="no model", why=str(e).splitlines()[0][:120])
    if sig is None:
        return dict(result="removes it")
    return dict(result="keeps it" if sig == shrunk.signature else f"changes it: {sig.describe()}")


def _assets(spec: mujoco.MjSpec, source: Path | None, out: Path) -> None:
    """Copies the mesh and height-field files ``spec`` reads into ``out``, named as the
    bundle's model refers to them."""
    folder = (source / spec.meshdir) if source is not None else None
    for asset in [*spec.meshes, *spec.hfields]:
        if not asset.file:
            continue
        path = Path(asset.file)
        if not path.is_absolute() and folder is not None:
            path = folder / path
        shutil.copyfile(path, out / Path(asset.file).name)
        asset.file = Path(asset.file).name
    spec.meshdir = ""


def write_model(shrunk: Shrunk, out: str | Path, source: str | Path | None = None) -> mujoco.MjModel:
    """``model.xml`` (with the mesh files it reads) and ``state.json`` of ``shrunk`` in ``out``;
    returns the model as written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    spec = shrunk.spec.copy()
    _assets(spec, Path(source) if source is not None else None, out)
    atomic_write(out / "model.xml", spec.to_xml())
    m = mujoco.MjModel.from_xml_path(str(out / "model.xml"))
    d = shrunk.state.data(m)
    atomic_write(out / "state.json", json.dumps(dict(qpos=d.qpos.tolist(), qvel=d.qvel.tolist(), ctrl=d.ctrl.tolist(),
                                                     act=d.act.tolist(), time=float(d.time)), indent=1) + "\n")
    return m


def write(shrunk: Shrunk, out: str | Path, source: str | Path | None = None, origin: str = "") -> Path:
    """Writes the bundle of ``shrunk`` into the directory ``out`` (made if missing): see the
    module's docstring. ``source``: the directory the original model's relative asset paths
    start from; ``origin``: what was shrunk (a path or a name), for the README."""
    from mjxdiff.engine.digest import code_digest
    from mjxdiff.output import report

    out = Path(out)
    m = write_model(shrunk, out, source)
    sig = shrunk.signature
    title = f"MJX vs MuJoCo C: {sig.describe()}"
    atomic_write(out / "repro.py", SCRIPT.format(title=title, check=sig.check, field=sig.field, rtol=_rtol(sig)))
    size = magnitude(m, shrunk.state, sig)
    tried = ablations(shrunk)
    doc = dict(signature=dataclasses.asdict(sig), magnitude=size, before=dataclasses.asdict(shrunk.before),
               after=dataclasses.asdict(shrunk.after), candidates=shrunk.candidates, compiles=shrunk.compiles,
               seconds=round(shrunk.seconds, 1), complete=shrunk.complete, edits=list(shrunk.log), ablations=tried,
               versions=report.versions(), mjx_code_digest=code_digest(), origin=origin)
    atomic_write(out / "signature.json", json.dumps(doc, indent=1) + "\n")
    atomic_write(out / "README.md", _readme(doc, title))
    return out


def _readme(doc: dict[str, Any], title: str) -> str:
    sig, size = doc["signature"], doc["magnitude"]
    before, after = doc["before"], doc["after"]
    lines = [f"# {title}", "",
             f"Shrunk by `mjxdiff shrink` from {doc['origin'] or 'a model'}: "
             + ", ".join(f"{k} {before[k]} -> {after[k]}" for k in before) + ".", "",
             "Run it (only `mujoco` and `mujoco-mjx` needed): `python repro.py` prints both engines' values and "
             "exits 1 while they differ.", "",
             "## What differs", "",
             f"- check: {CHECKS[sig['check']]} from the state in state.json, both solvers converged (200 "
             "iterations, tolerance 1e-14)",
             f"- first differing stage: {sig['stage']}; field: `{sig['field']}`"
             + (f"; contacts: {sig['kinds']}" if sig["kinds"] else ""),
             f"- where: {size.get('object') or 'see repro.py'}",
             f"- magnitude: scaled difference {size['error']:.3g} (|MJX - C| / (1 + max|C|)); C against itself "
             f"from the state moved by 4 ulps: {size['rounding']:.3g}", "",
             "## Ablations on the minimal model", "",
             "| edit | result |", "|---|---|"]
    lines += [f"| {a['edit']} | {a['result']}{(' (' + a['why'] + ')') if a.get('why') else ''} |"
              for a in doc["ablations"]]
    lines += ["", "## Versions", "",
              ", ".join(f"{k} {v}" for k, v in doc["versions"].items())
              + f"; MJX code digest `{doc['mjx_code_digest'][:16]}`",
              "", f"Shrinking: {doc['candidates']} candidates, {doc['compiles']} XLA compiles, {doc['seconds']} s"
              + ("" if doc["complete"] else " (stopped early: the best so far)") + "."]
    return "\n".join(lines) + "\n"
