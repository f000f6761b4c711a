"""MJX vs MuJoCo C: mjx.get_data(mjx.put_data(C's data)) differs from C's data: contact. Needs only mujoco and mujoco-mjx: python repro.py (exit 1 while they differ)."""
import json, pathlib
import jax
jax.config.update("jax_enable_x64", True)
import mujoco, numpy as np
from mujoco import mjx

HERE, CHECK, FIELD, RTOL = pathlib.Path(__file__).parent, "transfer", "contact", 1.0000000000000002e-06
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
if FIELD == "contact":  # active contacts by geom pair: C's, and MJX's with dist below the margin
    cx = getattr(dx, "_impl", dx).contact
    on = np.asarray(cx.dist) < np.asarray(cx.includemargin)
    c = sorted((tuple(sorted(g)), float(x)) for g, x in zip(d.contact.geom[:d.ncon].tolist(), d.contact.dist[:d.ncon]))
    x = sorted((tuple(sorted(g)), float(y)) for g, y in zip(np.asarray(cx.geom)[on].tolist(), np.asarray(cx.dist)[on]))
    print("C   contacts (geom pair, dist):", c); print("MJX contacts (geom pair, dist):", x)
    same = [p for p, _ in c] == [p for p, _ in x]
    err = max((abs(a[1] - b[1]) for a, b in zip(c, x)), default=0.0) if same else float("inf")
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
