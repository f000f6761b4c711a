"""MJX vs MuJoCo C: one mj_step differs first at integration: qpos. Needs only mujoco and mujoco-mjx: python repro.py (exit 1 while they differ)."""
import json, pathlib
import jax
jax.config.update("jax_enable_x64", True)
import mujoco, numpy as np
from mujoco import mjx

HERE, CHECK, FIELD, RTOL = pathlib.Path(__file__).parent, "step", "qpos", 1e-06
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
    print(f"C   {FIELD}:", c); print(f"MJX {FIELD}:", x); print("difference:", x - c)
    err = float(np.max(np.abs(x - c)) / (1 + np.max(np.abs(c))))
print(f"scaled difference {err:.3g} (differs above {RTOL:g})")
raise SystemExit(1 if err > RTOL else 0)
