"""The catalogue of model extensions `identify.diagnose` tries: each entry is a real model
component with its own physical parameters (`flexdyn.nonlinear`, `identify.measurement`,
the chain's parts), switched on at a neutral value that reproduces the baseline exactly.

| name                 | component                                          | parameters (SI)                     |
| -------------------- | -------------------------------------------------- | ----------------------------------- |
| `coulomb_friction`   | smoothed dry friction of joint i                   | `joint<i>.coulomb` (N m)            |
| `quadratic_damping`  | aerodynamic drag on link i                         | `link<i>.drag` (kg/m^2)             |
| `missing_mode`       | one more assumed mode on flexible link i           | (structure; refits the baseline)    |
| `joint_elasticity`   | rigid joint i made elastic (rotor + spring)        | `joint<i>.stiffness`, `.rotor_inertia` |
| `sensor_delay`       | delay of an output channel                         | `sensor.<ch>.delay` (s)             |
| `sensor_gain_offset` | calibration error of an output channel             | `sensor.<ch>.gain`, `.offset`       |
| `sensor_highpass`    | AC-coupled channel (first-order high-pass)         | `sensor.<ch>.highpass` (Hz)         |
| `actuator_lag`       | first-order lag of joint i's applied torque        | `actuator<i>.lag` (s)               |
| `backlash`           | smoothed dead zone in elastic joint i's gear       | `joint<i>.backlash` (rad)           |
| `base_tilt`          | a horizontal-plane rig tilted: in-plane gravity    | `gravity[0]`, `gravity[1]` (m/s^2)  |
| `geometric_stiffening` | axial-load stiffness of flexible link i (spin, weight) | (structure; refits the baseline) |

`implausible(name, values, ...)` says when a candidate's fitted values are outside what
the component plausibly does on a working rig (a calibration error beyond 2x, a tilt of
more than 10 deg, dry friction above the torques that move the rig, a delay or lag longer
than a tenth of the log, an AC-coupling corner above the lowest mode, more air drag than
a flat plate as wide as the link is long): such a value is
usually standing in for an effect the catalogue lacks, as two sensor gains of 12 and 17
stood in for the missing geometric stiffening of a spinning link before the catalogue had
that entry, and a link drag of 0.75 kg/m^2 for the stiction of a simulated servo rig
(`tests/identify/test_servo_rig.py`). A candidate that passes the search's tests with such values is not named
(`Plausibility.judge`, on one rig and its logs).

`wider_starts(...)`: the starts a continuous candidate is fitted from again when its fit
never left its own.

A channel whose sensor declares its kind (`identify.measurement.KINDS`) is offered only the
sensor effects that kind can have (`kind_left_out` says which are not, and why):

| kind            | `sensor_delay` | `sensor_gain_offset` | `sensor_highpass` |
| --------------- | -------------- | -------------------- | ----------------- |
| `encoder`       | yes            | offset only          | no                |
| `potentiometer` | yes            | yes                  | no                |
| `strain_gauge`  | yes            | yes                  | yes               |
| `accelerometer` | yes            | yes                  | yes               |
| `optical`       | yes            | yes                  | no                |

`candidates(...)` lists the entries that apply to a rig and its logs (friction on every
joint, drag on every link, sensor effects on every recorded channel (those its kind can
have), actuator lag on
every driven joint, backlash on elastic joints, tilt on a rig without gravity, a
missing mode on flexible links, elasticity on driven rigid joints, geometric stiffening on
flexible links without it where the logs' motion or gravity would shift the first mode's
`omega_1^2` by more than 1 % (`identify.evidence.stiffening_checks`, the model check
that flags it), with starting values
scaled to the rig (several per parameter: the extension fits are multi-start).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

import flexdyn as fd
from flexdyn._checks import as_float_array

from .._data import channels as ch, measurement as meas
from .stiffness import aim_joint_mode

NAMES = (
    "coulomb_friction",
    "quadratic_damping",
    "missing_mode",
    "joint_elasticity",
    "sensor_delay",
    "sensor_gain_offset",
    "sensor_highpass",
    "actuator_lag",
    "backlash",
    "base_tilt",
    "geometric_stiffening",
)

DESCRIPTION = {
    "coulomb_friction": "dry (Coulomb) friction in the joint",
    "quadratic_damping": "aerodynamic (quadratic) drag on the link",
    "missing_mode": "one more assumed mode on the flexible link",
    "joint_elasticity": "an elastic joint (rotor inertia on a torsional spring) instead of a rigid one",
    "sensor_delay": "a delay in the sensor channel",
    "sensor_gain_offset": "a calibration (gain/offset) error of the sensor channel",
    "sensor_highpass": "an AC-coupled (high-passed) sensor channel",
    "actuator_lag": "a first-order lag between commanded and applied torque",
    "backlash": "backlash (a dead zone) in the joint's gear",
    "base_tilt": "a tilted base: gravity acts in the plane of a horizontal rig",
    "geometric_stiffening": "geometric stiffening of the flexible link (its axial load: spin, gravity)",
}

# Entries that can be applied again to their own result: from a model that gained a mode,
# the next search offers one more mode on the same link (a link may miss several).
REPEATABLE = ("missing_mode",)

# Structural entries whose model contains the model they extend as a limit, with what that
# limit is. Their fit can always get as close to the extended model's cost as it likes, so
# one that ends well above it stopped in a local minimum (its rejection is no evidence
# against the effect). `missing_mode` and `geometric_stiffening` have no such limit: the
# extra mode, or the axial-load stiffness, cannot be switched off by a parameter.
#
# On a rigid joint the elastic joint's soft starts (joint mode near 2x the link's) can end
# far above the rigid model. One more start with the joint mode at the logs' Nyquist
# frequency would reach the limit, but its fine integration grid makes the whole diagnosis
# about 3x slower, for a candidate rejected either way (docs/performance.md). So the fit
# keeps its soft starts, and `diagnose` notes a fit that ends above the limit
# (`diagnose._stuck_above_nested`).
NESTED_LIMIT = {
    "joint_elasticity": "an infinitely stiff spring, the rotor's inertia added to the hub's",
}


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One catalogue entry applied at one place of a rig.

    - `name`: the catalogue name (`NAMES`); `where`: the joint, link or channel.
    - `params`: its named parameters (chain or measurement), `log_scale` per parameter
      (positive parameters are fitted as logs), `starts`: starting values (SI), one tuple
      per start.
    - `structural`: it changes the model's coordinates (`missing_mode`,
      `joint_elasticity`), so it is fitted as a model of its own.
    - `members`: for two entries fitted together (`pair`), the two; else empty.
    """

    name: str
    where: str
    params: tuple[str, ...]
    log_scale: tuple[bool, ...]
    starts: tuple[tuple[float, ...], ...]
    structural: bool = False
    members: tuple = ()

    @property
    def label(self) -> str:
        return pair_label(m.label for m in self.members) if self.members else f"{self.name}:{self.where}"


