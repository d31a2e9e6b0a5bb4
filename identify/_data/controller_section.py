"""The experiment file's `[controller]` section: the feedback law every log ran under
(`identify.Controller`; docs/experiment-format.md, "[controller]")."""

from __future__ import annotations

from collections.abc import Mapping

import flexdyn as fd

from . import units as u
from .channels import channel_problem
from .controller import Controller, check_period, feedback_channel
from .experiment import LogSpec
from .toml_reader import _Reader, _show

FEEDBACK_CHANNELS = "theta<i>, phi<i>, alpha<i>, tip<i>, curvature<i>, end_x, end_y"

_CONTROLLER_KEYS = (
    "command",
    "gains",
    "rate_gains",
    "references",
    "feedforward",
    "limit",
    "period",
    "delay",
    "quantise",
)


def _controller(r: _Reader, chain: fd.Chain, logs: list[LogSpec], table: Mapping) -> Controller:
    """`[controller]`, checked against the rig and every log (each records the command and
    the references)."""
    key = ("controller",)
    r.table(table, key, _CONTROLLER_KEYS)
    if "command" not in table:
        raise r.error(key, 'missing command: expected the input column the law computes, e.g. command = "voltage1"')
    command = r.string(table["command"], key + ("command",))
    if not u.is_input(command):
        raise r.error(
            key + ("command",), f"{command!r} is not an input channel; expected torque<i>, voltage<i> or current<i>"
        )
    why = channel_problem(chain, command)
    if why is not None:
        raise r.error(key + ("command",), why)
    dimension = u.channel_dimension(command)
    gains = {}
    for field in ("gains", "rate_gains"):
        gains[field] = {}
        for channel, value in r.table(table.get(field, {}), key + (field,)).items():
            ckey = key + (field, channel)
            if not feedback_channel(channel):
                raise r.error(
                    ckey,
                    f"not a channel a controller reads; expected one of {FEEDBACK_CHANNELS}",
                )
            why = channel_problem(chain, channel)
            if why is not None:
                raise r.error(ckey, why)
            if isinstance(value, str):
                raise r.error(
                    ckey,
                    f"expected a number in SI units ({u.SI_UNIT[dimension]} per SI unit of {channel}"
                    f"{' per second' if field == 'rate_gains' else ''}), got {_show(value)}",
                )
            gains[field][channel] = r.number(value, ckey)
    if not (gains["gains"] or gains["rate_gains"]):
        raise r.error(key, "no gains: expected gains = { theta1 = ... } and/or rate_gains = { theta1 = ... }")
    references = tuple(r.names(table.get("references", []), key + ("references",)))
    for k, channel in enumerate(references, start=1):
        if channel not in gains["gains"]:
            raise r.error(
                key + ("references",),
                f"{channel!r} has no entry in gains, so its reference would not enter the law; expected channels of "
                f"gains: {sorted(gains['gains'])}",
            )
    feedforward = _amount(r, table.get("feedforward", 0.0), dimension, key + ("feedforward",))
    limit = None
    if "limit" in table:
        limit = _amount(r, table["limit"], dimension, key + ("limit",))
        if limit <= 0:
            raise r.error(key + ("limit",), f"expected a saturation > 0, got {limit!r}")
    period = None
    if table.get("period", "samples") != "samples":
        period = _amount(r, table["period"], u.TIME, key + ("period",))
        if period <= 0:
            raise r.error(key + ("period",), f'expected a sample period > 0 or "samples", got {period!r}')
    delay, quantise = table.get("delay", False), table.get("quantise", False)
    if not isinstance(delay, bool):
        raise r.error(key + ("delay",), f"expected true (one sample of computation delay) or false, got {_show(delay)}")
    if not isinstance(quantise, bool):
        raise r.error(
            key + ("quantise",), f"expected true (readings rounded to their resolution) or false, got {_show(quantise)}"
        )
    try:
        controller = Controller(
            command, gains["gains"], gains["rate_gains"], references, feedforward, limit, period, delay, quantise
        )
    except ValueError as e:
        raise r.error(key, str(e)) from None
    for k, entry in enumerate(logs, start=1):
        _check_log(r, controller, entry, k)
    return controller


def _amount(r: _Reader, value, dimension: str, key: tuple) -> float:
    """A number (SI) or a string with a unit of `dimension`."""
    if isinstance(value, str):
        try:
            value = u.parse_quantity(value, dimension)
        except ValueError as e:
            raise r.error(key, str(e)) from None
    return r.number(value, key)


def _check_log(r: _Reader, controller: Controller, entry: LogSpec, k: int) -> None:
    """A log run under the controller records its command and its references."""
    key = ("logs", k)
    if controller.command not in entry.log.inputs:
        raise r.error(
            key + ("columns",),
            f"log {entry.name!r} has no {controller.command} column; a log under [controller] records the command "
            f'the law computed (map it: {controller.command} = "<column> [unit]")',
        )
    for channel in controller.references:
        if channel not in entry.log.references:
            raise r.error(
                key + ("columns",),
                f"log {entry.name!r} has no {u.reference_channel(channel)} column; [controller] references takes "
                f'{channel}\'s reference from each log (map it: {u.reference_channel(channel)} = "<column> [unit]")',
            )
    extra = sorted(set(entry.log.references) - set(controller.references))
    if extra:
        raise r.error(
            key + ("columns",),
            f"log {entry.name!r} maps {', '.join(u.reference_channel(c) for c in extra)}, which [controller] does not "
            f"read; add {extra[0]!r} to [controller] references, or drop the column",
        )
    read = sorted(set(entry.offsets) & set(controller.channels))
    if read:
        raise r.error(
            key + ("offsets",),
            f"{read[0]} is read by [controller]: a per-log offset would change what the controller read; declare a "
            f"calibration offset under [sensors.{read[0]}] (fittable as sensor.{read[0]}.offset) instead",
        )
    try:
        check_period(controller, entry.log.t_relative, f"log {entry.name!r}")
    except ValueError as e:
        raise r.error(("controller", "period"), str(e)) from None
