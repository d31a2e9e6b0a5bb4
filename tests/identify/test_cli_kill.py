"""`identify fit` killed at random times (SIGINT, SIGTERM, SIGKILL) in a real process: the output
folder never looks like a finished result it is not, and the inputs are never touched.

A folder "looks finished" when it holds `result.json`; then that file must parse, every
file it lists (`files`) must be there and no other result file of ours beside it, and a
run that was interrupted must say so (`interrupted`, the marker's status). After SIGINT
the command ends with its own message, never a traceback."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_cli import _copy_example, _snapshot  # tests/identify is on sys.path (rootdir conftest)

import identify
from identify._report.fit_plots import BY_LOG_PLOT, PLOT_FILES
from identify.cli.output import MARKER

ROOT = Path(identify.__file__).resolve().parents[1]


def _command(exp: Path, out: Path) -> tuple[list[str], dict]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return [sys.executable, "-m", "identify", "fit", str(exp), "--out", str(out), "--stages", "2", "--quiet"], env


def _start(exp: Path, out: Path) -> subprocess.Popen:
    cmd, env = _command(exp, out)
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _check_folder(out: Path) -> str:
    """What the folder holds ('nothing', 'no result', 'complete', 'interrupted', or a complete
    result with a later run killed beside it: the marker can say only "running" then); fails
    where it looks like a finished result and is not one."""
    if not out.exists():
        return "nothing"
    if not (out / "result.json").exists():
        return "no result"
    doc = json.loads((out / "result.json").read_text())
    ours = {*PLOT_FILES, BY_LOG_PLOT, "result.json"}
    present = {p.name for p in out.iterdir() if p.name in ours}
    assert present == set(doc["files"]), (present, doc["files"])
    assert all((out / name).stat().st_size > 0 for name in doc["files"])
    status = (out / MARKER).read_text()
    if "status: running" in status:  # a run killed (SIGKILL) after this result was committed, or before it
        return "complete, then a run killed"
    if "nothing written" in status:  # a later run that wrote nothing: the result is an earlier run's
        assert "the files here are an earlier run's" in status, status
        status = status.split("the files here are an earlier run's", 1)[1]
    if doc["interrupted"]:
        assert "interrupted" in status, status
        return "interrupted"
    assert "complete" in status, status
    return "complete"


def _wait_for_claim(proc: subprocess.Popen, out: Path, timeout_s: float = 120.0) -> None:
    """Until `proc` holds `out` (its pid in the lock file) or has ended. (Before that it is
    Python importing the libraries, where Ctrl-C is Python's own KeyboardInterrupt.)"""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and proc.poll() is None:
        try:
            if f"pid {proc.pid}," in (out / ".identify-lock").read_text():
                return
        except OSError:
            pass
        time.sleep(0.05)


def _trials(tmp_path: Path, n: int, window_s: tuple[float, float], seed: int) -> list[str]:
    exp = _copy_example(tmp_path / "example")
    inputs = _snapshot(exp.parent)
    rng = random.Random(seed)
    seen = []
    for k in range(n):
        out = tmp_path / "out"  # one folder: each run replaces (or leaves) the last one's
        proc = _start(exp, out)
        how = rng.choice([signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
        if how != signal.SIGKILL:  # Ctrl-C "during identify fit": once the command runs (it holds its folder)
            _wait_for_claim(proc, out)
        time.sleep(rng.uniform(*window_s))
        proc.send_signal(how)
        try:
            _, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
            pytest.fail(f"trial {k}: still running 120 s after SIGINT")
        if how != signal.SIGKILL:  # (SIGTERM is handled as Ctrl-C once the command runs)
            assert "Traceback" not in err, f"trial {k}:\n{err}"
            assert proc.returncode in (0, 3, 130, -how), (k, proc.returncode, err)
        seen.append(f"{how.name}: {_check_folder(out)}")
        assert _snapshot(exp.parent) == inputs, f"trial {k}: an input changed"
    return seen


def test_killed_early_leaves_no_result(tmp_path):
    """Killed while starting (loading, compiling): no folder that looks finished."""
    seen = _trials(tmp_path, 3, (0.0, 3.0), seed=0)
    assert all(not s.endswith(("complete", "interrupted")) for s in seen), seen


@pytest.mark.slow  # ~10-20 min: 20 real runs, each killed at a random time of its course
def test_killed_at_random_times_never_leaves_a_result_it_is_not(tmp_path):
    t0 = time.perf_counter()
    exp = _copy_example(tmp_path / "timing")
    cmd, env = _command(exp, tmp_path / "timing-out")
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    full = time.perf_counter() - t0
    assert done.returncode == 0 and _check_folder(tmp_path / "timing-out") == "complete"
    seen = _trials(tmp_path, 20, (0.5, full * 1.05), seed=1)
    print("\n".join(seen))
    assert len({s.split(": ")[1] for s in seen}) >= 2, seen  # (the kills fell at different stages)