def pair_label(labels) -> str:
    """The label of entries fitted together: their labels joined by ' + '."""
    return " + ".join(labels)


def pair(first: Candidate, first_values, second: Candidate) -> Candidate:
    """Two continuous entries fitted together: `first` starts from `first_values` (its own
    fit), `second` from each of its starts."""
    if first.structural or second.structural:
        raise ValueError(f"pair: {first.label} and {second.label} must both be continuous entries")
    first_values = tuple(float(v) for v in first_values)
    return Candidate(
        f"{first.name}+{second.name}",
        f"{first.where}+{second.where}",
        first.params + second.params,
        first.log_scale + second.log_scale,
        tuple(first_values + tuple(s) for s in second.starts),
        members=(first, second),
    )


# Plausible ranges (`implausible`): what a working rig's components do.
PLAUSIBLE_GAIN = (0.5, 2.0)  # a sensor reading within 2x of its calibration
MAX_TILT_DEG = 10.0  # a rig meant to be horizontal, levelled by eye
MAX_DELAY_FRACTION = 0.1  # a delay or lag at most a tenth of the shortest log
# Air drag per unit length of a link, `c = rho_air C_D w / 2` (kg/m^2; the quadratic drag
# force per length `c v |v|`, Hoerner, *Fluid-Dynamic Drag*, 1965, ch. 3): at most that of
# a flat plate broadside (C_D = 2) as wide as the link is long (w = L), in air at sea level
# (1.2 kg/m^3): `c <= AIR_DENSITY MAX_DRAG_COEFFICIENT L / 2 = 1.2 L`. Paper 000's 25 mm
# strip (C_D ~1.2) gives 0.018 kg/m^2, as fitted on the real pendulum.
AIR_DENSITY = 1.2  # kg/m^3
MAX_DRAG_COEFFICIENT = 2.0


