"""`identify diagnose`: print and write what the library's diagnosis returns."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from .._report.json import package_versions
from .check_command import _set_up_checks
from .fit_command import _failure_text
from .output import (
    NOT_CONVERGED,
    PROGRESS_FILE,
    _experiment_and_folder,
    _Refused,
    _write_marker,
    check_output_folder,
    printers,
)


def run_diagnose(args) -> int:
    start = time.perf_counter()

    say, error = printers("diagnose", args.quiet)

    from .._diagnose.catalogue import NAMES

    catalogue = NAMES
    if args.only:
        catalogue = tuple(x.strip() for x in args.only.split(",") if x.strip())
        bad = [x for x in catalogue if x not in NAMES]
        if bad:
            return error(f"--only: unknown catalogue entries {bad}; expected some of {', '.join(NAMES)}")
    if args.max_effects < 1:
        return error(f"--max-effects expects an integer >= 1, got {args.max_effects}")
    try:
        exp, inputs, out = _experiment_and_folder(args, "diagnosis")
    except _Refused as e:
        return error(str(e))

    from .._report.diagnosis_report import write_report
    from .._workflow import diagnose

    # The output folder is made now and every progress line goes to its progress.log as
    # it is said, so that a diagnosis stopped part way (Ctrl-C, a job's time limit) leaves
    # what it found so far: the baseline fit, the screening, each round's scores.
    out.mkdir(parents=True, exist_ok=True)
    _write_marker(out)
    log_path = out / PROGRESS_FILE
    log_file = log_path.open("w", encoding="utf-8")

    def record(msg: str):
        say(msg)
        log_file.write(msg + "\n")
        log_file.flush()

    record(f"identify diagnose: experiment {exp.name!r} ({exp.path})")
    for line in _set_up_checks(exp):
        record(f"  {line}")
    record(f"  catalogue: {', '.join(catalogue)}; compiling takes most of the first minutes")
    last = [time.perf_counter()]

    def progress(msg: str):
        now = time.perf_counter()
        record(f"[{now - start:6.1f} s, +{now - last[0]:5.1f} s] {msg.strip()}")
        last[0] = now

    try:
        diag = diagnose(
            exp,
            catalogue=catalogue,
            max_effects=args.max_effects,
            progress=progress,
            **({"n_fit": None} if args.fit_all else {}),
        )
    except (RuntimeError, ValueError) as e:
        record(f"identify diagnose: failed: {_failure_text(e)}")
        log_file.close()
        print(f"identify diagnose: failed: {_failure_text(e)}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        record(f"identify diagnose: interrupted after {time.perf_counter() - start:.1f} s")
        log_file.close()
        print(
            f"identify diagnose: interrupted; what it had found so far is in {log_path}",
            file=sys.stderr,
            flush=True,
        )
        return 130
    log_file.close()
    print()
    print(diag.summary())
    try:
        check_output_folder(out, inputs, args.force, "diagnosis")
    except _Refused as e:
        return error(str(e))
    _write_marker(out)
    extra = {
        "experiment": {"name": exp.name, "path": str(Path(exp.path).resolve())},
        "command": ["identify", "diagnose", str(args.experiment)],
        "versions": package_versions(),
    }
    written = write_report(diag, out, title=exp.name, extra=extra)
    print()
    print(f"total {time.perf_counter() - start:.1f} s. Report: {out / 'report.md'} (open it; plots beside it)")
    for p in [*written, log_path]:
        print(f"  {p}")
    if not diag.baseline_converged:  # on stderr and in the exit status, not only in the report
        print(
            f"identify diagnose: exit status {NOT_CONVERGED}: the baseline fit did not converge "
            f"({diag.baseline.stages[-1].outcome}); the diagnosis is written, but its scores are measured "
            "against a model short of its optimum (see the baseline note in the summary)",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0
