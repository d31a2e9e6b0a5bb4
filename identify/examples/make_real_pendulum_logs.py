"""Convert the measured free swings of Kaheman et al.'s single and double pendulum into the
logs and experiment files of `real_single_pendulum/` and `real_double_pendulum/`.

Source: `dynamicslab/MultiArm-Pendulum` (MIT licence), commit e99a7e13, the MATLAB files
`ParameterEstimation/{Single,Double}Pendulum/*DataForParameterEstimation.mat`, as CSV
(one file per rig, a `segment` column, 6 significant digits, 1 kHz). Run

    python identify/examples/make_real_pendulum_logs.py PATH/TO/multiarm-pendulum-dynamicslab

to rewrite `logs/*.csv`, `experiment.toml` (the authors' viscous model) and
`experiment_drag_friction.toml` (the dissipation law `identify diagnose` names: air drag
and dry friction) in both example folders (nothing else).

What is done to the data, and nothing more:

- one CSV per segment (`id<k>` -> role fit, `vad<k>` -> role validation);
- **decimated from 1 kHz to 200 Hz** by keeping every 5th sample of each segment, starting
  with its first (no filtering, no averaging: every value kept is the source's text,
  character for character). Reason: repository size (the 1 kHz files are 4.9 MB) and fit
  speed; the swings are below 3 Hz and the encoder angle is smooth at 200 Hz;
- the columns are renamed to our channel vocabulary with their units
  (`theta1_rad` -> `theta1 [rad]`; `phi1_rad` -> `phi1 [rad]` etc.; the authors' denoised
  velocities are kept as `dtheta1 [rad/s]` / `dphi<i> [rad/s]`, unused by the model but
  the source of each segment's initial rate);
- `t_s` is kept as it is (it runs on across segments; identify starts every log at its
  own first sample).
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
DECIMATE = 5  # 1 kHz -> 200 Hz

SOURCE_NOTE = (
    "# Kaheman, Fasel, Bramburger, Strom, Kutz, Brunton: The Experimental Multi-Arm Pendulum on a Cart,\n"
    "# arXiv:2205.06231 (2022). Data: github.com/dynamicslab/MultiArm-Pendulum (MIT licence, (c) 2022\n"
    "# dynamicslab), commit e99a7e13, {mat}, segment {seg}.\n"
    "# Every 5th sample of the 1 kHz source (200 Hz), values unchanged. Angles from upright\n"
    "# (hanging = pi); {angle_note}; d* columns: the authors' denoised velocities.\n"
)

SINGLE = {
    "folder": "real_single_pendulum",
    "csv": "single_pendulum_free_swing_segments.csv",
    "mat": "SinglePendulumDataForParameterEstimation.mat",
    "columns": {"t_s": "time [s]", "theta1_rad": "theta1 [rad]", "dtheta1_rad_s": "dtheta1 [rad/s]"},
    "angle_note": "theta1 is the encoder angle of the arm",
}
DOUBLE = {
    "folder": "real_double_pendulum",
    "csv": "double_pendulum_free_swing_segments.csv",
    "mat": "DoublePendulumDataForParameterEstimation.mat",
    "columns": {
        "t_s": "time [s]",
        "phi1_rad": "phi1 [rad]",
        "phi2_rad": "phi2 [rad]",
        "dphi1_rad_s": "dphi1 [rad/s]",
        "dphi2_rad_s": "dphi2 [rad/s]",
    },
    "angle_note": "phi1, phi2 are the ABSOLUTE angles of links 1 and 2",
}

SINGLE_HEAD = """\
# The real single compound pendulum of Kaheman et al. (arXiv:2205.06231), free swings
# recorded by its encoder; see README.md (data, licence, citation, what was fitted and why).
# Written by ../make_real_pendulum_logs.py.
#
#   identify fit identify/examples/real_single_pendulum/experiment.toml
#   identify diagnose identify/examples/real_single_pendulum/experiment.toml

[experiment]
name = "real single pendulum (Kaheman et al. 2022)"
description = "one compound pendulum arm on a clamped cart, 4 identification + 2 validation swings, encoder at 200 Hz"

[rig]
# The data measure angles from UPRIGHT (hanging = pi). Our angle is measured from the
# base x axis, so the base x axis points up and gravity acts along -x.
gravity = [-9.81, 0.0]

[[rig.links]]
type = "rigid"
length = 0.2955       # m; only the end point depends on it (not measured here)
mass = 0.14758        # kg, the authors' value: FIXED (a free swing cannot set the scale)
com = 0.14775         # m, the authors' value: FIXED, so m1*a1 is the authors'
inertia = 1.0e-3      # kg m^2 about the centre of mass; fitted (start: 10x the authors')

