"""The `identify fit` command (`identify.cli.main`) on a copy of the shipped example
(`identify/examples/pendulum_drops`), shortened to 3 s per log: exit codes, result.json,
plots, error messages, the output-folder policy, and that inputs are never touched."""

import hashlib
import json
import math
import os
import re
import shutil
from pathlib import Path

import pytest

import identify._workflow as _workflow_module
from identify._report.fit_plots import BY_LOG_PLOT, PLOT_FILES
from identify.cli import main
from identify.cli.output import MARKER

EXAMPLE = Path(__file__).resolve().parents[2] / "identify" / "examples" / "pendulum_drops"
TRUTH = {"joint1.damping": 1.9e-3, "hub1.inertia": 2e-5}
KEEP_S = 3.0  # seconds of each log kept by the tests (the shipped logs are 6 s)


def _shorten(csv: Path, keep_s: float):
    lines = csv.read_text().splitlines()
    out = []
    for line in lines:
        head = line.split(",", 1)[0]
        try:
            if float(head) > keep_s:
                continue
        except ValueError:  # comment or header
            pass
        out.append(line)
    csv.write_text("\n".join(out) + "\n")


def _copy_example(folder: Path) -> Path:
    """A shortened copy of the example; returns its experiment file."""
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("__pycache__", "*-fit"))
    for csv in (folder / "logs").glob("*.csv"):
        _shorten(csv, KEEP_S)
    return folder / "experiment.toml"