def implausible(
    name: str,
    values: dict,
    *,
    torque_scale: float,
    log_duration: float,
    lowest_mode_hz: float | None,
    link_lengths: tuple[float, ...] = (),
) -> list[str]:
    """Sentences saying which fitted values of a named cause (`values`: parameter name ->
    SI value) are outside the plausible ranges above; empty when all are plausible.
    `torque_scale` (N m): `characteristic_torque` of the rig and the logs' peak torque
    (dry friction above it would hold the rig still; above the RMS torque it need not: a
    hub standing still between moves is what friction does);
    `log_duration` (s): the shortest log's; `lowest_mode_hz`: the baseline's lowest
    positive natural frequency (None if it has none); `link_lengths` (m): link i's is
    entry i - 1 (a link's air drag is judged only where its length is given)."""
    out = _implausible_values(
        name,
        values,
        torque_scale=torque_scale,
        log_duration=log_duration,
        lowest_mode_hz=lowest_mode_hz,
        link_lengths=link_lengths,
    )
    return out + [STANDING_IN] if out else out


#: what `implausible` adds after the values it names
STANDING_IN = "the value is probably standing in for an effect the catalogue lacks: read the model checks"


def _implausible_values(
    name: str,
    values: dict,
    *,
    torque_scale: float,
    log_duration: float,
    lowest_mode_hz: float | None,
    link_lengths: tuple[float, ...] = (),
) -> list[str]:
    """`implausible`'s sentences about the values, without the closing one."""
    out = []
    for n, v in values.items():
        v = float(v)
        field = n.rsplit(".", 1)[-1]
        if name == "sensor_gain_offset" and field == "gain" and not PLAUSIBLE_GAIN[0] <= v <= PLAUSIBLE_GAIN[1]:
            out.append(
                f"{n} = {v:.3g}: a calibration error beyond {PLAUSIBLE_GAIN[1]:g}x is unlikely on a working sensor"
            )
        elif name in ("sensor_delay", "actuator_lag") and v > MAX_DELAY_FRACTION * log_duration:
            out.append(
                f"{n} = {v:.3g} s: longer than {MAX_DELAY_FRACTION:g} of the shortest log ({log_duration:.3g} s)"
            )
        elif name == "coulomb_friction" and v > torque_scale:
            out.append(
                f"{n} = {v:.3g} N m: more than the torques that move the rig ({torque_scale:.3g} N m), "
                "which would hold it still"
            )
        elif name == "quadratic_damping" and field == "drag" and (limit := _max_drag(n, link_lengths)) < v:
            out.append(
                f"{n} = {v:.3g} kg/m^2: more air drag than a flat plate as wide as the link is long "
                f"({limit:.3g} kg/m^2)"
            )
        elif name == "sensor_highpass" and lowest_mode_hz is not None and v > lowest_mode_hz:
            out.append(
                f"{n} = {v:.3g} Hz: a corner above the lowest mode ({lowest_mode_hz:.3g} Hz) would remove most "
                "of the motion the sensor was chosen to record"
            )
    if name == "base_tilt":
        g = float(np.hypot(*[float(values.get(f"gravity[{i}]", 0.0)) for i in (0, 1)]))
        if g > 9.81:
            out.append(f"in-plane gravity {g:.3g} m/s^2: more than the whole of gravity, not a tilt")
        elif g > 9.81 * np.sin(np.radians(MAX_TILT_DEG)):
            out.append(
                f"a tilt of {np.degrees(np.arcsin(g / 9.81)):.3g} deg: more than {MAX_TILT_DEG:g} deg on a rig "
                "meant to be horizontal"
            )
    return out


