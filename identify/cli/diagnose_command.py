"""`identify diagnose`: print and write what the library's diagnosis returns."""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

from .._report.json import package_versions
from .check_command import _set_up_checks
from .fit_command import _failure_text
from .folder import OutputFolder
from .output import INTERRUPTED, NOT_CONVERGED, PROGRESS_FILE, _experiment_and_folder, _Refused, printers


def run_diagnose(args) -> int:
    """`identify diagnose EXPERIMENT`: the diagnosis, its report and plots. Exit status 0,
    1 (failed), 2 (bad arguments or folder), `NOT_CONVERGED` (the baseline fit), 130
    (interrupted: its progress so far is in `progress.log`)."""
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
        folder = OutputFolder.claim(out, inputs, args.force, "diagnosis")
    except _Refused as e:
        return error(str(e))
    with folder:
        if folder.killed_before:
            say(f"note: the previous run into {out} was killed ({folder.previous}); its files are replaced")
        return _diagnose_into(args, exp, folder, catalogue, start, say)


def _diagnose_into(args, exp, folder: OutputFolder, catalogue, start: float, say) -> int:
    """`run_diagnose` once its output `folder` is claimed."""
    from .._workflow import diagnose

    # Every progress line goes to progress.log as it is said (not staged), so that a
    # diagnosis stopped part way (Ctrl-C, a job's time limit, a kill) leaves what it found
    # so far: the baseline fit, the screening, each round's scores.
    log_path = folder.path / PROGRESS_FILE
    with log_path.open("w", encoding="utf-8") as log_file:

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
            folder.abandon("failed (see progress.log)")
            print(f"identify diagnose: failed: {_failure_text(e)}", file=sys.stderr, flush=True)
            return 1
        except KeyboardInterrupt:
            record(f"identify diagnose: interrupted after {time.perf_counter() - start:.1f} s")
            folder.abandon("interrupted (see progress.log)")
            print(
                f"identify diagnose: interrupted; what it had found so far is in {log_path}",
                file=sys.stderr,
                flush=True,
            )
            return INTERRUPTED
    written = _write_diagnosis(args, exp, folder, diag)
    print()
    try:
        print(diag.summary())
    except Exception as e:  # noqa: BLE001 (formatting must not cost the written report)
        print(
            f"identify diagnose: warning: the summary could not be printed ({type(e).__name__}: {e})", file=sys.stderr
        )
    print()
    out = folder.path
    print(f"total {time.perf_counter() - start:.1f} s. Report: {out / 'report.md'} (open it; plots beside it)")
    for p in [*written, log_path]:
        print(f"  {p}")
    if diag.interrupted:
        print(
            f"identify diagnose: exit status {INTERRUPTED}: {diag.interrupted}; the report of what was accepted "
            "before it is written",
            file=sys.stderr,
        )
        return INTERRUPTED
    if not diag.baseline_converged:  # on stderr and in the exit status, not only in the report
        print(
            f"identify diagnose: exit status {NOT_CONVERGED}: the baseline fit did not converge "
            f"({diag.baseline.stages[-1].outcome}); the diagnosis is written, but its scores are measured "
            "against a model short of its optimum (see the baseline note in the summary)",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    return 0


def _write_diagnosis(args, exp, folder: OutputFolder, diag) -> list[Path]:
    """`diagnosis.json`, `report.md` and the plots, staged and committed into `folder`
    (`diagnosis.json` last; `progress.log` stays). A file that cannot be made is a warning."""
    from .._report.diagnosis_report import JSON_FILE, write_report

    extra = {
        "experiment": {"name": exp.name, "path": str(Path(exp.path).resolve())},
        "command": ["identify", "diagnose", str(args.experiment)],
        "versions": package_versions(),
    }
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        write_report(diag, folder.staging(), title=exp.name, extra=extra)
    for w in caught:
        print(f"identify diagnose: warning: {w.message}", file=sys.stderr, flush=True)
    status = "interrupted, the report of what was accepted before it" if diag.interrupted else "complete"
    return folder.commit(JSON_FILE, status, keep=(PROGRESS_FILE,))
