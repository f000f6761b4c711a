"""``mjxdiff versions``: the same sweep on several MJX releases, one table.

Each target (``3.9.0``, or ``3.9.0/0.7.2`` for MJX 3.9.0 with JAX 0.7.2; ``3.17.0+core4.0.1`` for
MJX 3.17.0 judged against MuJoCo C 4.0.1, the reference alone changed) gets an environment
of its own, a venv under ``~/.cache/mjxdiff/versions/`` (``--envs``) made with the standard library's ``venv`` and
filled by pip from the package index: MuJoCo and MJX of that release (MJX 3.17 is MuJoCo 4.0's),
JAX as pinned or as pip resolves within mjxdiff's range, and mjxdiff's other dependencies. The
mjxdiff running the command is linked in (a ``.pth`` file), so every environment tests the
same mjxdiff code. A venv is reused while it holds every requirement (extras included).

The sweep of each is ``mjxdiff sweep`` itself, in a subprocess of that venv, writing its own
``report.json`` under ``OUT/<target>/`` and appending to one history (``OUT/history``), so the
history, baseline and report machinery all apply. :func:`table` joins the reports: scenario x
version, each cell its status, worst ratio, first step and known label, marked where it
changed since the previous version. A target that cannot be installed or swept is one error
line; the others still run.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Any, Callable, Sequence

from mjxdiff import compat
from mjxdiff.output import report
from mjxdiff.errors import one_line
from mjxdiff.files import atomic_write

__all__ = ["Target", "parse_target", "requirements", "prepare", "run", "table", "format_table", "VersionsError"]

#: MuJoCo release of an MJX release where they differ: MJX 3.17 is MuJoCo 4.0's.
_MUJOCO_OF = {(3, 17): "4.0"}
_VERSION = re.compile(r"\d+\.\d+\.\d+")


class VersionsError(RuntimeError):
    """A target that could not be installed or swept (one line, with the log's path)."""


@dataclasses.dataclass(frozen=True)
class Target:
    """One MJX release to sweep, with the JAX to pair it with (None: pip's choice within
    mjxdiff's range) and the MuJoCo C to judge it against (``core``: ``mujoco-core`` of that
    release installed over the one ``mujoco`` pins, without its dependencies; None: the pinned one).
    MuJoCo 4.0's ``mujoco`` pins its ``mujoco-core`` exactly, so a patch release of C (4.0.1 fixes
    4.0.0's sparse Cholesky, :mod:`mjxdiff.compare.reference`) reaches MJX users only this way."""

    mjx: str
    jax: str | None = None
    core: str | None = None

    @property
    def mujoco(self) -> str:
        """The MuJoCo release this MJX belongs to (``3.9.0`` -> ``3.9.0``; ``3.17.0`` -> ``4.0.0``)."""
        major, minor, patch = (int(x) for x in self.mjx.split("."))
        base = _MUJOCO_OF.get((major, minor))
        return f"{base}.{patch}" if base else self.mjx

    @property
    def label(self) -> str:
        return ((self.mjx if self.jax is None else f"{self.mjx}/jax{self.jax}")
                + (f"+core{self.core}" if self.core else ""))


def parse_target(text: str) -> Target:
    """``3.9.0``, ``3.9.0/0.7.2`` (MJX, then JAX), either with ``+core4.0.1`` (the MuJoCo C to judge
    against); ValueError naming the form otherwise."""
    rest, plus, core = text.partition("+core")
    mjx, slash, jax = rest.partition("/")
    if (not _VERSION.fullmatch(mjx) or (slash and not _VERSION.fullmatch(jax))
            or (plus and not _VERSION.fullmatch(core))):
        raise ValueError(f"{text!r} is not MJX[/JAX][+coreC], e.g. 3.9.0, 3.9.0/0.7.2 or 3.17.0+core4.0.1")
    return Target(mjx, jax or None, core or None)


def requirements(target: Target, extras: Sequence[str] = ()) -> list[str]:
    """What pip installs for ``target``: MuJoCo and MJX of its release, JAX as pinned (or
    mjxdiff's range), and mjxdiff's other requirements (and those of ``extras``) as declared."""
    pinned = {"mujoco": f"mujoco=={target.mujoco}", "mujoco-mjx": f"mujoco-mjx=={target.mjx}"}
    if target.jax:
        pinned |= {"jax": f"jax[cpu]=={target.jax}", "jaxlib": f"jaxlib=={target.jax}"}
    out = list(pinned.values())
    for req in metadata.requires("mjxdiff") or []:
        name = re.match(r"[A-Za-z0-9_.-]+", req).group(0).lower()  # pyright: ignore[reportOptionalMemberAccess]
        spec, _, marker = req.partition(";")
        extra = re.search(r"extra\s*==\s*['\"]([^'\"]+)['\"]", marker)
        if name in pinned or (extra and extra.group(1) not in extras):
            continue
        out.append(spec.strip())
    return out


def core_requirement(target: Target) -> str:
    """The ``mujoco-core`` a C-only target installs over the pinned one (:attr:`Target.core`)."""
    return f"mujoco-core=={target.core}"


def _python(env: Path) -> Path:
    return env / "bin" / "python"


def _pip(env: Path, args: list[str], log: Path) -> None:
    with open(log, "a") as f:
        f.write(f"$ pip {' '.join(args)}\n")
        f.flush()
        done = subprocess.run([str(_python(env)), "-m", "pip", *args], stdout=f, stderr=subprocess.STDOUT)
    if done.returncode:
        tail = [line for line in log.read_text().splitlines() if line.strip() and "WARNING: Location" not in line]
        raise VersionsError(f"pip install failed ({tail[-1].strip() if tail else 'no output'}); log: {log}")


def prepare(target: Target, cache: Path, extras: Sequence[str] = (), say: Callable[[str], None] = print) -> Path:
    """The venv of ``target`` under ``cache``, made or reused; its directory.
    VersionsError in one line (with the log) when it cannot be made."""
    env = cache / re.sub(r"[^A-Za-z0-9._-]", "_", f"mjx-{target.label}")
    reqs = requirements(target, extras)
    stamped = reqs + ([f"{core_requirement(target)} --no-deps"] if target.core else [])
    stamp = env / "mjxdiff-requirements.json"
    if stamp.is_file() and set(stamped) <= set(json.loads(stamp.read_text())) and _python(env).exists():
        say(f"versions: {target.label}: reusing {env}")
    else:
        say(f"versions: {target.label}: installing MuJoCo {target.mujoco}, MJX {target.mjx}"
            f"{', JAX ' + target.jax if target.jax else ''}"
            f"{', MuJoCo C ' + target.core if target.core else ''} into {env}")
        env.mkdir(parents=True, exist_ok=True)
        log = env / "install.log"
        made = subprocess.run([sys.executable, "-m", "venv", "--clear", str(env)], capture_output=True, text=True)
        if made.returncode:
            raise VersionsError(f"venv failed: {' '.join((made.stderr or made.stdout).split())}")
        log.write_text("")
        _pip(env, ["install", "--disable-pip-version-check", "--quiet", *reqs], log)
        if target.core:  # over the pinned core: pip's resolver would refuse it beside `mujoco`
            _pip(env, ["install", "--disable-pip-version-check", "--quiet", "--no-deps", core_requirement(target)], log)
        atomic_write(stamp, json.dumps(stamped))
    _link(env)  # the mjxdiff running now, wherever it lives
    return env


def _link(env: Path) -> None:
    """Makes this process's mjxdiff package importable in ``env`` (a symlink and a .pth), and
    nothing else of this environment."""
    import mjxdiff

    src = env / "mjxdiff-source"
    src.mkdir(exist_ok=True)
    link = src / "mjxdiff"
    package = Path(mjxdiff.__file__).resolve().parent
    if link.is_symlink() and link.resolve() != package:
        link.unlink()
    if not link.exists():
        link.symlink_to(package, target_is_directory=True)
    site = subprocess.run([str(_python(env)), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    atomic_write(Path(site) / "mjxdiff-source.pth", f"{src}\n")


def sweep(env: Path, target: Target, sweep_args: Sequence[str], out: Path, say: Callable[[str], None] = print
          ) -> dict[str, Any]:
    """``mjxdiff sweep`` of ``sweep_args`` in ``env``; its report (``out/<label>/report.json``)."""
    from mjxdiff.input.scenario import bundled_dir

    where = out / re.sub(r"[^A-Za-z0-9._-]", "_", target.label)
    log = where / "sweep.log"
    where.mkdir(parents=True, exist_ok=True)
    cmd = [str(_python(env)), "-m", "mjxdiff", "sweep", *sweep_args, "--out", str(where),
           "--history", str(out / "history"), "--allow-untested-versions"]
    scenarios = bundled_dir()
    child = dict(os.environ, MJXDIFF_SCENARIOS=str(scenarios) if scenarios else "")
    say(f"versions: {target.label}: sweeping (log: {log})")
    t0 = time.perf_counter()
    with open(log, "w") as f:
        done = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=child)
    doc_path = where / "report.json"
    if done.returncode not in (0, 1) or not doc_path.is_file():
        lines = [x for x in log.read_text().splitlines() if x.strip()]
        raise VersionsError(f"sweep exited {done.returncode} ({lines[-1].strip() if lines else 'no output'}); "
                            f"log: {log}")
    say(f"versions: {target.label}: swept in {time.perf_counter() - t0:.0f} s")
    return json.loads(doc_path.read_text())


@dataclasses.dataclass(frozen=True)
class Cell:
    """One scenario on one version: status, worst ratio to its bound (None: nothing judged),
    first step out (-1: none), known label (``""``: none), and whether any of those but the
    ratio changed since the previous version."""

    status: str
    ratio: float | None
    first_step: int
    known: str
    changed: bool = False


def _cell(s: dict[str, Any]) -> Cell:
    ratios = [f.get("ratio") for f in (s.get("fields") or {}).values()]
    ratios = [r for r in ratios if isinstance(r, (int, float))]
    first = (s.get("first_divergence") or {}).get("step", -1)
    return Cell(s["status"], max(ratios) if ratios else None, int(first), (s.get("known") or {}).get("id", ""))


def table(results: Sequence[tuple[Target, dict[str, Any] | str]]) -> dict[str, Any]:
    """Scenario x version from each target's report (or its one-line error): ``versions``
    (labels), ``errors`` (label -> line), ``rows`` (scenario -> label -> :class:`Cell` as a
    dict; a cell is ``changed`` where its status, first step or known label differs from the
    previous version that has the scenario)."""
    labels = [t.label for t, _ in results]
    errors = {t.label: r for t, r in results if isinstance(r, str)}
    names: list[str] = []
    cells: dict[str, dict[str, Cell]] = {}
    for t, r in results:
        if isinstance(r, str):
            continue
        for s in r.get("scenarios", []):
            if s["name"] not in cells:
                names.append(s["name"])
                cells[s["name"]] = {}
            cells[s["name"]][t.label] = _cell(s)
    rows = {}
    for name in names:
        row, before = {}, None
        for label in labels:
            c = cells[name].get(label)
            if c is None:
                continue
            key = (c.status, c.first_step, c.known)
            row[label] = dataclasses.asdict(dataclasses.replace(c, changed=before is not None and key != before))
            before = key
        rows[name] = row
    return dict(versions=labels, errors=errors, rows=rows)


def format_table(t: dict[str, Any]) -> str:
    """The table as text: one row per scenario, one column per version; ``*`` marks a cell that
    changed since the previous version."""
    labels = t["versions"]
    width = max([len(n) for n in t["rows"]] + [8])

    def cell(c: dict[str, Any] | None) -> str:
        if c is None:
            return "-"
        ratio = f" {c['ratio']:.2g}" if c["ratio"] is not None else ""
        step = f" @{c['first_step']}" if c["first_step"] >= 0 else ""
        known = f" [{c['known']}]" if c["known"] else ""
        return f"{'*' if c['changed'] else ''}{c['status']}{ratio}{step}{known}"

    body = [[cell(row.get(label)) for label in labels] for row in t["rows"].values()]
    widths = [max([len(label)] + [len(r[i]) for r in body]) for i, label in enumerate(labels)]
    lines = ["scenario".ljust(width) + "  " + "  ".join(label.ljust(w) for label, w in zip(labels, widths))]
    for name, r in zip(t["rows"], body):
        lines.append(name.ljust(width) + "  " + "  ".join(x.ljust(w) for x, w in zip(r, widths)))
    lines += [f"{label}: ERROR {line}" for label, line in t["errors"].items()]
    lines.append("cells: status, worst ratio to the bound, @first step out, [known divergence]; "
                 "* changed since the previous version")
    return "\n".join(line.rstrip() for line in lines)


def run(targets: Sequence[Target], sweep_args: Sequence[str], out: Path, cache: Path,
        extras: Sequence[str] = (), say: Callable[[str], None] = print) -> dict[str, Any]:
    """Every target installed and swept in turn (an error is that target's line); the
    ``versions`` JSON output (the envelope, then the table and each target's requirements),
    written to ``out/versions.json``."""
    results: list[tuple[Target, dict[str, Any] | str]] = []
    for target in targets:
        try:
            env = prepare(target, cache, extras, say)
            results.append((target, sweep(env, target, sweep_args, out, say)))
        except VersionsError as e:
            say(f"versions: {target.label}: {e}")
            results.append((target, str(e)))
        except (OSError, subprocess.SubprocessError, json.JSONDecodeError) as e:
            say(f"versions: {target.label}: {one_line(e)}")
            results.append((target, one_line(e)))
    t = table(results)
    supported = {}
    for target, _ in results:
        try:
            jax = target.jax or compat.REFERENCE["jax"]
            compat.check_versions({"mujoco": target.mujoco, "mujoco-mjx": target.mjx, "jax": jax})
            supported[target.label] = True
        except compat.UntestedVersions:
            supported[target.label] = False
    doc = report.envelope("versions", dict(targets=[t.label for t, _ in results], sweep=list(sweep_args)),
                          table=t, supported=supported,
                          installed={t.label: (r.get("versions") if isinstance(r, dict) else None) for t, r in results})
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "versions.json", json.dumps(doc, indent=2) + "\n")
    return doc
