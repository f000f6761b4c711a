"""Fetch public MJX-ready robot models (MuJoCo Menagerie, MuJoCo Playground) for sweeps.

The meshes are tens of MB per robot, so they stay out of this repository: this
script puts them under a destination directory (default ~/.cache/mjxdiff/robots),
one folder per robot, from pinned commits of the public repositories:

    python benchmarks/scripts/fetch_robots.py [DEST] [--robots go2,panda,...]

Sources, tried in this order:
  * ``--from-mirror GITDIR`` (menagerie) and ``--playground-mirror GITDIR``: export
    from an existing local git directory (bare or not) that holds the pinned
    commit; no network.  A mirror may lack some blobs (e.g. a snapshot without
    files of 4 MiB or more): they are listed, and the robots that need them
    fail to load and are reported as not ready.
  * ``git``: ``git clone --filter=blob:none --sparse`` + ``git sparse-checkout set
    <dirs>`` + checkout of the pinned commit, so only the chosen directories'
    blobs are downloaded.
  * no git: the GitHub tarball of the pinned commit, streamed, keeping only the
    chosen directories.

Layout.  A menagerie robot is its menagerie directory copied to DEST/<robot>/
(so DEST/go2/scene_mjx.xml).  A playground robot is the playground ``xmls``
directory copied to DEST/<robot>/ plus the menagerie directory whose meshes it
uses, at DEST/<robot>/mujoco_menagerie/<dir>/; the playground XML files point
at menagerie with paths like ``../../../../../mujoco_menagerie/`` or
``../../../../external_deps/mujoco_menagerie/`` (playground loads them from an
asset dict, not from disk), and those prefixes are rewritten to
``mujoco_menagerie/`` so that ``mujoco.MjModel.from_xml_path`` works.

Output: one line per robot (name, kind, status, scene path) and DEST/robots.json
(the same plus source commits, missing blobs and, when mujoco is importable, the
load check: nq, nv, nu or the load error).  Exit status 1 if any chosen robot is
not ready.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import urllib.request
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Source:
    name: str
    url: str
    commit: str


MENAGERIE = Source("mujoco_menagerie", "https://github.com/google-deepmind/mujoco_menagerie",
                   "75df466bb0e39d8d7fa66b556513cfc676919924")  # main, 2026-03-18 (merge of PR #245)
PLAYGROUND = Source("mujoco_playground", "https://github.com/google-deepmind/mujoco_playground",
                    "d5e6b47531328468da1eec33b8b304a00bb0873c")  # main, 2026-08-06
# (playground itself pins menagerie 1b86ece5; between that commit and MENAGERIE.commit
#  the directories below differ only by the added toddlerbot_2xc and panda mjx_hand.xml)

_PG = "mujoco_playground/_src/"


@dataclass(frozen=True)
class Robot:
    name: str
    kind: str            # quadruped / humanoid / arm / hand
    menagerie_dir: str   # directory in mujoco_menagerie
    scene: str           # scene XML, relative to DEST/<name>/
    playground_dir: str = ""  # xmls directory in mujoco_playground ("" = menagerie model)


ROBOTS: tuple[Robot, ...] = (
    # MJX variants shipped in menagerie itself
    Robot("go2", "quadruped", "unitree_go2", "scene_mjx.xml"),
    Robot("anymal_c", "quadruped", "anybotics_anymal_c", "scene_mjx.xml"),
    Robot("barkour_vb", "quadruped", "google_barkour_vb", "scene_mjx.xml"),
    Robot("g1", "humanoid", "unitree_g1", "scene_mjx.xml"),
    Robot("toddlerbot_2xc", "humanoid", "toddlerbot_2xc", "scene_mjx.xml"),
    Robot("panda", "arm", "franka_emika_panda", "mjx_scene.xml"),
    # MJX variants from playground (locomotion / manipulation envs), meshes from menagerie
    Robot("go1", "quadruped", "unitree_go1", "scene_mjx_feetonly_flat_terrain.xml", _PG + "locomotion/go1/xmls"),
    Robot("h1", "humanoid", "unitree_h1", "scene_mjx_feetonly.xml", _PG + "locomotion/h1/xmls"),
    Robot("t1", "humanoid", "booster_t1", "scene_mjx_feetonly_flat_terrain.xml", _PG + "locomotion/t1/xmls"),
    Robot("leap_hand", "hand", "leap_hand", "scene_mjx_cube.xml", _PG + "manipulation/leap_hand/xmls"),
    # plain (not MJX-tuned) scenes, as a user brings them: full meshes, default solver settings
    Robot("anymal_c_plain", "quadruped", "anybotics_anymal_c", "scene.xml"),
    Robot("g1_plain", "humanoid", "unitree_g1", "scene.xml"),
    Robot("panda_plain", "arm", "franka_emika_panda", "scene.xml"),
    Robot("iiwa14_plain", "arm", "kuka_iiwa_14", "scene.xml"),
    Robot("ur5e_plain", "arm", "universal_robots_ur5e", "scene.xml"),
    Robot("shadow_hand_plain", "hand", "shadow_hand", "scene_right.xml"),
    Robot("spot_plain", "quadruped", "boston_dynamics_spot", "scene.xml"),
    Robot("leap_hand_plain", "hand", "leap_hand", "scene_right.xml"),
    Robot("fr3_plain", "arm", "franka_fr3", "scene.xml"),
    Robot("xarm7_plain", "arm", "ufactory_xarm7", "scene.xml"),
    Robot("aero_hand_plain", "hand", "tetheria_aero_hand_open", "scene_right.xml"),
)

_MENAGERIE_PREFIX = re.compile(r'(?<=")(?:\.\./)+(?:external_deps/)?mujoco_menagerie/')


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, check=True, **kw)


# ---- sources: each puts the repository paths `dirs` (at src.commit) under `root`, returns missing files

def _from_mirror(gitdir: str, src: Source, dirs: list[str], root: Path) -> list[str]:
    """Export from a local git directory with ls-tree + cat-file --batch (tolerates missing blobs)."""
    g = ["git", "--git-dir", gitdir]
    entries = []
    for d in dirs:
        out = _run(g + ["ls-tree", "-r", "-z", src.commit, "--", d], capture_output=True).stdout
        for rec in out.split(b"\0"):
            if rec:
                meta, path = rec.split(b"\t", 1)
                mode, kind, sha = meta.split()
                if kind == b"blob":
                    entries.append((sha.decode(), path.decode(), mode == b"100755"))
    missing = []
    proc = subprocess.Popen(g + ["cat-file", "--batch"], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    for sha, path, executable in entries:
        proc.stdin.write(sha.encode() + b"\n")
        proc.stdin.flush()
        header = proc.stdout.readline().split()
        if len(header) < 3 or header[1] != b"blob":
            missing.append(path)
            continue
        data = proc.stdout.read(int(header[2]))
        proc.stdout.read(1)  # trailing newline
        dest = root / path
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(data)
        if executable:
            dest.chmod(0o755)
    proc.stdin.close()
    proc.wait()
    return missing


def _from_git(src: Source, dirs: list[str], root: Path) -> list[str]:
    """Sparse, blob-less clone: downloads only the blobs under `dirs`."""
    _run(["git", "clone", "--quiet", "--filter=blob:none", "--sparse", "--no-checkout", src.url + ".git", str(root)])
    _run(["git", "-C", str(root), "sparse-checkout", "set", *dirs])
    if subprocess.run(["git", "-C", str(root), "checkout", "--quiet", "--detach", src.commit]).returncode:
        _run(["git", "-C", str(root), "fetch", "--quiet", "--filter=blob:none", "origin", src.commit])
        _run(["git", "-C", str(root), "checkout", "--quiet", "--detach", src.commit])
    return []


def _from_tarball(src: Source, dirs: list[str], root: Path) -> list[str]:
    """GitHub tarball of the commit, streamed; keeps only the members under `dirs`."""
    with urllib.request.urlopen(f"{src.url}/archive/{src.commit}.tar.gz") as resp, \
            tarfile.open(fileobj=resp, mode="r|gz") as tar:
        for m in tar:
            rel = m.name.split("/", 1)[1] if "/" in m.name else ""
            if not m.isfile() or ".." in rel.split("/") or not any(rel.startswith(d + "/") for d in dirs):
                continue
            dest = root / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            with tar.extractfile(m) as f:
                dest.write_bytes(f.read())
    return []


def _materialize(src: Source, dirs: list[str], root: Path, mirror: str | None) -> list[str]:
    if mirror:
        return _from_mirror(mirror, src, dirs, root)
    if shutil.which("git"):
        return _from_git(src, dirs, root)
    return _from_tarball(src, dirs, root)


# ---- per robot

def _copy_dir(src: Path, dst: Path) -> None:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(".git"), dirs_exist_ok=True)


def _assemble(robot: Robot, dest: Path, trees: dict[str, Path]) -> Path:
    out = dest / robot.name
    if out.exists():
        shutil.rmtree(out)
    if not robot.playground_dir:
        _copy_dir(trees[MENAGERIE.name] / robot.menagerie_dir, out)
    else:
        _copy_dir(trees[PLAYGROUND.name] / robot.playground_dir, out)
        _copy_dir(trees[MENAGERIE.name] / robot.menagerie_dir, out / "mujoco_menagerie" / robot.menagerie_dir)
        for xml in out.glob("*.xml"):
            text = xml.read_text()
            new = _MENAGERIE_PREFIX.sub("mujoco_menagerie/", text)
            if new != text:
                xml.write_text(new)
    return out / robot.scene


def _check(scene: Path) -> dict:
    try:
        import mujoco
    except ImportError:
        return {}
    try:
        m = mujoco.MjModel.from_xml_path(str(scene))
    except Exception as e:  # noqa: BLE001 - report any load failure
        return {"loads": False, "error": str(e).strip().splitlines()[0][:300]}
    return {"loads": True, "nq": m.nq, "nv": m.nv, "nu": m.nu}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dest", nargs="?", default=os.path.expanduser("~/.cache/mjxdiff/robots"))
    ap.add_argument("--robots", default="", help="comma-separated names (default: all): "
                    + ",".join(r.name for r in ROBOTS))
    ap.add_argument("--from-mirror", metavar="GITDIR", help="local git dir holding menagerie " + MENAGERIE.commit[:12])
    ap.add_argument("--playground-mirror", metavar="GITDIR",
                    help="local git dir holding playground " + PLAYGROUND.commit[:12])
    ap.add_argument("--list", action="store_true", help="print the robot table and exit")
    args = ap.parse_args(argv)

    by_name = {r.name: r for r in ROBOTS}
    names = [n for n in args.robots.split(",") if n] or list(by_name)
    unknown = [n for n in names if n not in by_name]
    if unknown:
        ap.error(f"unknown robot(s) {unknown}; known: {list(by_name)}")
    robots = [by_name[n] for n in names]
    if args.list:
        for r in robots:
            print(f"{r.name}\t{r.kind}\t{r.playground_dir or MENAGERIE.name + '/' + r.menagerie_dir}/{r.scene}")
        return 0

    dest = Path(args.dest).expanduser().resolve()
    dest.mkdir(parents=True, exist_ok=True)
    offline = bool(args.from_mirror)
    # playground robots need playground: skip them offline when no playground mirror is given
    skipped = {r.name for r in robots if r.playground_dir and offline and not args.playground_mirror}
    wanted = {MENAGERIE.name: sorted({r.menagerie_dir for r in robots if r.name not in skipped}),
              PLAYGROUND.name: sorted({r.playground_dir for r in robots if r.playground_dir and r.name not in skipped})}
    mirrors = {MENAGERIE.name: args.from_mirror, PLAYGROUND.name: args.playground_mirror}

    results, ok = [], True
    with tempfile.TemporaryDirectory(dir=dest, prefix=".fetch-") as tmp:
        trees, missing = {}, {}
        for src in (MENAGERIE, PLAYGROUND):
            if wanted[src.name]:
                trees[src.name] = Path(tmp) / src.name
                trees[src.name].mkdir()
                missing[src.name] = _materialize(src, wanted[src.name], trees[src.name], mirrors[src.name])
                for p in missing[src.name]:
                    print(f"warning: {src.name}@{src.commit[:12]}: blob missing from source: {p}", file=sys.stderr)
        for r in robots:
            rec = {"name": r.name, "kind": r.kind, "menagerie_dir": r.menagerie_dir,
                   "menagerie_commit": MENAGERIE.commit}
            if r.playground_dir:
                rec.update(playground_dir=r.playground_dir, playground_commit=PLAYGROUND.commit)
            if r.name in skipped:
                rec.update(status="skipped", reason="playground model: pass --playground-mirror (offline)")
            else:
                scene = _assemble(r, dest, trees)
                miss = [p for p in missing.get(MENAGERIE.name, []) if p.startswith(r.menagerie_dir + "/")]
                miss += [p for p in missing.get(PLAYGROUND.name, [])
                         if r.playground_dir and p.startswith(r.playground_dir + "/")]
                rec.update(scene=str(scene), missing=miss, **_check(scene))
                ready = scene.exists() and rec.get("loads", not miss)
                rec["status"] = "ok" if ready else "not-ready"
            ok &= rec["status"] == "ok"
            results.append(rec)
            detail = (rec.get("scene", "") if rec["status"] == "ok"
                      else rec.get("error") or rec.get("reason") or rec.get("missing"))
            print(f"{r.name}\t{r.kind}\t{rec['status']}\t{detail}")
    (dest / "robots.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