def _max_drag(name: str, link_lengths: tuple[float, ...]) -> float:
    """The most air drag per unit length link `name` (`link<i>.drag`) can have (kg/m^2;
    `MAX_DRAG_COEFFICIENT` above); infinite where its length is not given."""
    i = int(name.split(".", 1)[0].removeprefix("link")) - 1
    if not 0 <= i < len(link_lengths):
        return float("inf")
    return 0.5 * AIR_DENSITY * MAX_DRAG_COEFFICIENT * float(link_lengths[i])


@dataclasses.dataclass(frozen=True)
class Plausibility:
    """What `implausible` judges a candidate's fitted values against on one rig and its
    logs: `torque_scale` (N m), `log_duration` (s, the shortest fit log's) and
    `lowest_mode_hz` (None without a mode), as `implausible` takes them."""

    torque_scale: float
    log_duration: float
    lowest_mode_hz: float | None
    link_lengths: tuple[float, ...] = ()  # m, link i's at i - 1 (air drag's bound)

    def judge(self, cand: Candidate, values: dict) -> list[str]:
        """`implausible` of candidate `cand` at its fitted `values` (parameter name -> SI
        value): a pair (`Candidate.members`) is implausible when either member's values
        are; the closing sentence is said once."""
        out = []
        for member in cand.members or (cand,):
            mine = {n: values[n] for n in member.params if n in values}
            out += _implausible_values(
                member.name,
                mine,
                torque_scale=self.torque_scale,
                log_duration=self.log_duration,
                lowest_mode_hz=self.lowest_mode_hz,
                link_lengths=self.link_lengths,
            )
        return out + [STANDING_IN] if out else out


#: `wider_starts`: how far beyond a candidate's own starts its second try goes
WIDER_ABOVE, WIDER_BELOW = 10.0, 100.0


def wider_starts(cand: Candidate, scale: dict) -> tuple[tuple[float, ...], ...]:
    """Two starts of `cand` spread wider than its own (`Candidate.starts`), for a fit that
    never left them: every log-scale parameter `WIDER_ABOVE` times above its largest start,
    then `WIDER_BELOW` times below its smallest; every signed one at `+WIDER_ABOVE` and
    `-WIDER_ABOVE` times its scale (its largest start's magnitude, or `scale[name]` where
    every start is 0: `signed_scale`)."""
    above, below = [], []
    for i, (n, log) in enumerate(zip(cand.params, cand.log_scale)):
        values = [float(s[i]) for s in cand.starts]
        if log:
            above.append(WIDER_ABOVE * max(values))
            below.append(min(values) / WIDER_BELOW)
        else:
            size = max(abs(v) for v in values) or float(scale[n])
            above.append(WIDER_ABOVE * size)
            below.append(-WIDER_ABOVE * size)
    return tuple(above), tuple(below)


#: `signed_scale` of a base tilt's in-plane gravity: a 0.5 deg tilt (the wider starts at
#: 10x it are a 5 deg tilt, inside `MAX_TILT_DEG`)
TILT_SCALE = 9.81 * float(np.sin(np.radians(0.5)))


def signed_scale(name: str, noise: dict) -> float:
    """The size of signed parameter `name` for `wider_starts` where its starts are all 0: a
    sensor offset's channel noise (`noise`: channel -> standard deviation, SI), a tilt's
    `TILT_SCALE` (m/s^2); 1 for anything else."""
    if name.startswith("gravity["):
        return TILT_SCALE
    if name.startswith("sensor.") and name.endswith(".offset"):
        return float(noise.get(name.split(".")[1], 1.0))
    return 1.0


def _none(x):
    return x is None


def set_field(chain: fd.Chain, getter, value) -> fd.Chain:
    """`chain` with a (possibly absent, None) field set to `value`."""
    return eqx.tree_at(getter, chain, as_float_array(value) if value is not None else None, is_leaf=_none)