def _snapshot(folder: Path) -> dict:
    """Path -> (mtime_ns, sha256) of every file under `folder`."""
    return {
        p: (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """One run of `identify fit` (2 stages) from a working folder; shared by the tests."""
    root = tmp_path_factory.mktemp("cli")
    exp = _copy_example(root / "example")
    work = root / "work"
    work.mkdir()
    before = _snapshot(root / "example")
    out = work / "experiment-fit"
    code = main(["fit", str(exp), "--out", str(out), "--stages", "2"])
    after = _snapshot(root / "example")
    return {"code": code, "exp": exp, "out": out, "before": before, "after": after, "work": work}


def test_fit_succeeds_and_writes_results(fitted):
    assert fitted["code"] == 0
    out = fitted["out"]
    assert (out / MARKER).is_file()
    for name in PLOT_FILES:
        assert (out / name).is_file() and (out / name).stat().st_size > 1000, name
    doc = json.loads((out / "result.json").read_text())
    assert doc["converged"] is True
    params = {p["name"]: p for p in doc["parameters"]}
    assert set(params) == set(TRUTH)
    for name, truth in TRUTH.items():
        lo, hi = params[name]["ci95"]
        assert lo <= truth <= hi, (name, params[name])
        assert params[name]["std_error"] > 0
    assert doc["experiment"]["path"] == str(fitted["exp"].resolve())
    assert {log["role"] for log in doc["experiment"]["logs"]} == {"fit", "validation"}
    assert set(doc["residuals"]) == {"drop_0deg", "drop_m45deg"}
    assert doc["residuals"]["drop_0deg"]["theta1"]["rms"] > 0
    assert set(doc["validation"]) == {"drop_m97deg"}
    assert doc["validation"]["drop_m97deg"]["residuals"]["theta1"]["rms"] < 3 * 0.1 * 3.14159 / 180  # ~noise
    # review: initial states and offsets were bare [value, SE] pairs, per-channel values had no unit
    assert doc["channel_units"] == {"theta1": "rad"}
    start = doc["initial_states"]["drop_0deg"]["theta1"]
    assert set(start) == {"value", "std_error", "unit"} and start["unit"] == "rad"
    assert abs(start["value"]) < 0.05 and 0 < start["std_error"] < 0.01  # released at 0 deg
    assert doc["offsets"]["drop_0deg"]["theta1"]["unit"] == "rad"
    held = doc["validation"]["drop_m97deg"]["initial_states"]["theta1"]
    assert held["unit"] == "rad" and abs(held["value"] - math.radians(-97)) < 0.05
    # small-amplitude frequency of the pendulum about the hanging equilibrium
    assert any(0.9 < f < 1.2 for f in doc["natural_frequencies_hz"])
    assert doc["model_checks"] == []  # a rigid link: no stiffening check (tests/identify/test_evidence.py)
    assert doc["clustered_uncertainty"] is None  # 2 fit logs: below CLUSTER_MIN_LOGS
    assert doc["versions"]["jax"]


def test_a_fit_that_did_not_converge_exits_3(fitted, monkeypatch, capsys):
    """Review: a fit that printed `NOT converged` and a parameter on its bound exited 0,
    so a script read it as a success. The real fit (programs cached by the fixture's run)
    with its result marked as ended on a bound, as `identify.fit` marks it."""
    import dataclasses

    real = _workflow_module.fit_experiment

    def on_a_bound(experiment, **options):
        result = real(experiment, **options)
        values = result.values.copy()
        values[0] = 1.000001e-6  # joint1.damping on its lower bound, 1e-6
        return dataclasses.replace(result, converged=False, at_bounds=[result.names[0]], values=values)

    monkeypatch.setattr(_workflow_module, "fit_experiment", on_a_bound)
    out = fitted["work"] / "not-converged"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 3
    printed = capsys.readouterr()
    err = printed.err
    assert "exit status 3: the fit did not converge" in err and "on a bound" in err
    # review: a payload of 0 g fitted in log space ended on its lower bound, and its intervals
    # (10-17 standard errors off) were printed as any others
    assert "cannot reach 0: if its true value may be 0" in printed.out, printed.out
    assert "The intervals above assume an interior optimum" in printed.out
    assert json.loads((out / "result.json").read_text())["converged"] is False  # results still written


def test_inputs_untouched(fitted):
    assert fitted["before"] == fitted["after"]


def test_rerun_into_own_folder_and_default_folder(fitted, monkeypatch, capsys):
    # A second run may reuse the folder of a previous run (marked by MARKER); the compiled
    # programs are cached, so this is quick. The default folder is ./<stem>-fit.
    monkeypatch.chdir(fitted["work"])
    before = _snapshot(fitted["exp"].parent)
    assert main(["fit", str(fitted["exp"]), "--stages", "2", "--quiet"]) == 0
    assert _snapshot(fitted["exp"].parent) == before
    printed = capsys.readouterr().out
    assert "joint1.damping" in printed and "hub1.inertia" in printed and "white" in printed
    assert "compiling" not in printed and "] horizon" not in printed  # --quiet: no progress lines
    assert (fitted["work"] / "experiment-fit" / "result.json").is_file()


def test_cluster_robust_intervals_printed_and_written(fitted, monkeypatch, capsys):
    # From CLUSTER_MIN_LOGS fit logs on, the cluster-robust intervals are added (lowered to
    # 2 here; the estimator's tests are in test_uncertainty.py), if there are more fit logs
    # than free parameters (review: with 2 logs for 2 parameters the covariance is singular).
    monkeypatch.setattr(_workflow_module, "CLUSTER_MIN_LOGS", 2)
    out = fitted["work"] / "robust-2"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "cluster-robust intervals not computed: 2 fit logs for 2 free parameters" in printed
    assert json.loads((out / "result.json").read_text())["clustered_uncertainty"] is None
    # the held-out log made a third fit log (a copy of the experiment)
    exp = fitted["exp"].with_name("experiment_three.toml")
    exp.write_text(fitted["exp"].read_text().replace('role = "validation"', 'role = "fit"'))
    out = fitted["work"] / "robust"
    assert main(["fit", str(exp), "--out", str(out), "--stages", "2", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "cluster-robust uncertainty (3 logs as clusters, t with 2 dof)" in printed
    doc = json.loads((out / "result.json").read_text())
    robust = doc["clustered_uncertainty"]
    assert robust["n_logs"] == 3 and robust["dof"] == 2
    white = {p["name"]: p for p in doc["parameters"]}
    for p in robust["parameters"]:
        assert p["value"] == white[p["name"]]["value"] and p["std_error"] > 0
        assert p["ci"][0] < p["value"] < p["ci"][1]


def test_bad_experiment_is_exit_2_naming_the_file(tmp_path, capsys):
    exp = _copy_example(tmp_path / "example")
    text = exp.read_text().replace('"hub1.inertia"', '"hub1.inertai"')
    exp.write_text(text)
    assert main(["fit", str(exp), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "experiment.toml" in err and "hub1.inertai" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_bad_log_is_exit_2_naming_the_log(tmp_path, capsys):
    exp = _copy_example(tmp_path / "example")
    log = tmp_path / "example" / "logs" / "drop_m45deg.csv"
    lines = log.read_text().splitlines()
    lines[10] = "0.035,n/a"
    log.write_text("\n".join(lines) + "\n")
    assert main(["fit", str(exp), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "drop_m45deg.csv" in err and "line 11" in err


def test_a_log_in_milliseconds_labelled_seconds_is_refused(tmp_path, capsys):
    """Found in review: a time column in ms labelled [s] (0.2 Hz, a 1000-fold span) was
    warned about, then the fit ran on for longer than the reviewer waited."""
    exp = _copy_example(tmp_path / "example")
    log = tmp_path / "example" / "logs" / "drop_m45deg.csv"
    lines = log.read_text().splitlines()
    rows = [k for k, line in enumerate(lines) if line[:1].isdigit() or line[:1] == "-"]
    for k in rows:
        t, rest = lines[k].split(",", 1)
        lines[k] = f"{1000 * float(t):.6g},{rest}"
    log.write_text("\n".join(lines) + "\n")
    for command in ("fit", "diagnose"):
        assert main([command, str(exp), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert "refusing to fit: log 'drop_m45deg'" in err and "milliseconds but labelled [s]" in err, err
        assert "--any-rate" in err and not (tmp_path / "out").exists()


def test_missing_experiment_is_exit_2(tmp_path, capsys):
    assert main(["fit", str(tmp_path / "nope.toml")]) == 2
    assert "nope.toml" in capsys.readouterr().err


def test_refuses_folder_with_foreign_file(tmp_path, capsys):
    exp = _copy_example(tmp_path / "example")
    out = tmp_path / "results"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    (out / "result.json").write_text("someone else's")  # one of our names, but not our folder
    before = _snapshot(out)
    assert main(["fit", str(exp), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "refusing" in err and "notes.txt" in err and "--force" in err
    assert _snapshot(out) == before


def test_refuses_unmarked_folder_holding_only_our_names(tmp_path, capsys):
    exp = _copy_example(tmp_path / "example")
    out = tmp_path / "results"
    out.mkdir()
    (out / "result.json").write_text("not from identify")
    assert main(["fit", str(exp), "--out", str(out)]) == 2
    assert MARKER in capsys.readouterr().err
    assert (out / "result.json").read_text() == "not from identify"


@pytest.mark.parametrize("where", ["experiment", "logs"])
def test_refuses_input_folders_even_with_force(tmp_path, capsys, where):
    exp = _copy_example(tmp_path / "example")
    out = exp.parent if where == "experiment" else exp.parent / "logs"
    before = _snapshot(exp.parent)
    assert main(["fit", str(exp), "--out", str(out), "--force"]) == 2
    err = capsys.readouterr().err
    assert "refusing" in err and "input" in err
    assert _snapshot(exp.parent) == before


def test_help_and_usage_errors(capsys):
    assert main(["--help"]) == 0
    assert "fit" in capsys.readouterr().out
    assert main([]) == 2
    assert main(["fit", "x.toml", "--stages", "0"]) == 2
    assert "--stages" in capsys.readouterr().err


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_a_bad_experiment_file_is_a_usage_error_naming_file_and_line(tmp_path, capsys, command):
    """A mistake in the experiment file (here a start outside its parameter's bounds) stops
    either command before anything is compiled or written: exit 2, the message names the
    file, line and key, and no output folder appears."""
    exp = _copy_example(tmp_path / "example")
    text = exp.read_text()
    name = next(line.split("=")[0].strip() for line in text.splitlines() if line.startswith('"') and "{" in line)
    exp.write_text(text + f"\n[[starts]]\n{name} = -1e9\n")
    out = tmp_path / "out"
    assert main([command, str(exp), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    line = len(exp.read_text().splitlines())
    assert f"identify {command}: " in err and f"{exp}, line {line}: starts[1].{name}" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "flag, expected",
    [
        ([], {"frequency_init": True, "restart_poor_fit": True, "max_restarts": 2}),
        (["--no-frequency-init"], {"frequency_init": False}),
        (["--no-restart-poor-fit"], {"restart_poor_fit": False, "max_restarts": 2}),
        (["--max-restarts", "0"], {"max_restarts": 0, "restart_poor_fit": True}),
    ],
)
def test_fit_flags_reach_the_fit(tmp_path, monkeypatch, capsys, flag, expected):
    """`--no-frequency-init` keeps the EI guesses as given (`frequency_init=False`),
    `--no-restart-poor-fit` and `--max-restarts` set the fit's restarts; the defaults
    are the library's (`identify.fit`). The fit is replaced by a stand-in that records its
    options and fails, which the command reports as exit 1."""

    exp = _copy_example(tmp_path / "example")
    seen = {}

    def stand_in(experiment, **options):
        seen.update(options)
        raise RuntimeError("stand-in fit")

    monkeypatch.setattr(_workflow_module, "fit_experiment", stand_in)
    assert main(["fit", str(exp), "--out", str(tmp_path / "out"), "--quiet", *flag]) == 1
    for key, value in expected.items():
        assert seen[key] == value, key
    assert "stand-in fit" in capsys.readouterr().err


@pytest.mark.filterwarnings("default")  # (the suite turns warnings into errors; a user's shell does not)
def test_warnings_are_printed_as_the_commands_print_them(tmp_path, monkeypatch, capsys):
    """A library warning (say a log at rest, `identify.fit.make_problem`) reaches a
    command-line user as `WARNING: ...`, not as Python's `path:line: UserWarning:` and the
    library's source line; outside the command Python's own format is back."""
    import warnings

    def stand_in(experiment, **options):
        warnings.warn("log 'a' shows no motion above its noise", UserWarning, stacklevel=2)
        raise RuntimeError("stand-in fit")

    monkeypatch.setattr(_workflow_module, "fit_experiment", stand_in)
    assert main(["fit", str(_copy_example(tmp_path / "example")), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "WARNING: log 'a' shows no motion above its noise" in err and "UserWarning" not in err, err
    with pytest.warns(UserWarning, match="outside"):
        warnings.warn("outside", UserWarning, stacklevel=1)
    assert warnings.showwarning.__name__ != "_show_warning"


def test_library_defaults_match_the_command_line():
    """The command's defaults are `identify.fit`'s (a change to one must reach the other)."""
    import inspect

    from identify import fit
    from identify.cli import _parser

    args = _parser().parse_args(["fit", "x.toml"])
    defaults = inspect.signature(fit).parameters
    assert args.max_restarts == defaults["max_restarts"].default
    assert (not args.no_restart_poor_fit) == defaults["restart_poor_fit"].default
    assert (not args.no_frequency_init) == defaults["frequency_init"].default
    assert args.stages == defaults["n_stages"].default
    assert args.segment == defaults["segment"].default and defaults["shooting"].default == "single"


def test_negative_max_restarts_is_a_usage_error(capsys):
    assert main(["fit", "x.toml", "--max-restarts", "-1"]) == 2
    assert "--max-restarts expects an integer >= 0, got -1" in capsys.readouterr().err


def test_diagnose_help_lists_every_catalogue_entry():
    from identify._diagnose.catalogue import NAMES
    from identify.cli import _parser

    sub = next(a for a in _parser()._actions if isinstance(getattr(a, "choices", None), dict))
    only = next(a for a in sub.choices["diagnose"]._actions if a.dest == "only")
    listed = only.help.split("apply): ", 1)[1].split(", ")
    assert listed == list(NAMES)


def test_the_set_up_checks_name_gravity_and_an_implausible_time_unit():
    """Printed before a fit or diagnosis: where gravity makes the first link hang, and a
    warning for a log whose rate questions its time unit (seconds labelled [ms]: 1 MHz)."""
    import dataclasses

    import numpy as np

    from identify import load_experiment
    from identify._data.logs import _sampling
    from identify.cli.check_command import _set_up_checks

    exp = load_experiment(EXAMPLE / "experiment.toml")
    lines = _set_up_checks(exp)
    assert lines[0].startswith("gravity [0, -9.81] m/s^2: the first link hangs at theta1 = -90 deg"), lines
    assert not any(line.startswith("warning") for line in lines)
    spec = exp.logs[0]
    fast = dataclasses.replace(spec, log=dataclasses.replace(spec.log, sampling=_sampling(1e-6 * np.arange(50), 0.0)))
    lines = _set_up_checks(dataclasses.replace(exp, logs=[fast, *exp.logs[1:]]))
    assert lines[1].startswith(f"warning: log {spec.name!r}: 1e+06 Hz") and "labelled [ms]" in lines[1], lines


def test_residual_table_notes_coloured_fit_residuals():
    """Found in review: a fit whose residuals failed the whiteness test (p = 4.5e-280, an
    initial angle held at a noisy first sample) printed intervals 10 standard errors off
    with no note; the note now follows the table for fit logs (not validation logs)."""
    from identify.cli.fit_text import _residual_lines

    def item(white):
        return {"rms": 1e-3, "whiteness": {"white": white, "p_value": 0.5 if white else 1e-9}, "input_correlation": {}}

    report = {"run_a": {"theta1": item(False), "tip1": item(True)}, "run_v": {"theta1": item(False)}}
    roles = {"run_a": "fit", "run_v": "validation"}
    text = "\n".join(_residual_lines(report, {}, roles))
    assert "note: the residuals of run_a theta1 (fit logs) are not white" in text
    assert "run_v theta1" not in text.split("note:")[1]
    white = {"run_a": {"theta1": item(True)}}
    assert "note:" not in "\n".join(_residual_lines(white, {}, roles))


def test_residual_table_takes_a_declared_resolution_into_the_floor():
    """The residual table's RMS/floor uses the same floor as the fit's `fit_quality`: at
    least q / sqrt(12) for a channel with a declared step q (a staircase moving 0.1 count
    per sample, whose own floor is 0.46 of that: `test_noise_floor.py`)."""
    import numpy as np

    from identify.cli.fit_text import _residual_lines

    q = 1e-3
    t = np.arange(5000) * 1e-3
    counts = q * np.round(20.25 * q * np.sin(0.1 / 20.25 * np.arange(5000)) / q)
    item = {"rms": q / np.sqrt(12), "whiteness": {"white": True, "p_value": 0.5}, "input_correlation": {}}
    outputs = {"run": {"t": t, "measured": {"tip1": counts}}}

    def ratio(resolution):
        line = _residual_lines({"run": {"tip1": item}}, outputs, {"run": "fit"}, resolution)[1]
        return float(line.split()[4])

    assert ratio(None) > 2.0
    assert ratio({"tip1": q}) == pytest.approx(1.0, abs=1e-3)


def test_diagnose_refusing_the_experiment_folder_names_its_own_default(tmp_path, capsys):
    # found in review: the message named the fit command's default folder (-fit)
    exp = _copy_example(tmp_path / "example")
    assert main(["diagnose", str(exp), "--out", str(exp.parent), "--force"]) == 2
    err = capsys.readouterr().err
    assert "it holds an input of the experiment" in err and "<experiment stem>-diagnosis" in err, err


def test_diagnose_from_python_given_a_path_says_what_it_expects():
    import identify

    with pytest.raises(TypeError, match=r"expected an Experiment \(identify.load_experiment\(path\)\), got str"):
        identify.diagnose(str(EXAMPLE / "experiment.toml"))


@pytest.mark.parametrize("flag, n_fit", [([], "default"), (["--fit-all"], None)])
def test_diagnose_fit_all_fits_every_candidate(tmp_path, monkeypatch, capsys, flag, n_fit):
    """`--fit-all` turns the screening off (`n_fit=None`); without it the library's
    default holds. A stand-in records the options and fails (exit 1)."""
    import importlib

    module = importlib.import_module("identify._workflow")
    exp = _copy_example(tmp_path / "example")
    seen = {}

    def stand_in(experiment, **options):
        seen.update(options)
        raise RuntimeError("stand-in diagnose")

    monkeypatch.setattr(module, "diagnose", stand_in)
    assert main(["diagnose", str(exp), "--out", str(tmp_path / "out"), "--quiet", *flag]) == 1
    assert ("n_fit" not in seen) if n_fit == "default" else (seen["n_fit"] is None), seen
    assert "stand-in diagnose" in capsys.readouterr().err


@pytest.mark.parametrize("result, status", [("successful", 0), ("max_steps_reached", 3), ("failed", 3)])
def test_diagnose_exits_3_when_its_baseline_fit_did_not_converge(tmp_path, monkeypatch, capsys, result, status):
    """Found in review: a diagnosis whose baseline fit ran out of steps exited 0, and the
    scores it printed were measured against a model short of its optimum. It is written
    (the user may read it) and the exit status says so, as `identify fit`'s does."""
    import dataclasses
    import importlib
    from types import SimpleNamespace

    module = importlib.import_module("identify._workflow")
    report = importlib.import_module("identify._report.diagnosis_report")
    exp = _copy_example(tmp_path / "example")
    baseline = SimpleNamespace(stages=[SimpleNamespace(outcome="successful"), SimpleNamespace(outcome=result)])

    @dataclasses.dataclass
    class StandIn:
        baseline: object
        interrupted: object = None
        baseline_converged = property(module.Diagnosis.baseline_converged.fget)

        def summary(self):
            return "stand-in summary"

    monkeypatch.setattr(module, "diagnose", lambda experiment, **options: StandIn(baseline))
    monkeypatch.setattr(report, "write_report", lambda diag, out, **kw: [out / "report.md"])
    assert main(["diagnose", str(exp), "--out", str(tmp_path / "out"), "--quiet"]) == status
    err = capsys.readouterr().err
    assert (f"exit status 3: the baseline fit did not converge ({result})" in err) == (status == 3), err


def test_check_validates_an_experiment_without_fitting(tmp_path, capsys):
    """Review: the only way to validate an experiment file was to start a fit (and wait
    for its compilation). `identify check` loads it with the fit's checks and exits."""
    exp = _copy_example(tmp_path / "example")
    before = _snapshot(tmp_path)
    assert main(["check", str(exp)]) == 0
    out = capsys.readouterr().out
    assert "free hub1.inertia" in out and "[validation] log 'drop_m97deg'" in out
    assert re.search(r"ok: a fit can start: 2 free parameter\(s\), 2 fit log\(s\) \(\d+ samples\), 1 validation", out)
    assert _snapshot(tmp_path) == before  # nothing written
    assert "declared noise" not in out  # 0.1 deg, the logs' own
    # a declared noise in the wrong unit (review: "0.05 m" for a 0.05 mm gauge passed the
    # check and was flagged only after a 5-minute fit): against the logs' model-free floor
    exp.write_text(exp.read_text().replace('theta1 = "0.1 deg"', 'theta1 = "0.1 rad"'))
    assert main(["check", str(exp)]) == 0
    out = capsys.readouterr().out
    m = re.search(r"warning: the declared noise of theta1 \(5\.73 deg\) is ([\d.]+) times the noise floor", out)
    assert m and 40 < float(m[1]) < 80, out  # 0.1 rad / 0.1 deg = 57.3
    exp.write_text(exp.read_text().replace('"hub1.inertia"', '"hub1.inertai"'))
    assert main(["check", str(exp)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("identify check: ") and "experiment.toml" in err and "hub1.inertai" in err


def test_a_failed_fit_prints_the_check_not_the_stacks():
    """A run-time check inside the fit (`eqx.error_if`) is printed as its own message, not
    with the JAX and Equinox stacks around it (review: pages of stack for one line)."""
    from identify.cli.fit_command import _failure_text

    wrapped = RuntimeError("Above is the stack outside of JIT...\n_EquinoxRuntimeError: link1.EI must be > 0\n\n---")
    assert _failure_text(wrapped) == "link1.EI must be > 0"
    assert _failure_text(ValueError("fit: no logs")) == "fit: no logs"


def test_the_compile_estimate_allows_for_a_single_core(monkeypatch, tmp_path):
    """Review: on one core (`taskset -c 0`) the first call took 2x the guess made for two."""
    from identify import load_experiment
    from identify.cli import fit_command as cli

    exp = load_experiment(_copy_example(tmp_path / "example"))
    monkeypatch.setattr(cli, "_cores", lambda: 2)
    two = cli._compile_estimate(exp)
    monkeypatch.setattr(cli, "_cores", lambda: 1)
    assert cli._compile_estimate(exp) == pytest.approx(2 * two)
    assert 10 < two < 20  # measured 10.6 s for this example on 2 cores (the docstring's)


@pytest.mark.slow  # (CI's 30-minute budget: one of the slowest in the fresh-clone run, 2026-12-07)
def test_fit_independent_fits_each_log_and_compares_them(tmp_path, capsys):
    """`identify fit --independent`: each fit log of the example on its own (the two drops
    from 0 and -45 deg, the same rig): every log's 95 % intervals hold the truth the logs
    were made with, the chi-square test finds them consistent, and result.json, the plots
    and the per-log table are written; the validation log is said to be unused."""
    exp = _copy_example(tmp_path / "example")
    out = tmp_path / "out"
    assert main(["fit", str(exp), "--out", str(out), "--stages", "2", "--independent"]) == 0
    printed = capsys.readouterr().out
    assert "the 1 validation log(s) are not used" in printed
    assert "between the 2 logs' independent fits" in printed and "DIFFERS" not in printed, printed
    doc = json.loads((out / "result.json").read_text())
    assert doc["mode"] == "independent" and sorted(doc["logs"]) == ["drop_0deg", "drop_m45deg"]
    for name, res in doc["logs"].items():
        for p in res["parameters"]:
            assert p["ci95"][0] <= TRUTH[p["name"]] <= p["ci95"][1], (name, p)
    between = doc["between_logs"]
    assert between["names"] == [p["name"] for p in res["parameters"]] and not any(between["differs"]), between
    for name in ("measured_vs_fitted.png", "residuals.png", "parameters_by_log.png"):
        assert (out / name).is_file(), name


def test_an_interrupted_diagnosis_leaves_its_progress_on_disk(tmp_path, monkeypatch, capsys):
    """Review: a diagnosis stopped after 20 minutes (two-link arm) left nothing on disk.
    Every progress line goes to the output folder's progress.log as it is said; Ctrl-C
    exits 130 and says where it is."""

    def stopped(experiment, *, progress, **kw):
        progress("baseline: cost 123 over 45 residuals")
        progress("screening (one Gauss-Newton step per start), predicted costs: coulomb_friction:joint1 12")
        raise KeyboardInterrupt

    monkeypatch.setattr(_workflow_module, "diagnose", stopped)
    out = tmp_path / "diag"
    assert main(["diagnose", str(EXAMPLE / "experiment.toml"), "--out", str(out)]) == 130
    text = (out / "progress.log").read_text()
    assert "baseline: cost 123 over 45 residuals" in text and "coulomb_friction:joint1 12" in text
    assert "identify diagnose: interrupted after" in text.splitlines()[-1]
    assert f"what it had found so far is in {out / 'progress.log'}" in capsys.readouterr().err
    assert (out / MARKER).is_file()
    # the folder is ours: a rerun into it is allowed (no --force)
    monkeypatch.setattr(_workflow_module, "diagnose", stopped)
    assert main(["diagnose", str(EXAMPLE / "experiment.toml"), "--out", str(out)]) == 130


@pytest.mark.slow  # ~70 s; the same fit and held-out check through the library stay in CI (test_run)
def test_a_per_log_parameter_through_identify_fit(tmp_path, capsys):
    """`identify fit` on an experiment with `per_log = true` (tests/per_log_case.py): the
    per-log values in the table and `result.json`, and the validation log's own value,
    fitted with EI held, near the mass it was made with."""
    from per_log_case import MASSES, write_per_log_experiment

    path = write_per_log_experiment(tmp_path / "sweep")
    out = tmp_path / "out"
    assert main(["fit", str(path), "--out", str(out), "--stages", "2"]) == 0
    text = capsys.readouterr().out
    assert "free: link1.EI, payload.mass (per log)" in text
    assert re.search(r"^payload\.mass\[m20\] +0\.0200", text, re.M), text
    assert "m35 [val]: payload.mass = 0.035" in text, text
    assert "payload.mass at the rig's value, not a log's" in text
    assert "cluster-robust" not in text  # 3 fit logs: below CLUSTER_MIN_LOGS
    assert "per-log values in one joint fit" in text and "DIFFERS between logs" in text, text
    doc = json.loads((out / "result.json").read_text())
    params = {p["name"]: p for p in doc["parameters"]}
    for name in ("m10", "m20", "m50"):
        entry = params[f"payload.mass[{name}]"]
        assert entry["unit"] == "kg" and entry["ci95"][0] <= MASSES[name] <= entry["ci95"][1], entry
    assert doc["fitted_per_log"] == {"payload.mass": {n: f"payload.mass[{n}]" for n in ("m10", "m20", "m50")}}
    assert doc["per_log_agreement"]["names"] == ["payload.mass"] and doc["per_log_agreement"]["differs"] == [True]
    assert (out / BY_LOG_PLOT).stat().st_size > 1000
    held = doc["validation"]["m35"]["parameters"]["payload.mass"]
    # (its standard error is ~3e-5 kg: its interval is checked in test_run; here, that the
    # value written is the held-out fit's, not the guess of 0.03 or a fit log's)
    assert held["unit"] == "kg" and abs(held["value"] - MASSES["m35"]) < 5e-4, held


# --- nothing lost: a finished fit is written whatever fails or is interrupted after it ---


def _doc(out: Path) -> dict:
    return json.loads((out / "result.json").read_text())


def test_a_summary_that_cannot_be_formatted_loses_nothing(fitted, monkeypatch, capsys):
    """Found on a real 10 s log: `identify fit` ran 5 minutes, then crashed printing its
    summary (`math domain error` in `interval_text`) and wrote nothing. The files are
    written before the summary is printed, and a failure to print is a warning."""
    import identify.cli.fit_command as fit_command

    def broken(report):
        raise ValueError("math domain error")

    monkeypatch.setattr(fit_command, "print_results", broken)
    out = fitted["work"] / "unprintable"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "warning: the summary could not be printed (ValueError: math domain error)" in err, err
    doc = _doc(out)
    assert doc["converged"] is True and doc["problems"] == [] and doc["interrupted"] is False
    assert set(doc["files"]) == {"result.json", *PLOT_FILES}
    assert all((out / name).is_file() for name in doc["files"])


def test_a_failing_follow_up_or_plot_keeps_the_fit(fitted, monkeypatch, capsys):
    """A simulation failing on the validation log, or a plot failing, is named in
    `result.json`'s `problems` and on stderr; the fit is written and the run exits 0."""
    import identify._report.fit_plots as fit_plots

    def failing_validation(exp, result, progress=None):
        raise RuntimeError("the solver's step limit on log 'drop_c'")

    def failing_plot(*args, **kwargs):
        raise OverflowError("cannot convert float infinity to integer")

    monkeypatch.setattr(_workflow_module, "validate", failing_validation)
    monkeypatch.setattr(fit_plots, "write_plots", failing_plot)
    out = fitted["work"] / "follow-ups-failed"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 0
    captured = capsys.readouterr()
    doc = _doc(out)
    assert doc["problems"] == [
        "validation not computed: RuntimeError: the solver's step limit on log 'drop_c'",
        "plots not written: OverflowError: cannot convert float infinity to integer",
    ], doc["problems"]
    assert doc["validation"] == {} and doc["files"] == ["result.json"]
    assert not any((out / name).exists() for name in PLOT_FILES)
    assert "plots not written: OverflowError" in captured.err
    assert "Fitted parameters" in captured.out  # the summary is printed as usual


def test_ctrl_c_after_the_fit_writes_the_fit_marked_interrupted(fitted, monkeypatch, capsys):
    def interrupted(exp, result, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(_workflow_module, "fit_report", interrupted)
    out = fitted["work"] / "interrupted-after"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 130
    doc = _doc(out)
    assert doc["interrupted"] is True and doc["converged"] is True
    assert doc["problems"] == ["interrupted (Ctrl-C) before the fit's follow-ups were computed"]
    assert "status: interrupted, partly written" in (out / MARKER).read_text()
    assert "interrupted after the fit; writing the fit alone" in capsys.readouterr().err


@pytest.mark.parametrize("existing", [False, True])
def test_ctrl_c_during_the_fit_writes_nothing_and_keeps_the_previous_result(fitted, monkeypatch, capsys, existing):
    def interrupted(experiment, **options):
        raise KeyboardInterrupt

    out = fitted["work"] / f"interrupted-during-{existing}"
    if existing:
        shutil.copytree(fitted["out"], out)
        before = _snapshot(out)
    monkeypatch.setattr(_workflow_module, "fit_experiment", interrupted)
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 130
    assert "interrupted during the fit; nothing was written" in capsys.readouterr().err
    if not existing:  # the folder this run created is removed again
        assert not out.exists()
        return
    after = _snapshot(out)
    changed = {p.name for p in set(before) | set(after) if before.get(p) != after.get(p)}
    assert changed <= {MARKER, ".identify-lock"}, changed  # the previous result is untouched
    assert "status: interrupted during the fit, nothing written" in (out / MARKER).read_text()


def test_the_output_folder_is_checked_before_the_fit(fitted, monkeypatch, tmp_path, capsys):
    """A folder the result could not be written to is refused before minutes of fitting:
    `--out` under a file, a result name taken by a folder (even with --force), a folder
    another run holds, a read-only folder."""
    from identify.cli.folder import OutputFolder

    def must_not_fit(experiment, **options):
        raise AssertionError("the fit started")

    monkeypatch.setattr(_workflow_module, "fit_experiment", must_not_fit)
    exp = str(fitted["exp"])
    (tmp_path / "a-file").write_text("x")
    assert main(["fit", exp, "--out", str(tmp_path / "a-file" / "out")]) == 2
    assert f"{tmp_path / 'a-file'} is a file, not a folder" in capsys.readouterr().err
    blocked = tmp_path / "blocked"
    (blocked / "result.json").mkdir(parents=True)
    (blocked / MARKER).write_text("")
    assert main(["fit", exp, "--out", str(blocked), "--force"]) == 2
    assert f"cannot write {blocked / 'result.json'}: it is a folder" in capsys.readouterr().err
    held = tmp_path / "held"
    with OutputFolder.claim(held, [fitted["exp"]], force=False):
        assert main(["fit", exp, "--out", str(held)]) == 2
    err = capsys.readouterr().err
    assert f"refusing to write into {held}: another identify run is writing there (pid" in err, err
    readonly = tmp_path / "readonly"
    readonly.mkdir()
    readonly.chmod(0o500)
    try:
        if os.access(readonly, os.W_OK):  # (root writes anyway: then so would the result)
            pytest.skip("running as a user who can write into read-only folders")
        assert main(["fit", exp, "--out", str(readonly)]) == 2
        assert f"cannot write into {readonly}" in capsys.readouterr().err
    finally:
        readonly.chmod(0o700)


def test_a_killed_previous_run_is_said_and_its_leftovers_cleared(fitted, capsys):
    out = fitted["work"] / "after-a-kill"
    shutil.copytree(fitted["out"], out)
    (out / MARKER).write_text("Written by `identify`.\nstatus: running (pid 999999, since 2026-12-07T00:00:00)\n")
    (out / ".identify-staging-abc").mkdir()
    (out / ".identify-staging-abc" / "result.json").write_text("{")
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2"]) == 0
    printed = capsys.readouterr().out
    assert f"note: the previous run into {out} was killed (running (pid 999999" in printed
    assert not list(out.glob(".identify-staging-*"))
    assert "status: complete" in (out / MARKER).read_text()


def test_a_folder_that_cannot_take_the_result_after_the_fit_loses_nothing(fitted, monkeypatch, capsys):
    """The folder removed or the disk full during the fit: the result goes to the system's
    temporary folder, and the command says where."""
    import identify.cli.fit_command as fit_command

    def disk_full(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fit_command, "_write_fit", disk_full)
    out = fitted["work"] / "disk-full"
    assert main(["fit", str(fitted["exp"]), "--out", str(out), "--stages", "2", "--quiet"]) == 0
    err = capsys.readouterr().err
    saved = re.search(r"the result is saved as (\S+\.json)", err)
    assert saved and "No space left on device" in err, err
    doc = json.loads(Path(saved.group(1)).read_text())
    assert doc["converged"] is True and "No space left on device" in doc["problems"][-1]
    Path(saved.group(1)).unlink()


def test_a_diagnosis_interrupted_in_its_rounds_writes_what_it_accepted(tmp_path, monkeypatch, capsys):
    """Found on a real rig: a diagnosis stopped by a time limit or Ctrl-C left no report
    although a cause was already accepted. The library returns what was accepted, marked
    `interrupted` (tests/identify/test_diagnose_interrupted.py); the command writes it,
    says so and exits 130."""
    import dataclasses
    import importlib
    from types import SimpleNamespace

    report = importlib.import_module("identify._report.diagnosis_report")

    @dataclasses.dataclass
    class StandIn:
        baseline: object
        interrupted: object
        baseline_converged = True

        def summary(self):
            return f"INTERRUPTED: {self.interrupted}"

    def write(diag, out, **kw):
        (Path(out) / "diagnosis.json").write_text(json.dumps({"interrupted": diag.interrupted}))
        return [Path(out) / "diagnosis.json"]

    text = "interrupted (Ctrl-C) in round 2, after 1 cause(s) accepted; the search did not finish"
    monkeypatch.setattr(_workflow_module, "diagnose", lambda experiment, **options: StandIn(SimpleNamespace(), text))
    monkeypatch.setattr(report, "write_report", write)
    out = tmp_path / "out"
    assert main(["diagnose", str(EXAMPLE / "experiment.toml"), "--out", str(out), "--quiet"]) == 130
    assert json.loads((out / "diagnosis.json").read_text())["interrupted"] == text
    assert "status: interrupted, the report of what was accepted before it" in (out / MARKER).read_text()
    assert f"exit status 130: {text}; the report of what was accepted before it is written" in capsys.readouterr().err


@pytest.mark.parametrize("example", ["pendulum_friction", "ros_bag_link"])
def test_check_takes_the_noise_floors_from_the_logs_as_the_fit_does(example):
    """`identify check` computes the fit logs' noise floors from the logs' own arrays (not
    copied off the device: a 1 GB log's 0.6 GB): the same values as the fit's
    `noise_floors(problem)`, a ROS bag's nanosecond stamps included."""
    import argparse

    import numpy as np

    from identify._fit.quality import noise_floors
    from identify._workflow import problem_from_experiment
    from identify.cli.check_command import _fit_log_floors
    from identify.cli.output import _load_experiment

    path = EXAMPLE.parent / example / "experiment.toml"
    exp = _load_experiment(argparse.Namespace(experiment=path, any_rate=False))
    problem = problem_from_experiment(exp)
    floor, count = _fit_log_floors(exp, problem.channels)
    expected_floor, expected_count = noise_floors(problem)
    np.testing.assert_allclose(floor, expected_floor, rtol=1e-12)
    np.testing.assert_array_equal(count, expected_count)


# ---------------------------------------------------------------------------
# Several experiments in one process (identify.cli.batch)
# ---------------------------------------------------------------------------


def test_check_over_several_experiments_and_a_folder(capsys):
    """`identify check A B FOLDER`: each in turn, one that fails does not stop the others,
    the summary names each file's status and the command returns the largest."""
    examples = EXAMPLE.parent
    missing = examples / "no_such_experiment.toml"
    code = main(["check", str(examples / "pendulum_friction" / "experiment.toml"), str(missing), str(EXAMPLE)])
    out, err = capsys.readouterr()
    assert code == 2
    for k, path in enumerate(
        [examples / "pendulum_friction" / "experiment.toml", missing, EXAMPLE / "experiment.toml"]
    ):
        assert f"identify check [{k + 1}/3]: {path}" in out
    assert "identify check: 2 of 3 experiment(s) done (exit status 0)" in out
    assert re.search(rf"exit 2 +[0-9.]+ s  {re.escape(str(missing))}", out)
    assert f"identify check: not done: {missing} (2)" in err
    assert out.count("ok: a fit can start") == 2


def test_a_batch_runs_each_experiment_in_its_own_folder_and_goes_on_after_a_failure(tmp_path, capsys):
    import argparse

    from identify.cli import batch

    a, b, c = (tmp_path / name / "experiment.toml" for name in ("a", "b", "c"))
    seen = []

    def run_one(args):
        seen.append((args.experiment, args.out))
        if args.experiment == b:
            raise RuntimeError("a bug in one experiment")
        return 3 if args.experiment == c else 0

    args = argparse.Namespace(command="fit", experiments=[a, b, c], out=tmp_path / "results")
    assert batch.run_batch(args, run_one, "fit") == 3
    # the stems agree: each folder named after its experiment's folder too
    assert seen == [(p, tmp_path / "results" / f"{p.parent.name}-experiment-fit") for p in (a, b, c)]
    out, err = capsys.readouterr()
    assert f"{b}: failed: RuntimeError: a bug in one experiment" in err
    assert "1 of 3 experiment(s) done" in out and f"not done: {b} (1), {c} (3)" in err

    def interrupted(args):
        if args.experiment == b:
            raise KeyboardInterrupt
        return 0

    assert batch.run_batch(args, interrupted, "fit") == 130
    out, err = capsys.readouterr()
    assert "interrupted at" in err and re.search(rf"not run +{re.escape(str(c))}", out)


def test_batch_output_folders_and_folders_of_experiments(tmp_path):
    from identify.cli import batch

    assert batch.output_folders([Path("x/one.toml"), Path("y/two.toml")], None, "fit") == [None, None]
    assert batch.output_folders([Path("x/one.toml")], tmp_path, "diagnosis") == [tmp_path / "one-diagnosis"]
    for name in ("b.toml", "a.toml", "notes.txt"):
        (tmp_path / "flat" / name).parent.mkdir(exist_ok=True)
        (tmp_path / "flat" / name).write_text("")
    (tmp_path / "nested" / "r1").mkdir(parents=True)
    (tmp_path / "nested" / "r1" / "experiment.toml").write_text("")
    assert batch.experiment_files([tmp_path / "flat", tmp_path / "nested"]) == [
        tmp_path / "flat" / "a.toml",
        tmp_path / "flat" / "b.toml",
        tmp_path / "nested" / "r1" / "experiment.toml",
    ]


@pytest.mark.slow  # (the first fit compiles ~100 programs: minutes on 2 cores)
def test_a_second_experiment_of_the_same_rig_compiles_no_program(tmp_path, monkeypatch, capsys):
    """`identify fit A B` with B a copy of A (the same rig, logs of the same shapes): the
    second fit reuses every program the first compiled (XLA's backend compilations counted
    through `jax.monitoring`), and both results agree."""
    import jax

    import identify.cli as cli

    compiled, counts = [], []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, secs, **kw: compiled.append(name) if name.endswith("backend_compile_duration") else None
    )

    def counted(args, _run=cli._run_one):
        before = len(compiled)
        code = _run(args)
        counts.append(len(compiled) - before)
        return code

    monkeypatch.setattr(cli, "_run_one", counted)
    for name in ("a", "b"):
        shutil.copytree(EXAMPLE, tmp_path / name)
    code = main(["fit", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "out"), "--quiet"])
    assert code == 0, capsys.readouterr().err
    assert counts[0] > 10 and counts[1] == 0, counts
    a, b = (json.loads((tmp_path / "out" / f"{n}-experiment-fit" / "result.json").read_text()) for n in "ab")
    assert a["parameters"] == b["parameters"]


def test_a_bad_segment_fails_naming_the_option(tmp_path, capsys):
    """`--segment` (multiple shooting): a non-positive length is refused by the fit (exit 1,
    nothing written) naming `segment`; with `--independent` it is a usage error (exit 2)."""
    exp = _copy_example(tmp_path / "example")
    assert main(["fit", str(exp), "--out", str(tmp_path / "out"), "--segment", "0", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "segment expected a length in seconds > 0" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "result.json").exists()
    args = ["fit", str(exp), "--out", str(tmp_path / "out2"), "--segment", "0.1", "--independent", "--quiet"]
    assert main(args) == 2
    assert "--segment (multiple shooting) is an option of the joint fit" in capsys.readouterr().err
