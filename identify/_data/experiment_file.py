"""`load_experiment`: an experiment file (TOML, `docs/experiment-format.md`) and its logs."""

from __future__ import annotations

import tomllib
from pathlib import Path

from .columns import MIN_SAMPLES
from .controller_section import _controller
from .experiment import Experiment
from .experiment_sections import _build_rig, _free_parameters, _log_entry, _measurement, _noise, _starts
from .files import absolute, file_problem
from .toml_reader import ExperimentError, _Reader, _show

_TOP_KEYS = ("experiment", "rig", "parameters", "starts", "noise", "logs", "sensors", "actuators", "controller")


_EXPERIMENT_KEYS = ("name", "description", "strict", "min_samples")


_RIG_KEYS = ("base", "options", "set", "gravity", "links", "joints", "hubs", "payload", "motors")


_LOG_KEYS = (
    "file",
    "name",
    "role",
    "columns",
    "calibration",
    "decimal",
    "initial",
    "fit_initial",
    "offsets",
    "strict",
    "set",
    "stamp",
    "time_base",
    "rate_hz",
    "hold",
)


def load_experiment(path) -> Experiment:
    """Read an experiment file (TOML) and everything it refers to; see `docs/experiment-format.md`.

    Raises `ExperimentError` for a problem in the experiment file and `LogError` for one
    in a log file (both `ValueError`); nothing is written.
    """
    path = Path(path)
    problem = file_problem(path)
    if problem is not None:
        raise ExperimentError(f"{absolute(path)}: experiment file {problem}; expected a TOML file")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not TOML
    except UnicodeDecodeError as e:
        raise ExperimentError(f"{path}: expected a UTF-8 text file ({e})") from None
    except OSError as e:
        raise ExperimentError(f"{path}: experiment file cannot be read ({e.strerror})") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ExperimentError(f"{path}: not valid TOML: {e}") from None
    r = _Reader(path, text)
    r.table(doc, (), _TOP_KEYS)

    meta = r.table(doc.get("experiment", {}), ("experiment",), _EXPERIMENT_KEYS)
    name = r.string(meta.get("name", path.stem), ("experiment", "name"))
    description = r.string(meta.get("description", ""), ("experiment", "description"))
    strict = meta.get("strict", False)
    if not isinstance(strict, bool):
        raise r.error(("experiment", "strict"), f"expected true or false, got {_show(strict)}")
    min_samples = meta.get("min_samples", MIN_SAMPLES)
    if isinstance(min_samples, bool) or not isinstance(min_samples, int) or min_samples < 2:
        raise r.error(("experiment", "min_samples"), f"expected an integer >= 2, got {_show(min_samples)}")

    if "rig" not in doc:
        raise r.error((), 'missing [rig]: expected base = "<named rig>" or an explicit chain ([[rig.links]], ...)')
    chain = _build_rig(r, r.table(doc["rig"], ("rig",), _RIG_KEYS))

    if "logs" not in doc:
        raise r.error((), 'no [[logs]]; expected at least one [[logs]] table with file = "..."')
    if not isinstance(doc["logs"], list) or not doc["logs"]:
        raise r.error(("logs",), "expected one or more [[logs]] tables")
    logs = []
    for k, spec in enumerate(doc["logs"], start=1):
        logs.append(_log_entry(r, chain, r.table(spec, ("logs", k), _LOG_KEYS), k, strict, min_samples))
    seen: dict[str, int] = {}
    for k, entry in enumerate(logs, start=1):
        if entry.name in seen:
            raise r.error(
                ("logs", k, "name"),
                f"log name {entry.name!r} is also used by logs[{seen[entry.name]}]; give each log a unique name",
            )
        seen[entry.name] = k
    same: dict[tuple, int] = {}
    for k, entry in enumerate(logs, start=1):
        read = (entry.file, repr(sorted(entry.columns.items())))  # (a bag's columns are tables)
        if read in same:
            raise r.error(
                ("logs", k, "file"),
                f"logs[{same[read]}] already reads {entry.file.name} with the same columns: the same samples "
                "would count twice (and the intervals come out too narrow); list each log once",
            )
        same[read] = k
    if not any(entry.role == "fit" for entry in logs):
        raise r.error(("logs",), 'every log has role = "validation"; expected at least one with role = "fit"')

    command = doc.get("controller", {}).get("command") if isinstance(doc.get("controller"), dict) else None
    noise = _noise(r, logs, r.table(doc.get("noise", {}), ("noise",)), command if isinstance(command, str) else None)
    measurement = _measurement(r, chain, logs, doc)
    free, measurement, chain = _free_parameters(
        r, chain, measurement, logs, r.table(doc.get("parameters", {}), ("parameters",))
    )
    free_names = {p.name for p in free}
    for k, entry in enumerate(logs, start=1):
        for pname in entry.set:
            if pname in free_names:
                raise r.error(
                    ("logs", k, "set", pname),
                    f"{pname} is also a free parameter in [parameters]; a known value per log and a fitted one "
                    "exclude each other (to fit a value per log: per_log = true under [parameters]; every "
                    "parameter in each log on its own: identify fit --independent)",
                )
    starts = _starts(r, free, doc.get("starts", []))
    controller = None
    if "controller" in doc:
        controller = _controller(r, chain, logs, r.table(doc["controller"], ("controller",)))
    elif any(entry.log.references for entry in logs):
        k, entry = next((k, e) for k, e in enumerate(logs, start=1) if e.log.references)
        raise r.error(
            ("logs", k, "columns"),
            f"log {entry.name!r} maps a reference column ({', '.join(sorted(entry.log.references))}'s), but the file "
            "has no [controller] to read it; declare the feedback law under [controller], or drop the column",
        )
    return Experiment(
        path=path,
        name=name,
        description=description,
        chain=chain,
        free=tuple(free),
        noise=noise,
        logs=tuple(logs),
        measurement=measurement,
        starts=starts,
        controller=controller,
    )