def characteristic_torque(chain: fd.Chain, torque_rms: float) -> float:
    """A torque scale for starting values, N m: the RMS applied torque of the logs, or the
    gravity moment of the whole chain held horizontal."""
    g = float(np.linalg.norm(np.asarray(chain.gravity)))
    moment = 0.0
    if g > 0:
        x = 0.0
        for link, hub in zip(chain.links, chain.hubs):
            m = float(link.mass) if isinstance(link, fd.RigidLink) else float(link.rho * link.length)
            com = float(link.com) if isinstance(link, fd.RigidLink) else 0.5 * float(link.length)
            moment += float(hub.mass) * x + m * (x + com)
            x += float(link.length)
        moment += float(chain.payload.mass) * x
    return max(torque_rms, g * moment, 1e-6)


def superset(chain: fd.Chain, measurement: meas.Measurement, channels, driven_joints) -> tuple:
    """`(chain, measurement)` with every applicable continuous extension present at its
    neutral value (identical equations, now with the parameters to fit)."""
    for i, joint in enumerate(chain.joints):
        if joint.coulomb is None:
            chain = set_field(chain, lambda c, i=i: c.joints[i].coulomb, 0.0)
        if joint.elastic and joint.backlash is None:
            chain = set_field(chain, lambda c, i=i: c.joints[i].backlash, 0.0)
    for i, link in enumerate(chain.links):
        if link.drag is None:
            chain = set_field(chain, lambda c, i=i: c.links[i].drag, 0.0)
    for c in filter(ch.is_output, channels):  # (a closed loop's command has no sensor)
        s = measurement.sensors.get(c, meas.Sensor())
        for f in ("gain", "offset", "delay", "highpass"):
            if getattr(s, f) is None and f not in meas.lacks(s.kind):
                measurement = meas.with_effect(measurement, f"sensor.{c}.{f}")
    for j in driven_joints:
        if measurement.lag(j) is None:
            measurement = meas.with_effect(measurement, f"actuator{j + 1}.lag")
    return chain, measurement


def candidates(
    chain: fd.Chain,
    channels,
    driven_joints,
    *,
    torque_rms: float,
    rate_rms: float,
    sample_interval: float,
    channel_rms: dict,
    offsets_fitted: set,
    max_frequency_hz: float,
    stiffening_links=(),
    sensor_kinds=None,
) -> list[Candidate]:
    """The catalogue entries that apply to this rig and these logs, with starting values.
    `stiffening_links`: the flexible links (`"link<i>"`) whose model check is flagged
    (`identify.evidence.stiffening_checks`); `geometric_stiffening` is offered on those.
    `sensor_kinds`: channel -> its sensor's kind (`identify.measurement.kinds`); a channel
    is offered only the sensor effects its kind can have (`kind_left_out`)."""
    tau = characteristic_torque(chain, torque_rms)
    w = max(rate_rms, 1e-3)
    out = []
    for i, joint in enumerate(chain.joints):
        out.append(
            Candidate(
                "coulomb_friction",
                f"joint{i + 1}",
                (f"joint{i + 1}.coulomb",),
                (True,),
                ((1e-4 * tau,), (0.003 * tau,), (0.03 * tau,)),
            )
        )
    for i, link in enumerate(chain.links):
        length = float(link.length)
        # drag whose moment at the typical rate is ~1 % / 10 % of the torque scale
        c0 = 4.0 * tau / (w**2 * length**4)
        out.append(
            Candidate(
                "quadratic_damping",
                f"link{i + 1}",
                (f"link{i + 1}.drag",),
                (True,),
                ((1e-4 * c0,), (0.01 * c0,), (0.1 * c0,)),
            )
        )
    dt = max(sample_interval, 1e-4)
    for c in filter(ch.is_output, channels):
        out.extend(_sensor_candidates(c, dt, c in offsets_fitted, meas.lacks((sensor_kinds or {}).get(c))))
    for j in driven_joints:
        out.append(
            Candidate(
                "actuator_lag",
                f"joint{j + 1}",
                (f"actuator{j + 1}.lag",),
                (True,),
                ((0.01 * dt,), (0.5 * dt,), (5 * dt,)),
            )
        )
    for i, joint in enumerate(chain.joints):
        if joint.elastic:
            k = float(joint.stiffness)
            defl = max(tau / k, 1e-5)
            out.append(
                Candidate(
                    "backlash",
                    f"joint{i + 1}",
                    (f"joint{i + 1}.backlash",),
                    (True,),
                    ((0.01 * defl,), (0.3 * defl,), (2 * defl,)),
                )
            )
    if float(np.linalg.norm(np.asarray(chain.gravity))) == 0.0:
        out.append(Candidate("base_tilt", "base", ("gravity[0]", "gravity[1]"), (False, False), ((0.0, 0.0),)))
    for i, link in enumerate(chain.links):
        if link.n_modes > 0 and link.n_modes < fd.modes.MAX_MODES:
            out.append(Candidate("missing_mode", f"link{i + 1}", (), (), ((),), structural=True))
    for i, link in enumerate(chain.links):
        if link.n_modes > 0 and not link.geometric_stiffening and f"link{i + 1}" in stiffening_links:
            out.append(Candidate("geometric_stiffening", f"link{i + 1}", (), (), ((),), structural=True))
    for j in driven_joints:
        if not chain.joints[j].elastic:
            out.append(
                Candidate(
                    "joint_elasticity",
                    f"joint{j + 1}",
                    (f"joint{j + 1}.stiffness", f"joint{j + 1}.rotor_inertia"),
                    (True, True),
                    ((),),
                    structural=True,
                )
            )
    return out