[[rig.joints]]
type = "rigid"
damping = 1.0e-3      # N m s/rad; fitted (start: 4x the authors')

# A free swing identifies only w0^2 = m1 a1 g / J1 and k1 / J1 (J1 = m1 a1^2 + I1, the
# inertia about the pivot): scaling m1 a1, J1 and k1 together changes nothing. m1 and a1
# are therefore fixed, and I1 (hence J1) and k1 are fitted relative to that m1 a1.
[parameters]
"link1.inertia" = { guess = 1.0e-3, lower = 1.0e-6, upper = 1.0e-1 }   # kg m^2
"joint1.damping" = { guess = 1.0e-3, lower = 1.0e-7, upper = 1.0e-1 }  # N m s/rad

[noise]
theta1 = "estimate"
"""

SINGLE_DRAG_FRICTION_HEAD = """\
# The real single compound pendulum of Kaheman et al. (arXiv:2205.06231) with the dissipation
# law `identify diagnose experiment.toml` names: air drag on the arm and dry friction in the
# pivot, in place of the authors' viscous damping. Same logs as experiment.toml; see
# README.md. Written by ../make_real_pendulum_logs.py.
#
#   identify fit identify/examples/real_single_pendulum/experiment_drag_friction.toml

[experiment]
name = "real single pendulum (Kaheman et al. 2022), air drag + dry friction"
description = "one compound pendulum arm on a clamped cart, 4 identification + 2 validation swings, encoder at 200 Hz"

[rig]
# Angles from UPRIGHT (hanging = pi): the base x axis points up, gravity along -x.
gravity = [-9.81, 0.0]

[[rig.links]]
type = "rigid"
length = 0.2955       # m; the drag acts along it (the arm's length is not measured: see README.md)
mass = 0.14758        # kg, the authors' value: FIXED (a free swing cannot set the scale)
com = 0.14775         # m, the authors' value: FIXED, so m1*a1 is the authors'
inertia = 1.0e-3      # kg m^2 about the centre of mass; fitted (start: 10x the authors')
drag = 1.0e-3         # kg/m^2, air drag per unit length, force -drag |v| v; fitted

[[rig.joints]]
type = "rigid"
damping = 0.0         # N m s/rad: no viscous term (fitted together with the two below it
                      # goes to its lower bound)
coulomb = 1.0e-4      # N m, dry friction, smoothed -coulomb tanh(rate / 0.01 rad/s); fitted

[parameters]
"link1.inertia" = { guess = 1.0e-3, lower = 1.0e-6, upper = 1.0e-1 }   # kg m^2
"joint1.coulomb" = { guess = 1.0e-4, lower = 1.0e-8, upper = 1.0e-1 }  # N m
"link1.drag" = { guess = 1.0e-3, lower = 1.0e-7, upper = 1.0 }         # kg/m^2

[noise]
theta1 = "estimate"
"""

DOUBLE_HEAD = """\
# The real double compound pendulum of Kaheman et al. (arXiv:2205.06231), free swings
# recorded by two encoders; see README.md (data, licence, citation, what was fitted and why).
# Written by ../make_real_pendulum_logs.py.
#
#   identify fit identify/examples/real_double_pendulum/experiment.toml
#   identify diagnose identify/examples/real_double_pendulum/experiment.toml

[experiment]
name = "real double pendulum (Kaheman et al. 2022)"
description = "two-arm compound pendulum on a clamped cart, 26 identification + 4 validation swings, 200 Hz"

[rig]
# Angles from UPRIGHT (hanging = pi): the base x axis points up, gravity along -x.
# The encoders give phi2, the ABSOLUTE angle of link 2: the logs map it to the channel
# phi2 (= theta1 + theta2 for our relative joint angles), phi1 = theta1.
gravity = [-9.81, 0.0]

[[rig.links]]
type = "rigid"
length = 0.15         # L1, m, pivot to joint 2; fitted
mass = 0.093844       # m1, kg, the authors' value: FIXED (only m1 a1 and I1 + m1 a1^2 matter)
com = 0.09            # a1, m; fitted
inertia = 3.0e-4      # I1, kg m^2 about the centre of mass; fitted

[[rig.links]]
type = "rigid"
length = 0.233558     # m; only the end point depends on it (not measured here)
mass = 0.137596       # m2, kg, the authors' value: FIXED
com = 0.116779        # a2, m, the authors' value: FIXED (sets the scale: m2 a2 is the authors')
inertia = 6.0e-4      # I2, kg m^2 about the centre of mass; fitted

