"""The fitting problem: logs (`LogData`) and free parameters gathered into a `Problem`."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import flexdyn as fd
from flexdyn.inputs import check_hold

from .._data import channels as ch, measurement as meas, noise_floor as nf
from .._data.channels import state_names
from .._data.controller import Controller
from .._data.logs import PLAUSIBLE_RATE_HZ
from .._data.measurement import Measurement
from .._data.units import display_unit
from .closed_loop import FeedbackLaw, check_closed_loop, reference_array
from .parameters import Parameter


@dataclasses.dataclass(frozen=True)
class LogData:
    """One measured log, in SI units.

    - `t`: sample times, s, increasing (non-uniform spacing and gaps are fine).
    - `outputs`: channel name -> samples, e.g. `{'theta1': ..., 'tip1': ...}`.
    - `torque`: applied joint torques at `t`, shape (T, n_joints), N m, or None.
    - `initial`: known initial-state entries by name (`theta1`, `q1_1`, `theta1_rate`, ...);
      entries not given are 0.
    - `fit_initial`: initial-state entries to estimate for this log.
    - `offsets`: output channels whose constant sensor offset is estimated for this log.
    - `set`: known parameter values of this log that differ from the rig's, SI (a payload
      sweep: `{'payload.mass': 0.02}`); the rig's values elsewhere. A parameter set in any
      log cannot be a free one.
    - `hold`: how `torque` is read between samples: `"linear"` (the default: samples of a
      continuous signal) or `"zoh"` (held until the next sample: a digital controller's
      command), or one of them per joint (`flexdyn.SampledTorque.hold`). The wrong one
      displaces the input by half a sample, which a fitted lag or delay then absorbs.
    - `reference`: a closed-loop log's reference samples at `t`, by the channel they are
      the reference of (`{'theta1': ...}`, SI; `identify.Controller.references`).
    """

    t: np.ndarray
    outputs: dict
    torque: np.ndarray | None = None
    initial: dict = dataclasses.field(default_factory=dict)
    fit_initial: tuple = ()
    offsets: tuple = ()
    name: str = "log"
    set: dict = dataclasses.field(default_factory=dict)
    hold: str | tuple = "linear"
    reference: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def from_log(cls, log, n_joints: int, **entries) -> LogData:
        """The `LogData` of a loaded log (`identify.load_log`'s `Log`): times from its first
        sample, its output channels, its `torque<j>` columns as the torque of joint j (0
        for a joint without one; None when it has none), `entries` (`initial`,
        `fit_initial`, `offsets`, `name`) passed on."""
        try:
            torque = log.torque(n_joints)
        except ValueError as e:
            raise ValueError(f"LogData.from_log: {e}") from None
        entries.setdefault("name", log.name)
        if getattr(log, "references", None):
            entries.setdefault("reference", {c: np.asarray(v, float) for c, v in log.references.items()})
        return cls(
            t=np.asarray(log.t_relative, float),
            outputs={c: np.asarray(v, float) for c, v in log.outputs.items()},
            torque=torque,
            **entries,
        )


class _LogLabels:
    """The logs' names, carried as static data that compares equal whenever the number of
    logs agrees. They label results and enter no computation, so problems that differ
    only in their logs' names share compiled programs (a fit compiles in 10-30 s). Safe
    because no jitted function returns anything built from them."""

    __slots__ = ("names",)

    def __init__(self, names):
        self.names = tuple(names.names if isinstance(names, _LogLabels) else names)

    def __eq__(self, other):
        return isinstance(other, _LogLabels) and len(self.names) == len(other.names)

    def __hash__(self):
        return hash((_LogLabels, len(self.names)))

    def __repr__(self):
        return repr(self.names)


class Problem(eqx.Module):
    """A fitting problem: the base chain, the free parameters and all logs, padded to a
    common length (`valid` masks the padding)."""

    chain: fd.Chain
    measurement: Measurement  # sensors' calibration/dynamics and actuator lags (identify.measurement)
    lower: jax.Array  # natural coordinates (log for positive parameters); -inf/inf if none
    upper: jax.Array
    t: jax.Array  # (L, T)
    valid: jax.Array  # (L, T) bool
    measured: jax.Array  # (L, T, C)
    present: jax.Array  # (L, C) bool: log l records channel c
    sigma: jax.Array  # (C,)
    torque_t: jax.Array  # (L, T)
    torque_v: jax.Array  # (L, T, n_joints)
    y0_known: jax.Array  # (L, 2n)
    onset: jax.Array  # (L,) s, on each log's clock: where its input or motion starts (`log_onset`)
    log_set: jax.Array  # (L, K): each log's values of the parameters `log_set_names` (`LogData.set`)
    names: tuple[str, ...] = eqx.field(static=True)
    log_scale: tuple[bool, ...] = eqx.field(static=True)
    channels: tuple[str, ...] = eqx.field(static=True)
    y0_free: tuple[tuple[int, int], ...] = eqx.field(static=True)  # (log, state index)
    offset_free: tuple[tuple[int, int], ...] = eqx.field(static=True)  # (log, channel index)
    labels: _LogLabels = eqx.field(static=True, converter=_LogLabels)  # the logs' names: `log_names`
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    dt: float | None = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    # the channels whose noise level make_problem was given (`fit` keeps them by default)
    declared: tuple[str, ...] = eqx.field(static=True, default=())
    log_set_names: tuple[str, ...] = eqx.field(static=True, default=())
    # the per-log free parameters (`Parameter.per_log`): (name, the index in `names` of each
    # log's own one, in log order), ...
    per_log: tuple[tuple[str, tuple[int, ...]], ...] = eqx.field(static=True, default=())
    # how the torque samples are read between samples (`LogData.hold`, the same in every log)
    hold: str | tuple[str, ...] = eqx.field(static=True, default="linear")
    # the free parameters' guesses, SI (an array: a static field would compile a program
    # per guess), so that `fit(problem)` needs no parameter list
    guess: jax.Array | None = None
    # a closed-loop problem (`make_problem(controller=...)`): the rig's feedback law, and each
    # log's references `(L, T, F)` of the law's channels (0 where none); None: open loop
    loop: FeedbackLaw | None = None
    reference: jax.Array | None = None

    @property
    def log_names(self) -> tuple[str, ...]:
        return self.labels.names

    @property
    def parameters(self) -> list[Parameter]:
        """The free parameters as given to `make_problem`: names, guesses and bounds (SI;
        None for none)."""
        if self.guess is None:
            raise ValueError("this Problem was not made by make_problem: it holds no guesses; pass the parameters")
        if not self.names:
            return []

        def bound(natural, log):
            natural = float(natural)
            return None if not math.isfinite(natural) else (math.exp(natural) if log else natural)

        # (a stacked problem, `fit_independent`'s, holds one row per log: the same)
        guesses = np.asarray(self.guess).reshape(-1, len(self.names))[0]
        lower = np.asarray(self.lower).reshape(-1, len(self.names))[0]
        upper = np.asarray(self.upper).reshape(-1, len(self.names))[0]
        first = {index[0]: name for name, index in self.per_log}  # (a per-log one: once, as given)
        own = {i for _, index in self.per_log for i in index}
        return [
            Parameter(first.get(i, n), float(g), bound(lo, log), bound(hi, log), per_log=i in first)
            for i, (n, g, lo, hi, log) in enumerate(zip(self.names, guesses, lower, upper, self.log_scale))
            if i not in own or i in first
        ]

    def base_name(self, name: str) -> str:
        """The rig's parameter a free parameter is: `payload.mass` for the per-log
        `payload.mass[m20g]`, the name itself otherwise."""
        for base, index in self.per_log:
            if name in (self.names[i] for i in index):
                return base
        return name

    @property
    def shared_names(self) -> tuple[str, ...]:
        """The free parameters shared by all logs (all but the per-log ones)."""
        own = {i for _, index in self.per_log for i in index}
        return tuple(n for i, n in enumerate(self.names) if i not in own)


def _log_set(chain, measurement, logs, free: set, known: set) -> tuple[tuple[str, ...], np.ndarray]:
    """The parameters some log sets (`LogData.set`) and each log's values `(L, K)` (the
    rig's where a log does not set one), each log's checked as the rig would check it."""
    names = sorted({n for log in logs for n in log.set})
    for log in logs:
        for n in log.set:
            if n not in known:
                raise ValueError(
                    f"log {log.name!r}: set {n!r} is not a parameter{fd.params.did_you_mean(n, known)}; "
                    f"this chain has: {', '.join(sorted(known))}"
                )
            if n in free:
                raise ValueError(
                    f"log {log.name!r}: set {n!r} is also a free parameter; a known value per log and a fitted "
                    "one exclude each other (fit a value per log with Parameter(..., per_log=True), or every "
                    "parameter per log with fit_independent, or drop it from the parameters)"
                )
    base = [
        float(meas.get_parameter(measurement, n) if meas.is_measurement_parameter(n) else fd.get_parameter(chain, n))
        for n in names
    ]
    values = np.tile(np.asarray(base, float), (len(logs), 1)).reshape(len(logs), len(names))
    for l, log in enumerate(logs):
        for k, n in enumerate(names):
            if n in log.set:
                v = log.set[n]
                if isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer):
                    raise ValueError(f"log {log.name!r}: set {n!r} expected a number (SI), got {v!r}")
                values[l, k] = float(v)
        chain_values, sensor_values = meas.split_values(dict(zip(names, values[l])))
        try:  # the rig's own checks (a negative mass, a NaN)
            fd.with_parameters(chain, chain_values)
            meas.with_parameters(measurement, sensor_values)
        except ValueError as e:
            raise ValueError(f"log {log.name!r}: set: {e}") from None
    return tuple(names), values


def _check_log_data(log: LogData) -> None:
    """A `LogData` built in Python gets the checks the CSV loader makes, naming the log, the
    channel and the first bad sample (a NaN or a wrong length would otherwise surface as
    an unrelated error deep in the fit)."""
    if not isinstance(log, LogData):
        hint = (
            ": convert it with identify.LogData.from_log(log, n_joints, fit_initial=..., ...)"
            if hasattr(log, "t_relative")
            else ""
        )
        raise TypeError(f"make_problem: expected identify.LogData entries, got {type(log).__name__}{hint}")
    where = f"log {log.name!r}"
    t = np.asarray(log.t, dtype=float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"{where}: t expected a 1-D array of at least 2 sample times (s), got shape {t.shape}")
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{where}: t[{bad[0]}] is {t[bad[0]]}; expected finite sample times (s)")
    steps = np.flatnonzero(np.diff(t) <= 0)
    if steps.size:
        i = int(steps[0]) + 1
        raise ValueError(
            f"{where}: t must be strictly increasing; t[{i}] = {t[i]:.9g} s after t[{i - 1}] = {t[i - 1]:.9g} s"
        )
    if not log.outputs:
        raise ValueError(f"{where}: no output channels (outputs is empty)")
    rate = 1.0 / float(np.median(np.diff(t)))
    if rate < PLAUSIBLE_RATE_HZ[0]:
        warnings.warn(
            f"{where}: sampled at {rate:.3g} Hz over {t[-1] - t[0]:.4g} s, below any rig's log "
            f"({PLAUSIBLE_RATE_HZ[0]:g} Hz): are its times in milliseconds? (in seconds: t / 1000); a fit of it "
            "can run for hours",
            UserWarning,
            stacklevel=4,
        )
    series = [(f"outputs[{c!r}]", v, (t.size,)) for c, v in log.outputs.items()]
    if log.torque is not None:
        tq = np.asarray(log.torque, dtype=float)
        series.append(("torque", tq, f"({t.size},) or ({t.size}, n_joints)"))
    for label, values, shape in series:
        v = np.asarray(values, dtype=float)
        if v.shape[:1] != (t.size,) or v.ndim > (2 if label == "torque" else 1):
            raise ValueError(f"{where}: {label} has shape {v.shape}; expected {shape}, one row per sample time")
        bad = np.flatnonzero(~np.all(np.isfinite(v.reshape(t.size, -1)), axis=1))
        if bad.size:
            raise ValueError(
                f"{where}: {label} is not finite at sample {bad[0]} (t = {t[bad[0]]:.9g} s); "
                "drop or fill such samples before fitting"
            )


#: `make_problem` warns of a log whose every channel varies about its mean by less than
#: this many times its model-free noise floor (`identify.noise_floor`)
AT_REST = 3.0


def _warn_if_at_rest(log: LogData, measurement: Measurement) -> None:
    """Warn when a log shows no motion above its noise: on every channel the RMS about its
    mean is below `AT_REST` times the channel's model-free noise floor (white noise alone
    gives 1; at least the quantisation noise of a declared `Sensor.resolution`): such a
    log "converges" with intervals that come from the noise. A static test under a load
    does determine the static parameters (a mass times its centre's distance, from torque
    against angle), so this warns and does not refuse."""
    t = np.asarray(log.t, dtype=float)
    if t.size <= nf.ORDER + 1:
        return
    parts = []
    for c, v in log.outputs.items():
        y = np.asarray(v, dtype=float)
        spread = float(np.std(y))
        floor = max(nf.noise_floor(t, y), nf.quantisation_noise(meas.resolutions(measurement, (c,))[0]))
        if spread > AT_REST * floor:  # (a constant channel, all zeros included, is at rest)
            return
        scale, unit = display_unit(c)
        parts.append(f"{c} {scale * spread:.3g} {unit} RMS about its mean, noise floor {scale * floor:.3g} {unit}")
    driven = log.torque is not None and np.any(np.asarray(log.torque, dtype=float) != 0)
    warnings.warn(
        f"log {log.name!r} shows no motion above its noise ({'; '.join(parts)}): a log at rest carries no "
        "information about inertia, damping or stiffness, and the fit's intervals for them would come from the "
        "noise; check the log (the right file? the sensor connected?)"
        + ("; a static test under load determines only static parameters" if driven else ""),
        UserWarning,
        stacklevel=3,
    )


def check_same_parameters(problem: Problem, parameters, caller: str) -> None:
    """The free parameters passed to a fit must be the problem's, in its order: the
    guesses are read by position (another parameter's guess would be used, silently)."""
    given = tuple((p.name, bool(getattr(p, "per_log", False))) for p in parameters)
    expected = tuple((p.name, p.per_log) for p in problem.parameters) if problem.guess is not None else None
    if expected is None:
        expected = tuple((n, False) for n in problem.names)
    if given != expected:
        show = lambda pairs: [n + (" (per log)" if per else "") for n, per in pairs]  # noqa: E731
        raise ValueError(
            f"{caller}: parameters {show(given)} are not the problem's {show(expected)} (as given to "
            "make_problem, in that order)"
        )


def make_problem(
    chain: fd.Chain,
    parameters: Sequence[Parameter],
    logs: Sequence[LogData],
    noise: dict | None = None,
    *,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    dt: float | None = None,
    max_steps: int = 100_000,
    measurement: Measurement | None = None,
    controller: Controller | None = None,
) -> Problem:
    """Build a `Problem`. `noise` maps channels to their standard deviation (SI); channels
    not in it start at 1 % of the channel's measured RMS and are re-estimated by `fit`
    (by default only those: `fit(estimate_noise=True)` re-estimates the given ones too).

    `measurement` (`identify.measurement.Measurement`): sensor gains, offsets, delays,
    high-pass cut-offs and actuator lags between the model and the log; its parameters
    (`sensor.tip1.gain`, `actuator1.lag`, ...) can be free parameters like the chain's.

    `rtol`, `atol` (adaptive Tsit5) or `dt` (fixed-step RK4) set the simulation. The
    default tolerances are tight on purpose: an adaptive solver's step choices make the
    loss a slightly noisy function of the parameters, which stalls Levenberg-Marquardt
    near the optimum.

    `controller` (`identify.Controller`): every log ran under this feedback law; each is
    simulated closed loop (`identify/_model/closed_loop.py`) and its command column (the
    law's output, `controller.command`) becomes an output channel too, compared with the
    model's commands."""
    if not logs:
        raise ValueError("make_problem: expected at least one log")
    measurement = Measurement() if measurement is None else measurement
    chain_names = set(fd.parameter_names(chain))
    known = chain_names | set(meas.parameter_names(measurement))
    free = _free_parameters(chain, chain_names, known, parameters, logs)
    seen = set()
    for log in logs:
        if log.name in seen:
            raise ValueError(f"make_problem: two logs are named {log.name!r}; names label the results and must differ")
        seen.add(log.name)
        _check_log_data(log)
        _warn_if_at_rest(log, measurement)
    channels = sorted({c for log in logs for c in log.outputs})
    for c in channels:
        ch.check_channel(chain, c)
    log_set_names, log_set = _log_set(chain, measurement, logs, {p.name for p in parameters}, known)
    padded = _padded_logs(chain, logs, channels)
    loop, reference = None, None
    referenced = [log.name for log in logs if log.reference]
    if controller is None and referenced:
        raise ValueError(
            f"make_problem: log {referenced[0]!r} has a reference, but no controller was given to follow it; pass "
            "controller=identify.Controller(...) (the law the rig ran), or drop the reference"
        )
    if controller is not None:
        check_closed_loop(chain, measurement, controller, logs)
        padded, channels = _with_command(padded, channels, controller), [*channels, controller.command]
        loop = FeedbackLaw.of(controller, meas.resolutions(measurement, controller.channels))
        reference = jnp.asarray(reference_array(controller, logs, padded.t.shape[1]))
    noise = dict(noise or {})
    sigma = _noise_levels(chain, noise, channels, padded)
    onset = _onsets(logs, channels, noise, sigma, padded, meas.resolutions(measurement, channels))
    # each padded array dropped as soon as it is on the device: a 1 GB log's copies one at a time
    device = {}
    for field in ("measured", "torque_v", "t", "valid", "present", "y0_known"):
        device[field] = jax.device_put(getattr(padded, field)).block_until_ready()  # (one copy, made now)
        padded = padded._replace(**{field: None})
    return Problem(
        chain=chain,
        measurement=measurement,
        lower=jnp.asarray(free.lower),
        upper=jnp.asarray(free.upper),
        t=device["t"],
        valid=device["valid"],
        measured=device["measured"],
        present=device["present"],
        sigma=jnp.asarray(sigma),
        torque_t=device["t"],
        torque_v=device["torque_v"],
        y0_known=device["y0_known"],
        onset=jnp.asarray(onset, dtype=float),
        log_set=jnp.asarray(log_set),
        names=tuple(free.names),
        log_scale=tuple(free.log_scale),
        channels=tuple(channels),
        y0_free=tuple(padded.y0_free),
        offset_free=tuple(padded.offset_free),
        labels=tuple(log.name for log in logs),
        rtol=rtol,
        atol=atol,
        dt=dt,
        max_steps=max_steps,
        declared=tuple(c for c in channels if noise.get(c) is not None),
        log_set_names=log_set_names,
        per_log=tuple(free.per_log),
        hold=_common_hold(logs, chain.n_links),
        guess=jnp.asarray(_guesses_made(parameters, len(logs)), dtype=float),
        loop=loop,
        reference=reference,
    )


def _with_command(padded: _PaddedLogs, channels: list[str], controller: Controller) -> _PaddedLogs:
    """A closed-loop problem's logs with the command column (`controller.command`) as their
    last output channel: the law's output, which every log records."""
    command = padded.torque_v[:, :, controller.joint - 1]
    return padded._replace(
        measured=np.concatenate([padded.measured, command[:, :, None]], axis=2),
        present=np.concatenate([padded.present, np.ones((padded.present.shape[0], 1), bool)], axis=1),
    )


class _FreeParameters(NamedTuple):
    """`make_problem`'s free parameters, a per-log one once per log (`name[log]`): names,
    whether each is fitted in log space, its bounds in natural coordinates, and the
    per-log ones' `Problem.per_log` entries."""

    names: list[str]
    log_scale: list[bool]
    lower: list[float]
    upper: list[float]
    per_log: list[tuple[str, tuple[int, ...]]]


def _free_parameters(chain, chain_names: set, known: set, parameters, logs) -> _FreeParameters:
    """The free parameters checked (listed once, existing, guess inside bounds, positive
    where fitted in log space) and laid out in natural coordinates."""
    names, log_scale, lower, upper, per_log = [], [], [], [], []
    listed = [p.name for p in parameters]
    twice = sorted({n for n in listed if listed.count(n) > 1})
    if twice:  # both would be fitted, and `FitResult.value` would keep one of them
        raise ValueError(f"make_problem: free parameter(s) {', '.join(map(repr, twice))} listed more than once")
    for p in parameters:
        if p.name not in known and fd.params.absent_optional_term(chain, p.name):
            # say how to add the term (the experiment file adds it by itself)
            raise ValueError(
                f"free parameter {p.name!r} is an optional term this chain does not have: add it with "
                f"`fd.with_optional_terms(chain, [{p.name!r}])` (at 0.0, its neutral value) before make_problem"
            )
        if p.name not in known:
            raise ValueError(
                f"free parameter {p.name!r} does not exist{fd.params.did_you_mean(p.name, known)}; "
                f"this chain has: {', '.join(sorted(known))}"
            )
        signed = fd.is_signed(chain, p.name) if p.name in chain_names else meas.is_signed(p.name)
        lo = -np.inf if p.lower is None else float(p.lower)
        hi = np.inf if p.upper is None else float(p.upper)
        if lo >= hi:
            raise ValueError(f"free parameter {p.name!r}: lower bound {lo!r} is not below the upper bound {hi!r}")
        if not lo <= p.guess <= hi:
            raise ValueError(f"free parameter {p.name!r}: guess {p.guess!r} is not inside bounds [{lo!r}, {hi!r}]")
        if not signed:
            if p.guess <= 0 or (p.lower is not None and p.lower <= 0):
                raise ValueError(
                    f"free parameter {p.name!r} is positive and fitted in log space: guess and lower bound "
                    f"must be > 0, got guess {p.guess!r}, lower {p.lower!r}"
                )
            lo, hi = (np.log(lo) if np.isfinite(lo) else -np.inf), np.log(hi)
        if p.per_log:  # one free parameter per log, `name[log]`, next to each other
            per_log.append((p.name, tuple(range(len(names), len(names) + len(logs)))))
            own = [f"{p.name}[{log.name}]" for log in logs]
        else:
            own = [p.name]
        names.extend(own)
        log_scale.extend([not signed] * len(own))
        lower.extend([lo] * len(own))
        upper.extend([hi] * len(own))
    return _FreeParameters(names, log_scale, lower, upper, per_log)


class _PaddedLogs(NamedTuple):
    """The logs padded to a common length `T` (`valid` masks the padding; times and torques
    repeat their last sample): the arrays of a `Problem` and its free nuisance entries."""

    t: np.ndarray  # (L, T) s
    valid: np.ndarray  # (L, T) bool
    measured: np.ndarray  # (L, T, C) SI
    present: np.ndarray  # (L, C) bool: log l records channel c
    torque_v: np.ndarray  # (L, T, n_joints) N m
    y0_known: np.ndarray  # (L, 2n)
    y0_free: list[tuple[int, int]]  # (log, state index)
    offset_free: list[tuple[int, int]]  # (log, channel index)


def _padded_logs(chain, logs, channels: list[str]) -> _PaddedLogs:
    """The logs' samples, torques and initial states on a common length, with their
    `initial`, `fit_initial` and `offsets` entries checked against the chain's states and
    the log's channels."""
    states = state_names(chain)
    L, T, nj = len(logs), max(len(log.t) for log in logs), chain.n_links
    # one log needs no padding: its times and torques are used as they are (read-only views,
    # never written to), not copied: a 1 GB log's copies are what `identify check` holds
    single = L == 1
    out = _PaddedLogs(
        t=np.asarray(logs[0].t, float)[None] if single else np.zeros((L, T)),
        valid=np.zeros((L, T), bool),
        measured=np.zeros((L, T, len(channels))),
        present=np.zeros((L, len(channels)), bool),
        torque_v=_single_torque(logs[0], nj) if single else np.zeros((L, T, nj)),
        y0_known=np.zeros((L, len(states))),
        y0_free=[],
        offset_free=[],
    )
    for l, log in enumerate(logs):
        tl = np.asarray(log.t, float)
        k = len(tl)
        if not single:
            out.t[l, :k], out.t[l, k:] = tl, tl[-1]
        out.valid[l, :k] = True
        for c, values in log.outputs.items():
            j = channels.index(c)
            out.measured[l, :k, j] = np.asarray(values, float)
            out.present[l, j] = True
        if log.torque is not None and not single:
            tv = _torque_columns(log, nj)
            out.torque_v[l, :k], out.torque_v[l, k:] = tv, tv[-1]
        for name, value in log.initial.items():
            if name not in states:
                raise ValueError(f"log {log.name!r}: initial-state entry {name!r} is not one of {states}")
            out.y0_known[l, states.index(name)] = float(value)
        for field in ("fit_initial", "offsets"):
            entries = list(getattr(log, field))
            twice = sorted({e for e in entries if entries.count(e) > 1})
            if twice:
                raise ValueError(f"log {log.name!r}: {field} lists {', '.join(map(repr, twice))} more than once")
        for name in log.fit_initial:
            if name not in states:
                raise ValueError(f"log {log.name!r}: fit_initial entry {name!r} is not one of {states}")
            out.y0_free.append((l, states.index(name)))
        for c in log.offsets:
            if c not in log.outputs:
                raise ValueError(f"log {log.name!r}: offset for channel {c!r}, which the log does not record")
            out.offset_free.append((l, channels.index(c)))
    return out


def _common_hold(logs, nj: int) -> str | tuple[str, ...]:
    """The logs' `hold`, one for the problem: the torque input of every log is read the same
    way (one compiled simulation); logs that differ are an error naming them."""
    holds = {}
    for log in logs:
        if log.torque is not None:
            hold = log.hold if isinstance(log.hold, str) else tuple(log.hold)
            try:
                hold = check_hold(hold, nj)
            except ValueError as e:
                raise ValueError(f"log {log.name!r}: hold: {e}") from None
            holds.setdefault(hold, []).append(log.name)
    if len(holds) > 1:
        listed = "; ".join(f"{hold!r}: {', '.join(map(repr, names))}" for hold, names in holds.items())
        raise ValueError(
            f"make_problem: the logs read their torque samples differently ({listed}); one problem reads every "
            "log's the same way (a rig's controller holds its commands, or none does): set the same hold"
        )
    return next(iter(holds), "linear")


def _torque_columns(log, nj: int) -> np.ndarray:
    """A log's torque as `(samples, nj)` (a view where it can be), checked against the rig."""
    tv = np.asarray(log.torque, float).reshape(len(log.t), -1)
    if tv.shape[1] != nj:
        raise ValueError(f"log {log.name!r}: torque has {tv.shape[1]} column(s), the rig has {nj} joint(s)")
    return tv


def _single_torque(log, nj: int) -> np.ndarray:
    """The torque of a problem's only log, `(1, samples, nj)`: its own array, or zeros."""
    if log.torque is None:
        return np.zeros((1, len(log.t), nj))
    return _torque_columns(log, nj)[None]


def _noise_levels(chain, noise: dict, channels: list[str], padded: _PaddedLogs) -> list[float]:
    """Each channel's noise standard deviation (SI): `noise`'s (checked: a channel of the
    chain, a level > 0), else 1 % of the channel's RMS over the logs that record it (1 for
    an all-zero channel)."""
    for c in sorted(set(noise) - set(channels)):  # a typo ("theta") would drop the noise level in silence
        try:
            ch.check_channel(chain, c)
        except ValueError as e:
            raise ValueError(f"make_problem: noise: {e}; the logs record {channels}") from None
        # a channel of this chain that no log records: its noise level is not used
    sigma = []
    for j, c in enumerate(channels):
        if noise.get(c) is not None:
            if not (np.isfinite(float(noise[c])) and float(noise[c]) > 0):
                raise ValueError(f"make_problem: noise[{c!r}] expected a standard deviation > 0 (SI), got {noise[c]!r}")
            sigma.append(float(noise[c]))
        else:
            rms = np.sqrt(np.mean(padded.measured[:, :, j][padded.valid & padded.present[:, j : j + 1]] ** 2))
            sigma.append(0.01 * rms if rms > 0 else 1.0)
    return sigma


def _onsets(logs, channels: list[str], noise: dict, sigma: list[float], padded: _PaddedLogs, resolution) -> list[float]:
    """Each log's `log_onset` (s, on its clock); `resolution` `(C,)`: the channels' declared
    quantisation steps (0: none), which keep their floors at least at its noise."""
    t, measured, present, torque_v = padded.t, padded.measured, padded.present, padded.torque_v
    onset = []
    for l, log in enumerate(logs):
        k = len(log.t)
        # a channel given no noise level is judged at rest against at least its own
        # model-free floor in this log: 1 % of its RMS can be under its noise, and noise
        # would then be read as motion
        own = [j for j, c in enumerate(channels) if present[l, j] and noise.get(c) is None]
        floors = dict(
            zip(own, nf.series_floors(t[l, :k], [measured[l, :k, j] for j in own], [resolution[j] for j in own]))
        )
        at_rest = [max(sigma[j], floors[j]) if j in floors else sigma[j] for j in range(len(channels)) if present[l, j]]
        recorded = measured[l, :k] if present[l].all() else measured[l, :k][:, present[l]]  # (a view if it can)
        onset.append(log_onset(t[l, :k], torque_v[l, :k], recorded, np.asarray(at_rest)))
    return onset


def _guesses_made(parameters, n_logs: int) -> list[float]:
    """`make_problem`'s guesses in its names' order (a per-log one's once per log)."""
    return [float(p.guess) for p in parameters for _ in range(n_logs if p.per_log else 1)]


#: `log_onset`: a log moves once a channel leaves its resting value by more than this many
#: noise standard deviations (a false trigger on Gaussian noise: 6e-7 per sample).
ONSET_SIGMAS = 5.0


#: `log_onset`: a channel's resting value is the median of at most this many first samples
ONSET_REST_SAMPLES = 16


def log_onset(t, torque, measured, sigma) -> float:
    """The time (s, on the log's clock) from which a log that starts at rest is driven: the
    earlier of
    - the input's start: the sample before the first one with a non-zero torque (the torque
      is linear between samples, so it starts to rise there);
    - the motion's start, where it comes first (the arm nudged before the input): the
      sample before the first one at which a recorded channel is more than `ONSET_SIGMAS`
      noise standard deviations from its resting value, the median of its first
      `ONSET_REST_SAMPLES` samples (of those before the input, if fewer).

    The first sample's time for every other log: one with no input (a release, a free
    decay: it moves from its initial state), and one whose torque is not zero at its first
    sample (driven from its start, or holding the arm against gravity: the first sample is
    the safe choice).

    `t` `(T,)`, `torque` `(T, n_joints)`, `measured` `(T, C)`, `sigma` `(C,)` (SI).

    A fit's horizons count from here (`fit`, `identify.residuals.predict`): a rig that sits
    still for seconds before the experimenter starts the input is common, and a growing
    horizon counted from the log's start would fit its first stages to the rest alone."""
    t, torque = np.asarray(t, float), np.asarray(torque, float).reshape(len(t), -1)
    measured, sigma = np.asarray(measured, float).reshape(len(t), -1), np.asarray(sigma, float)
    driven = np.flatnonzero(np.any(torque != 0.0, axis=1))
    if driven.size == 0 or driven[0] == 0:
        return float(t[0])
    k = k_in = int(driven[0])
    if measured.shape[1]:
        rest = np.median(measured[: min(k_in, ONSET_REST_SAMPLES)], axis=0)
        moved = np.flatnonzero(np.any(np.abs(measured[:k_in] - rest) > ONSET_SIGMAS * sigma, axis=1))
        if moved.size:
            k = int(moved[0])
    return float(t[max(k - 1, 0)])


def parameter_unit(problem: Problem, name: str) -> str:
    """SI unit of a free parameter of `problem` (chain or measurement parameter; a per-log
    one's, `name[log]`, is its parameter's)."""
    name = problem.base_name(name)
    if meas.is_measurement_parameter(name):
        return meas.unit(name, ch.channel_unit)
    return fd.parameter_unit(problem.chain, name)


def guesses_of(problem: Problem, parameters) -> list[float]:
    """The guesses of `parameters` (checked to be the problem's) in `problem.names` order:
    a per-log parameter's guess once per log."""
    return _guesses_made(parameters, problem.t.shape[0])