#: the sensor entries and the `identify.measurement.Sensor` fields each fits
SENSOR_FIELDS = {"sensor_delay": ("delay",), "sensor_gain_offset": ("gain", "offset"), "sensor_highpass": ("highpass",)}


def _sensor_candidates(c: str, dt: float, offset_fitted: bool, lacks: dict) -> list[Candidate]:
    """The sensor entries on channel `c` (sample interval `dt`, s): all but the fields its
    kind `lacks`; the calibration without its offset where each log fits its own."""
    starts = {
        "delay": ((0.01 * dt,), (0.5 * dt,), (3.0 * dt,)),
        "highpass": ((0.005,), (0.1,), (1.0,)),
    }
    out = []
    for name, fields in SENSOR_FIELDS.items():
        fields = [f for f in fields if f not in lacks and not (f == "offset" and offset_fitted)]
        if not fields:
            continue
        params = tuple(f"sensor.{c}.{f}" for f in fields)
        log_scale = tuple(not meas.is_signed(p) for p in params)
        if name == "sensor_gain_offset":  # one start: the calibration as declared
            out.append(Candidate(name, c, params, log_scale, (tuple(meas.NEUTRAL[f] for f in fields),)))
        else:
            out.append(Candidate(name, c, params, log_scale, starts[fields[0]]))
    return out


def kind_left_out(channels, sensor_kinds: dict, offsets_fitted=frozenset()) -> dict:
    """The sensor entries (or parts of one) `candidates` leaves out because of a channel's
    sensor kind (`sensor_kinds`: channel -> kind): label (`sensor_highpass:theta1`) -> why
    (`identify.measurement.KINDS`), in channel order. An entry still tried in part (an
    encoder's offset) says which part is tried."""
    out = {}
    for c in filter(ch.is_output, channels):
        lacks = meas.lacks(sensor_kinds.get(c))
        for name, fields in SENSOR_FIELDS.items():
            missing = [f for f in fields if f in lacks]
            if not missing:
                continue
            why = "; ".join(lacks[f] for f in missing)
            rest = [f for f in fields if f not in missing]
            if rest and c in offsets_fitted and rest == ["offset"]:
                why += " (its offset is fitted per log already)"
            elif rest:
                why += f" (only its {' and '.join(rest)} is tried)"
            out[f"{name}:{c}"] = why
    return out


