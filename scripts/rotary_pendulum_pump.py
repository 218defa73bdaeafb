"""Can the rotary pendulum's motor lift its pole past horizontal at all? Open-loop inputs on the bare MJCF.

From hanging (pole at 3.1 rad, at rest), over 5 s, at full command (+-1, i.e. +-10 V): square waves of 1 to
2.5 Hz at 8 phases each, and a bang-bang pump u = sign(pole velocity x cos(pole angle)). Prints the pole's
closest approach to upright (rad, 0 = upright, pi/2 = horizontal) for the pole damping of the example's
MJCF and for the damping given with --damping (N m s), e.g.

    .venv/bin/python scripts/rotary_pendulum_pump.py --damping 0.0005 0.0003 0.00005
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import mujoco
import numpy as np

MJCF = Path(__file__).resolve().parents[1] / "examples" / "rotary_pendulum" / "rotary_pendulum.xml"
SECONDS = 5.0


def closest_to_upright(model: mujoco.MjModel, command, start: float = 3.1) -> float:
    """The smallest |pole angle| over SECONDS under command(t, data) -> u."""
    data = mujoco.MjData(model)
    data.qpos[:] = [0.0, start]
    best = np.pi
    for k in range(round(SECONDS / model.opt.timestep)):
        data.ctrl[0] = command(k * model.opt.timestep, data)
        mujoco.mj_step(model, data)
        best = min(best, abs(float(np.angle(np.exp(1j * data.qpos[1])))))
    return best


def report(model: mujoco.MjModel, label: str) -> None:
    square = min(
        closest_to_upright(model, lambda t, _d, f=f, p=p: 1.0 if np.sin(2 * np.pi * (f * t + p)) > 0 else -1.0)
        for f in np.linspace(1.0, 2.5, 31)
        for p in np.linspace(0.0, 1.0, 8, endpoint=False)
    )
    pump = closest_to_upright(model, lambda _t, d: float(np.sign(d.qvel[1] * np.cos(d.qpos[1]) + 1e-9)))
    print(f"{label}: closest to upright, square waves {square:.2f} rad, bang-bang pump {pump:.2f} rad")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--damping", type=float, nargs="*", default=[], help="other pole dampings to try (N m s)")
    args = parser.parse_args()
    text = MJCF.read_text()
    model = mujoco.MjModel.from_xml_string(text)
    report(model, f"the example (pole damping {model.dof_damping[1]:g} N m s)")
    for damping in args.damping:
        changed = re.sub(r'(<joint name="pole"[^>]*damping=")[^"]*"', rf'\g<1>{damping:g}"', text)
        report(mujoco.MjModel.from_xml_string(changed), f"pole damping {damping:g} N m s")


if __name__ == "__main__":
    main()
