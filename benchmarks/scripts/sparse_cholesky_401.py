"""Makes ``tests/data/sparse_cholesky_401.json``: where MuJoCo C 4.0.0 (the reference pip gives MJX
users) and 4.0.1 part, on a model that meets mujoco issue 3767 (sparse Cholesky, fixed in 4.0.1).

A free-floating binary tree of 15 hinged capsules falls on a plane (``jacobian="sparse"``, Newton,
1 iteration). C 4.0.0 steps it 6 steps (both releases agree bit for bit up to there); the file
holds the model, that state (``mjSTATE_FULLPHYSICS``) with its warm start, and the qacc each
release's ``mj_forward`` computes from it. Usage, with 4.0.1 installed apart::

    pip download --no-deps mujoco-core==4.0.1 -d /tmp/w
    pip install --no-deps --target /tmp/core401 /tmp/w/mujoco_core-4.0.1-*.whl
    python benchmarks/scripts/sparse_cholesky_401.py tests/data/sparse_cholesky_401.json /tmp/core401
"""

import json
import os
import subprocess
import sys

import numpy as np


def tree(depth: int, branch: int, iterations: int) -> str:
    """A free base with a ``branch``-ary tree of hinged capsules ``depth`` levels deep, over a plane."""
    def body(d: int, name: str) -> str:
        if d == 0:
            return ""
        kids = "".join(body(d - 1, f"{name}{k}") for k in range(branch))
        return (f'<body name="b{name}" pos="0.1 0 -0.05"><joint type="hinge" axis="{int(d % 3 == 0)} '
                f'{int(d % 3 == 1)} {int(d % 3 == 2)}" damping="0.5"/>'
                f'<geom type="capsule" fromto="0 0 0 0.1 0 -0.05" size="0.02"/>{kids}</body>')
    return (f'<mujoco><option jacobian="sparse" solver="Newton" iterations="{iterations}"/><worldbody>'
            f'<geom type="plane" size="5 5 .1"/><body pos="0 0 0.3"><freejoint/><geom size="0.05"/>'
            f'{body(depth, "r")}</body></worldbody></mujoco>')


def qacc_at(xml: str, state: list[float], warmstart: list[float]) -> list[float]:
    """This process's C: qacc of ``mj_forward`` from ``state`` (full physics) and its warm start."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_setState(m, d, np.asarray(state), mujoco.mjtState.mjSTATE_FULLPHYSICS)
    d.qacc_warmstart[:] = warmstart
    mujoco.mj_forward(m, d)
    return d.qacc.tolist()


def main() -> None:
    import mujoco

    out, core401 = sys.argv[1], sys.argv[2]
    if len(sys.argv) > 3:  # the child, with 4.0.1 first on the path: its qacc from the saved state
        doc = json.loads(open(out).read())
        print(json.dumps(dict(version=mujoco.__version__, qacc=qacc_at(doc["xml"], doc["state"], doc["warmstart"]))))
        return
    xml = tree(4, 2, iterations=1)
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    d.qvel[:] = np.random.default_rng(0).normal(0, 0.3, m.nv)
    for _ in range(6):
        mujoco.mj_step(m, d)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    state = np.zeros(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, state, spec)
    doc = dict(xml=xml, steps=6, ncon=int(d.ncon), state=state.tolist(), warmstart=d.qacc_warmstart.tolist(),
               qacc={mujoco.__version__: qacc_at(xml, state.tolist(), d.qacc_warmstart.tolist())})
    with open(out, "w") as f:
        json.dump(doc, f)
    child = subprocess.run([sys.executable, __file__, out, core401, "child"], capture_output=True, text=True,
                           check=True, env=dict(os.environ, PYTHONPATH=core401))
    other = json.loads(child.stdout.strip().splitlines()[-1])
    doc["qacc"][other["version"]] = other["qacc"]
    with open(out, "w") as f:
        json.dump(doc, f)
    a, b = (np.asarray(v) for v in doc["qacc"].values())
    print(f"{out}: {' vs '.join(doc['qacc'])}: max |qacc| difference {np.abs(a - b).max():.6g} "
          f"(scale {np.abs(b).max():.6g}), {doc['ncon']} contacts")


if __name__ == "__main__":
    main()