def not_applicable(chain: fd.Chain, driven_joints, stiffening_links=()) -> dict:
    """Why `candidates` offers a catalogue entry nowhere on this rig and these logs: entry
    name -> reason, for the entries it leaves out (the same conditions as `candidates`)."""
    elastic = [j for j in chain.joints if j.elastic]
    flexible = [link for link in chain.links if link.n_modes > 0]
    why = {}
    if not driven_joints:
        why["actuator_lag"] = "no joint is driven (no torque in the fit logs)"
    if not elastic:
        why["backlash"] = "no elastic joint (backlash is a dead band in an elastic joint's spring)"
    if float(np.linalg.norm(np.asarray(chain.gravity))) != 0.0:
        why["base_tilt"] = "the rig moves under gravity, whose direction the model sets (offered for horizontal rigs)"
    if not any(0 < link.n_modes < fd.modes.MAX_MODES for link in chain.links):
        why["missing_mode"] = (
            f"no flexible link with fewer than {fd.modes.MAX_MODES} modes" if flexible else "no flexible link"
        )
    if not any(
        link.n_modes > 0 and not link.geometric_stiffening and f"link{i + 1}" in stiffening_links
        for i, link in enumerate(chain.links)
    ):
        why["geometric_stiffening"] = (
            "no flexible link spins or hangs enough for the model check to flag it (evidence.stiffening_checks)"
            if flexible
            else "no flexible link"
        )
    if not any(not chain.joints[j].elastic for j in driven_joints):
        why["joint_elasticity"] = (
            "every driven joint is elastic in the model already"
            if driven_joints
            else "no joint is driven (an elastic joint is offered where a torque drives it)"
        )
    return why


def structural_model(
    chain: fd.Chain, cand: Candidate, *, max_frequency_hz: float, nyquist_hz: float | None = None
) -> tuple[fd.Chain, dict]:
    """The chain of a structural candidate and the guesses of its new parameters. With the
    logs' `nyquist_hz`, an elastic joint whose first guess rings above it with the link free
    is moved down to `max_frequency_hz` (`stiffness.aim_joint_mode`)."""
    index = int(cand.where.lstrip("linkjoint"))
    i = index - 1
    if cand.name == "missing_mode":
        link = chain.links[i]
        fields = {f: getattr(link, f) for f in ("length", "rho", "EI", "sqrt_stiffness_damping", "drag")}
        ratio = np.asarray(link.damping_ratio)
        new = fd.FlexibleLink(
            n_modes=link.n_modes + 1,
            damping_ratio=np.concatenate([ratio, ratio[-1:]]),
            geometric_stiffening=link.geometric_stiffening,
            **fields,
        )
        links = list(chain.links)
        links[i] = new
        return fd.Chain(links, chain.joints, chain.hubs, chain.payload, chain.gravity, chain.motors), {}
    if cand.name == "geometric_stiffening":
        # the same link with its axial-load stiffness (`flexdyn.FlexibleLink`'s option);
        # its parameters, EI included, are refitted from the baseline's values
        links = list(chain.links)
        links[i] = dataclasses.replace(chain.links[i], geometric_stiffening=True)
        return fd.Chain(links, chain.joints, chain.hubs, chain.payload, chain.gravity, chain.motors), {}
    if cand.name == "joint_elasticity":
        joint, hub = chain.joints[i], chain.hubs[i]
        # The motor's inertia (the hub's, if the rigid joint had no rotor) moves to the rotor
        # side of the spring; the spring's first guess puts the joint mode at
        # `max_frequency_hz` (diagnose: 2x the model's highest mode, at most Nyquist).
        rotor = float(joint.rotor_inertia) * float(joint.gear_ratio) ** 2 or 0.5 * float(hub.inertia) or 1e-5
        k = rotor * (2 * np.pi * max_frequency_hz) ** 2
        new = fd.ElasticJoint(
            stiffness=k,
            rotor_inertia=rotor,
            gear_ratio=1.0,
            damping=joint.damping,
            spong_approximation=joint.spong_approximation,
            coulomb=joint.coulomb,
            coulomb_velocity=joint.coulomb_velocity,
        )
        joints = list(chain.joints)
        joints[i] = new
        hubs = list(chain.hubs)
        if not float(joint.rotor_inertia):
            hubs[i] = fd.Hub(mass=hub.mass, inertia=float(hub.inertia) - rotor)
        elastic = fd.Chain(chain.links, joints, hubs, chain.payload, chain.gravity, chain.motors)
        if nyquist_hz is not None:
            elastic = aim_joint_mode(elastic, index, target_hz=min(max_frequency_hz, nyquist_hz), nyquist_hz=nyquist_hz)
            k = float(np.asarray(elastic.joints[i].stiffness))
        return elastic, {f"joint{index}.stiffness": k, f"joint{index}.rotor_inertia": rotor}
    raise ValueError(f"{cand.name} is not structural")
