r"""The feedback law a rig's digital controller ran while a log was recorded.

A log taken under feedback (a servo holding or tracking a reference) records the command
the controller computed (`voltage1`, `current1` or `torque1`) beside the outputs. Replayed
open loop, that command drives a model whose every error integrates into drift; simulated
closed loop, the law corrects the model as it corrected the rig (`identify.fit`: the
residual's simulation runs the loop, `identify/_model/closed_loop.py`). `Controller`
declares the law; the experiment file's `[controller]` section builds one
(docs/experiment-format.md).

**The law** (linear output feedback on model channels, a PD on each, sampled at the
log's sample times `t_k` and held between them):

    u_k = sat( u_ff + sum_c K_c (r_c,k - m_c,k) - sum_c D_c (m_c,k - m_c,k-1) / h_k )

- `m_c,k`: channel `c` as the controller read it: the model's output through the
  channel's sensor model (`Sensor.gain`, `Sensor.offset`: the value the log records, in
  the fit's SI units and sign convention); with `quantise`, rounded to the sensor's
  declared `resolution` (`q round(m / q)`, an encoder's counts).
- `r_c,k`: the log's reference column for `c` (`<c>_ref`, e.g. `theta1_ref`) where `c` is
  in `references`, else 0 (regulation to zero, e.g. of a tip deflection).
- the rate the controller computed: the backward difference of its readings over one
  sample, `h_k = period` (or `t_k - t_{k-1}` when `period` is None); at the first sample
  the rate is 0 (the controller's previous reading starts at its first).
- `sat`: clipping to `+-limit` (in the command's unit), if given.
- `delay`: the command computed at `t_k` is applied from `t_{k+1}` (one sample of
  computation delay); the command held over the first sample is then the log's first.

**Quantised readings** (`quantise`). Rounded, the model's loop is the rig's exactly (an
encoder's counts and the rate steps of `q / h` they make), but the model's command then
jumps wherever one of its readings crosses a count, so the fit's cost is piecewise
constant in the parameters at a scale below their standard errors. Measured on the
simulated servo pendulum of `tests/identify/test_closed_loop.py` (a 16-bit reading with
3e-4 rad of analog noise, 2 logs of 0.8 s): rounded, the fit took 138 iterations and
ended 2.5-4.6 standard errors from the truth; unrounded (the default: the rounding is
part of the reading's noise), 23 iterations and 0.7-2.1.

The log's command column at sample `k` records the command applied from `t_k` to
`t_{k+1}`. Joints other than the commanded one keep their logged inputs, held over each
sample.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from . import units as u

#: What a controller may read: positions and deflections (an accelerometer's channel
#: would make the command depend on the command).
FEEDBACK_KINDS = ("theta", "phi", "alpha", "tip", "curvature", "end_x", "end_y")

reference_channel = u.reference_channel


@dataclasses.dataclass(frozen=True)
class Controller:
    """A digital controller's feedback law (see the module docstring), SI.

    - `command`: the input channel the law computes and the log records (`torque<i>`,
      N m; `voltage<i>`, V; `current<i>`, A: what joint `i` is driven by).
    - `gains`: output channel -> `K_c`, command units per SI unit of the channel
      (V/rad, N m/m, ...), on `r_c - m_c`.
    - `rate_gains`: output channel -> `D_c`, command units per SI unit per second
      (V s/rad, ...), on the backward-difference rate of `m_c`.
    - `references`: the channels whose reference is a log column (`<c>_ref`); the others'
      is 0.
    - `feedforward`: a constant `u_ff` added to the command (command units).
    - `limit`: the saturation `|u| <= limit` (command units), or None.
    - `period`: the controller's sample period (s), or None for the log's sample
      intervals; the loop ticks at the log's samples, so a declared period must be
      theirs (`check_period`).
    - `delay`: one sample of computation delay.
    - `quantise`: the readings rounded to their sensors' `resolution` (see the module
      docstring); by default they are not.
    """

    command: str
    gains: dict = dataclasses.field(default_factory=dict)
    rate_gains: dict = dataclasses.field(default_factory=dict)
    references: tuple = ()
    feedforward: float = 0.0
    limit: float | None = None
    period: float | None = None
    delay: bool = False
    quantise: bool = False

    def __post_init__(self):
        kind, joint = u.channel_kind_index(self.command)
        if kind not in u.INPUT_KINDS or joint is None:
            raise ValueError(
                f"Controller.command: expected the input channel the law computes (torque<i>, voltage<i> or "
                f"current<i>), got {self.command!r}"
            )
        for field in ("gains", "rate_gains"):
            for c, k in getattr(self, field).items():
                if not feedback_channel(c):
                    raise ValueError(
                        f"Controller.{field}: {c!r} is not a channel a controller can read; expected one of "
                        f"theta<i>, phi<i>, alpha<i>, tip<i>, curvature<i>, end_x, end_y"
                    )
                if not _finite_number(k):
                    raise ValueError(f"Controller.{field}[{c!r}]: expected a finite number, got {k!r}")
        if not (self.gains or self.rate_gains):
            raise ValueError("Controller: no gains; expected at least one channel in gains or rate_gains")
        for c in self.references:
            if c not in self.gains:
                raise ValueError(
                    f"Controller.references: {c!r} has no gain (its reference would not enter the law); expected "
                    f"one of the channels in gains: {sorted(self.gains)}"
                )
        if len(set(self.references)) != len(self.references):
            raise ValueError(f"Controller.references: a channel is listed twice in {self.references!r}")
        if not _finite_number(self.feedforward):
            raise ValueError(f"Controller.feedforward: expected a finite number, got {self.feedforward!r}")
        if self.limit is not None and not (_finite_number(self.limit) and self.limit > 0):
            raise ValueError(f"Controller.limit: expected a saturation > 0 (command units) or None, got {self.limit!r}")
        if self.period is not None and not (_finite_number(self.period) and self.period > 0):
            raise ValueError(f"Controller.period: expected a sample period > 0 s or None, got {self.period!r}")
        for field in ("delay", "quantise"):
            if not isinstance(getattr(self, field), bool):
                raise ValueError(f"Controller.{field}: expected True or False, got {getattr(self, field)!r}")

    def describe(self) -> str:
        """The law in one line, SI: `voltage1 = clip(0.5 + 20 (theta1_ref - theta1) - 0.3
        d(theta1)/dt, +-6), every 0.001 s, ...`."""
        terms = [f"{self.feedforward:g}"] if self.feedforward else []
        for c in self.channels:
            if c in self.gains:
                ref = u.reference_channel(c) if c in self.references else "0"
                terms.append(f"{self.gains[c]:g} ({ref} - {c})")
            if c in self.rate_gains:
                terms.append(f"-{self.rate_gains[c]:g} d({c})/dt")
        law = " + ".join(terms).replace("+ -", "- ")
        if self.limit is not None:
            law = f"clip({law}, +-{self.limit:g})"
        period = "at the log's samples" if self.period is None else f"every {self.period:g} s"
        extras = [s for s, on in (("one sample of delay", self.delay), ("quantised readings", self.quantise)) if on]
        return (
            f"{self.command} = {law}, {period} (zero-order hold, rates by backward difference"
            + "".join(f", {e}" for e in extras)
            + ")"
        )

    @property
    def joint(self) -> int:
        """The commanded joint, 1-based."""
        return u.channel_kind_index(self.command)[1]

    @property
    def channels(self) -> tuple[str, ...]:
        """The channels the law reads (a gain or a rate gain), sorted."""
        return tuple(sorted(set(self.gains) | set(self.rate_gains)))


def feedback_channel(channel: str) -> bool:
    """Whether `channel` is an output a controller may read (`FEEDBACK_KINDS`)."""
    if not (isinstance(channel, str) and u.is_output(channel)):
        return False
    kind, _ = u.channel_kind_index(channel)
    return kind in FEEDBACK_KINDS


def check_period(controller: Controller, t, where: str) -> None:
    """A declared `period` must be the log's sample interval (the loop ticks at the
    samples): its median within 1 %. `t`: the log's times (s); `where`: names the log."""
    if controller.period is None or len(t) < 2:
        return
    dt = float(np.median(np.diff(np.asarray(t, float))))
    if not math.isclose(dt, controller.period, rel_tol=0.01):
        raise ValueError(
            f"{where}: sampled every {dt:.6g} s, but the controller's period is {controller.period:.6g} s; the loop "
            "is simulated at the log's samples, so a closed-loop log must record every controller tick (log at the "
            "controller's rate, or correct the period)"
        )


def _finite_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