[[rig.joints]]
type = "rigid"
damping = 1.0e-4      # k1, N m s/rad on phi1'; fitted

[[rig.joints]]
type = "rigid"
damping = 1.0e-4      # k2, N m s/rad on phi2' - phi1' (joint 2's relative rate); fitted

# The free double pendulum's equations depend on J1 = I1 + m1 a1^2 + m2 L1^2,
# J2 = I2 + m2 a2^2, c = m2 L1 a2, G1 = m1 a1 + m2 L1, G2 = m2 a2, k1, k2, and only up to
# one common scale factor. G2 = m2 a2 is fixed at the authors' value to set that scale,
# m1 too (it only trades against a1 and I1); the other five are fitted through
# L1 (c), a1 (G1), I1 (J1), I2 (J2), k1, k2.
[parameters]
"link1.length" = { guess = 0.15, lower = 0.05, upper = 0.4 }            # m
"link1.com" = { guess = 0.09, lower = 0.0, upper = 0.3 }                # m
"link1.inertia" = { guess = 3.0e-4, lower = 1.0e-6, upper = 1.0e-1 }    # kg m^2
"link2.inertia" = { guess = 6.0e-4, lower = 1.0e-6, upper = 1.0e-1 }    # kg m^2
"joint1.damping" = { guess = 1.0e-4, lower = 1.0e-7, upper = 1.0e-1 }   # N m s/rad
"joint2.damping" = { guess = 1.0e-4, lower = 1.0e-7, upper = 1.0e-1 }   # N m s/rad

[noise]
phi1 = "estimate"
phi2 = "estimate"
"""

DOUBLE_DRAG_FRICTION_HEAD = """\
# The real double compound pendulum of Kaheman et al. (arXiv:2205.06231), free swings
# recorded by two encoders, with the dissipation `identify diagnose experiment.toml` names:
# air drag on link 2 and dry friction in both joints, on top of viscous damping in joint 1
# (joint 2's goes to zero). Same logs as experiment.toml; see README.md. Written by
# ../make_real_pendulum_logs.py.
#
#   identify fit identify/examples/real_double_pendulum/experiment_drag_friction.toml

[experiment]
name = "real double pendulum (Kaheman et al. 2022), air drag + dry friction"
description = "two-arm compound pendulum on a clamped cart, 26 identification + 4 validation swings, 200 Hz"

[rig]
# Angles from UPRIGHT (hanging = pi): the base x axis points up, gravity along -x.
# The encoders give phi2, the ABSOLUTE angle of link 2: the logs map it to the channel
# phi2 (= theta1 + theta2 for our relative joint angles), phi1 = theta1.
gravity = [-9.81, 0.0]

[[rig.links]]
type = "rigid"
length = 0.15         # L1, m, pivot to joint 2; fitted
mass = 0.093844       # m1, kg, the authors' value: FIXED (only m1 a1 and I1 + m1 a1^2 matter)
com = 0.09            # a1, m; fitted
inertia = 3.0e-4      # I1, kg m^2 about the centre of mass; fitted

[[rig.links]]
type = "rigid"
length = 0.233558     # m; the drag acts along it (not measured: the drag per unit length
                      # fitted is relative to it)
mass = 0.137596       # m2, kg, the authors' value: FIXED
com = 0.116779        # a2, m, the authors' value: FIXED (sets the scale: m2 a2 is the authors')
inertia = 6.0e-4      # I2, kg m^2 about the centre of mass; fitted
drag = 1.0e-3         # kg/m^2, air drag per unit length, force -drag |v| v; fitted

[[rig.joints]]
type = "rigid"
damping = 1.0e-4      # k1, N m s/rad on phi1'; fitted
coulomb = 1.0e-5      # N m, dry friction, smoothed -coulomb tanh(rate / 0.01 rad/s); fitted

[[rig.joints]]
type = "rigid"
damping = 0.0         # N m s/rad: no viscous term in joint 2 (fitted together with the
                      # friction it goes to its lower bound)
coulomb = 1.0e-5      # N m, dry friction on the relative rate phi2' - phi1'; fitted

