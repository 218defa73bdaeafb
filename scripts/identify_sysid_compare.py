"""mujoco.sysid (MuJoCo 3.17's toolbox) against npp_ros.identification on one recording, measured.

The recording is scripts/identify_robots.py's for the set's corner robot (mass x1.2, gear x0.8, damping x1.5, one
control step late, noise 1e-3 on the states read; the certified policy from rest plus the multisine excitation, 10 s).
mujoco.sysid is given what it can use: the pendulum's MJCF with joint position and velocity sensors added, the
three parameters as modifiers of the spec (the mass geom's mass, which scales the body's mass and inertia, the gear,
the damping), the commands shifted by the true delay (it has no integer delay of its own), and its default residual
(the whole recording simulated open loop from its first state) and optimizer, from the nominal model.

It needs mujoco.sysid's imports (plotly, tabulate, imageio), which the project does not install; for this
measurement only, e.g. ``pip install --target runs/sysid-deps plotly tabulate imageio`` (then remove the numpy that
pip puts there) and ``PYTHONPATH=runs/sysid-deps``:

    PYTHONPATH=runs/sysid-deps .venv/bin/python scripts/identify_sysid_compare.py --run RUN --out results/identification
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

import npp_ros
from npp_ros.deployment.robot_model import model_mjcf
from npp_ros.identification.excitation import multisine
from npp_ros.identification.fit import identify
from npp_ros.identification.recording import record_motion
from npp_ros.tasks.uncertainty import Robot

CORNER = Robot((("mass", "pole", 1.2), ("gear", "torque", 0.8), ("damping", "hinge", 1.5)), 1, 1e-3, 102)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="the certified pendulum_swingup run (uncertainty 1)")
    ap.add_argument("--out", type=Path, required=True, help="where sysid.json goes")
    args = ap.parse_args(argv)
    from mujoco import sysid  # the optional toolbox: its imports are this script's alone

    run = npp_ros.read_run(args.run)
    plant = run.task.make_plant(int(run.metadata.seed))
    excitation = multisine(plant, 10.0)
    recording = record_motion(plant, CORNER, run.policy.controller(), [math.pi, 0.0], excitation.steps,
                              excitation.apply)  # fmt: skip
    started = time.perf_counter()
    ours = identify(run.task, recording, run.robots)
    ours_seconds = time.perf_counter() - started

    spec = mujoco.MjSpec.from_string(model_mjcf(plant) or "")
    for kind, name in ((mujoco.mjtSensor.mjSENS_JOINTPOS, "pos"), (mujoco.mjtSensor.mjSENS_JOINTVEL, "vel")):
        spec.add_sensor(name=f"hinge_{name}", type=kind, objtype=mujoco.mjtObj.mjOBJ_JOINT, objname="hinge")
    model = spec.compile()

    def set_mass(s: mujoco.MjSpec, p: sysid.Parameter) -> None:
        s.geom("mass").mass = float(p.value[0])  # the body's only massive geom: its mass and inertia scale together

    def set_gear(s: mujoco.MjSpec, p: sysid.Parameter) -> None:
        s.actuator("torque").gear[0] = float(p.value[0])

    def set_damping(s: mujoco.MjSpec, p: sysid.Parameter) -> None:
        s.joint("hinge").damping[0] = float(p.value[0])

    params = sysid.ParameterDict()
    params.add(sysid.Parameter("mass", 1.0, 0.2, 5.0, modifier=set_mass))
    params.add(sysid.Parameter("gear", 1.0, 0.2, 5.0, modifier=set_gear))
    params.add(sysid.Parameter("damping", 0.1, 0.01, 1.0, modifier=set_damping))
    delay = CORNER.action_delay
    applied = np.vstack([np.zeros((delay, 1)), recording.commands[:-delay]])  # what the actuator applied
    data = mujoco.MjData(model)
    initial = sysid.create_initial_state(model, recording.states[0, :1], recording.states[0, 1:], data.act)
    control = sysid.TimeSeries(recording.times, applied)
    sensors = sysid.TimeSeries.from_names(recording.times, recording.states, model)
    sequences = sysid.ModelSequences("pendulum", spec, "corner", initial, control, sensors)
    residual = sysid.build_residual_fn(models_sequences=[sequences])
    started = time.perf_counter()
    fitted, result = sysid.optimize(initial_params=params, residual_fn=residual, optimizer="mujoco", verbose=False)
    sysid_seconds = time.perf_counter() - started
    mass, gear, damping = (float(fitted[k].value[0]) for k in ("mass", "gear", "damping"))
    residuals, _, _ = residual(fitted.as_vector(), fitted)
    _, intervals = sysid.calculate_intervals(residuals, result.jac)
    out = {
        "recording": {"robot": CORNER.describe(), "seconds": recording.seconds, "rows": len(recording)},
        "truth": {"gear/mass": 0.8 / 1.2, "damping/mass": 1.5 / 1.2},
        "npp_ros.identification": {
            "seconds": ours_seconds, "delay": ours.delay,
            "combinations": {c.label: [c.value, c.low, c.high] for c in ours.combinations},
        },
        "mujoco.sysid": {
            "seconds": sysid_seconds, "delay": f"given ({delay})",
            "gear/mass": gear / mass, "damping/mass": damping / 0.1 / mass,
            "fitted": {"mass": mass, "gear": gear, "damping": damping},
            "half_widths": {"mass": float(intervals[0]), "gear": float(intervals[1]), "damping": float(intervals[2])},
        },
    }  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sysid.json").write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
