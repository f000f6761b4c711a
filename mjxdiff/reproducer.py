"""Self-contained reproducers of failing scenario members, and their replay.

A reproducer is one JSON file holding everything needed to re-run one failing
batch member with nothing else installed but mjxdiff's dependencies: the
member's compiled model as base64 MJB (exact: scaled parameters and
``mj_setConst`` constants included), the original MJCF text for reading, the
initial state, the controls, the seed, tolerances, the configuration, the
versions, and the verdict it produced. ``python -m mjxdiff replay FILE`` runs
it again; both engines are deterministic on the CPU, so the replay prints the
same diagnosis every time.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from mjxdiff.inputs import BatchedInputs
from mjxdiff.scenario import ScenarioError, Tolerances

__all__ = ["FORMAT", "Reproducer", "save", "load", "member_inputs"]

FORMAT = "mjxdiff-reproducer/1"


@dataclasses.dataclass(frozen=True)
class Reproducer:
    """One failing member: its model, inputs, settings and the verdict it gave."""

    scenario: str
    member: int
    model: mujoco.MjModel
    model_xml: str
    inputs: BatchedInputs
    tolerances: Tolerances
    config: dict[str, Any]
    verdict: dict[str, Any]
    versions: dict[str, str]


def _model_to_b64(m: mujoco.MjModel) -> str:
    buf = np.zeros(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    return base64.b64encode(buf.tobytes()).decode()


def _model_from_b64(text: str) -> mujoco.MjModel:
    fd, path = tempfile.mkstemp(suffix=".mjb")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(base64.b64decode(text))
        return mujoco.MjModel.from_binary_path(path)
    finally:
        os.unlink(path)


def member_inputs(inputs: BatchedInputs, member: int) -> BatchedInputs:
    """A batch of one: ``member`` of ``inputs``, keeping its identity for seeded draws."""
    return inputs.take(slice(member, member + 1))


def save(path: str | Path, scenario: str, member: int, inputs: BatchedInputs, model_xml: str,
         tolerances: Tolerances, config: dict[str, Any], verdict: dict[str, Any], versions: dict[str, str]) -> Path:
    """Writes member ``member`` of ``inputs`` as a reproducer file."""
    one = member_inputs(inputs, member)
    doc = dict(
        format=FORMAT, scenario=scenario, member=member, member_id=int(one.ids[0]), seed=inputs.seed,
        energy=inputs.energy, steps=inputs.steps, config=config, tolerances=tolerances.as_dict(), versions=versions,
        verdict=verdict, model_mjb_base64=_model_to_b64(one.models[0]), model_xml=model_xml,
        factors={k: v[0].tolist() for k, v in one.factors.items()},
        qpos=one.qpos[0].tolist(), qvel=one.qvel[0].tolist(), act=one.act[0].tolist(), ctrl=one.ctrl[0].tolist(),
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")  # floats round-trip exactly through repr
    return path


def load(path: str | Path) -> Reproducer:
    """Reads a reproducer; :class:`ScenarioError` in one line if it is not one."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ScenarioError(f"{path}: reproducer file not found") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ScenarioError(f"{path}: not a reproducer (invalid JSON: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ScenarioError(f"{path}: not a reproducer (expected format {FORMAT!r})")
    m = _model_from_b64(doc["model_mjb_base64"])
    arr = lambda key: np.asarray(doc[key], dtype=np.float64)[None]
    ctrl = np.asarray(doc["ctrl"], dtype=np.float64).reshape(1, doc["steps"], m.nu)  # nu may be 0
    inputs = BatchedInputs(qpos=arr("qpos"), qvel=arr("qvel"), act=arr("act").reshape(1, m.na), ctrl=ctrl,
                           models=(m,), factors={k: np.asarray(v)[None] for k, v in doc["factors"].items()},
                           seed=doc["seed"], energy=doc["energy"], member_ids=np.array([doc["member_id"]]))
    return Reproducer(scenario=doc["scenario"], member=doc["member"], model=m, model_xml=doc["model_xml"],
                      inputs=inputs, tolerances=Tolerances(**doc["tolerances"]), config=doc["config"],
                      verdict=doc["verdict"], versions=doc["versions"])