# The free double pendulum's equations depend on J1 = I1 + m1 a1^2 + m2 L1^2,
# J2 = I2 + m2 a2^2, c = m2 L1 a2, G1 = m1 a1 + m2 L1, G2 = m2 a2, k1, k2, and only up to
# one common scale factor. G2 = m2 a2 is fixed at the authors' value to set that scale,
# m1 too (it only trades against a1 and I1); the other five are fitted through
# L1 (c), a1 (G1), I1 (J1), I2 (J2), k1, k2.
[parameters]
"link1.length" = { guess = 0.15, lower = 0.05, upper = 0.4 }            # m
"link1.com" = { guess = 0.09, lower = 0.0, upper = 0.3 }                # m
"link1.inertia" = { guess = 3.0e-4, lower = 1.0e-6, upper = 1.0e-1 }    # kg m^2
"link2.inertia" = { guess = 6.0e-4, lower = 1.0e-6, upper = 1.0e-1 }    # kg m^2
"joint1.damping" = { guess = 1.0e-4, lower = 1.0e-7, upper = 1.0e-1 }   # N m s/rad
"link2.drag" = { guess = 1.0e-3, lower = 1.0e-7, upper = 1.0 }          # kg/m^2
"joint1.coulomb" = { guess = 1.0e-5, lower = 1.0e-8, upper = 1.0e-1 }   # N m
"joint2.coulomb" = { guess = 1.0e-5, lower = 1.0e-8, upper = 1.0e-1 }   # N m

[noise]
phi1 = "estimate"
phi2 = "estimate"
"""


def _segments(path: Path) -> dict[str, list[list[str]]]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    header, body = rows[0], rows[1:]
    out: dict[str, list[list[str]]] = {}
    for row in body:
        out.setdefault(row[0], []).append(row)
    return {"header": [header], **out}


def _write(spec: dict, source: Path) -> list[dict]:
    segs = _segments(source / spec["csv"])
    header = segs.pop("header")[0]
    keep = [header.index(c) for c in spec["columns"]]
    folder = HERE / spec["folder"] / "logs"
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for seg, rows in segs.items():
        rows = rows[::DECIMATE]
        text = SOURCE_NOTE.format(mat=spec["mat"], seg=seg, angle_note=spec["angle_note"])
        text += ",".join(spec["columns"].values()) + "\n"
        text += "".join(",".join(r[k] for k in keep) + "\n" for r in rows)
        (folder / f"{seg}.csv").write_text(text)
        first = {c: rows[0][header.index(c)] for c in spec["columns"]}
        entries.append({"segment": seg, "first": first})
    return entries


def _single_logs(entries) -> str:
    out = []
    for e in entries:
        seg, f = e["segment"], e["first"]
        out.append(
            f'\n[[logs]]\nname = "{seg}"\nfile = "logs/{seg}.csv"\n'
            'columns = { time = "time [s]", theta1 = "theta1 [rad]" }\n'
            f'initial = {{ theta1 = "measured", theta1_rate = {f["dtheta1_rad_s"]} }}  # denoised rate, 1st sample\n'
            'fit_initial = ["theta1", "theta1_rate"]\noffsets = ["theta1"]\n'
            + ('role = "validation"\n' if seg.startswith("vad") else "")
        )
    return "".join(out)


def _double_logs(entries) -> str:
    out = []
    for e in entries:
        seg, f = e["segment"], e["first"]
        # theta2 = phi2 - phi1 (relative joint angle), from the first sample; printed with
        # 6 decimals, the precision of the source's differences
        theta2 = float(f["phi2_rad"]) - float(f["phi1_rad"])
        rate2 = float(f["dphi2_rad_s"]) - float(f["dphi1_rad_s"])
        out.append(
            f'\n[[logs]]\nname = "{seg}"\nfile = "logs/{seg}.csv"\n'
            'columns = { time = "time [s]", phi1 = "phi1 [rad]", phi2 = "phi2 [rad]" }\n'
            f"initial = {{ theta1 = {f['phi1_rad']}, theta2 = {theta2:.6f}, "
            f"theta1_rate = {f['dphi1_rad_s']}, theta2_rate = {rate2:.6f} }}\n"
            'fit_initial = ["theta1", "theta2", "theta1_rate", "theta2_rate"]\noffsets = ["phi1", "phi2"]\n'
            + ('role = "validation"\n' if seg.startswith("vad") else "")
        )
    return "".join(out)


def main(source: Path) -> None:
    single = _write(SINGLE, source)
    (HERE / SINGLE["folder"] / "experiment.toml").write_text(SINGLE_HEAD + _single_logs(single))
    (HERE / SINGLE["folder"] / "experiment_drag_friction.toml").write_text(
        SINGLE_DRAG_FRICTION_HEAD + _single_logs(single)
    )
    double = _write(DOUBLE, source)
    (HERE / DOUBLE["folder"] / "experiment.toml").write_text(DOUBLE_HEAD + _double_logs(double))
    (HERE / DOUBLE["folder"] / "experiment_drag_friction.toml").write_text(
        DOUBLE_DRAG_FRICTION_HEAD + _double_logs(double)
    )


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]))
