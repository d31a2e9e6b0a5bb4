"""The output folder of a run (`identify.cli.folder`): claimed and locked before the work,
written through a staging folder, committed by renames so that, whenever the run stops,
the folder holds the previous complete result, the new complete one, or no result file,
never a result beside another run's files."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

import identify.cli.folder as folder_module
from identify.cli.folder import OutputFolder, deferred_interrupt, write_atomic
from identify.cli.output import LOCK_FILE, MARKER, RESULT_FILE, _Refused

PLOTS = ("fit.png", "fit_residuals.png", "parameters_by_log.png")


def _run(out: Path, tag: str, plots: tuple[str, ...]) -> None:
    """One run writing `result.json` (naming its `files`) and `plots`, each holding `tag`."""
    with OutputFolder.claim(out, [], force=False) as folder:
        stage = folder.staging()
        for name in plots:
            (stage / name).write_text(tag)
        (stage / RESULT_FILE).write_text(json.dumps({"tag": tag, "files": sorted([*plots, RESULT_FILE])}))
        folder.commit(RESULT_FILE)


def _state(out: Path) -> str:
    """'none' (no result file), or the tag of the complete result the folder holds;
    fails if the result file sits beside files of another run or misses one of its own."""
    if not (out / RESULT_FILE).exists():
        return "none"
    doc = json.loads((out / RESULT_FILE).read_text())
    present = {p.name for p in out.iterdir() if p.is_file() and p.name in (*PLOTS, RESULT_FILE)}
    assert present == set(doc["files"]), (present, doc)
    assert all((out / n).read_text() == doc["tag"] for n in doc["files"] if n != RESULT_FILE)
    return doc["tag"]


@pytest.fixture(autouse=True)
def _patch_output_files(monkeypatch):
    # the commands' own file names are those of the plots here
    import identify.cli.output as output_module

    names = (MARKER, LOCK_FILE, RESULT_FILE, *PLOTS)
    monkeypatch.setattr(output_module, "output_files", lambda: names)
    monkeypatch.setattr(folder_module, "output_files", lambda: names)


def test_a_run_replaces_the_previous_one_whole(tmp_path):
    out = tmp_path / "out"
    _run(out, "old", PLOTS)
    assert _state(out) == "old"
    _run(out, "new", PLOTS[:2])  # the new run writes fewer plots: the old third one goes
    assert _state(out) == "new" and not (out / PLOTS[2]).exists()
    assert "status: complete" in (out / MARKER).read_text()
    assert not list(out.glob(".identify-staging-*"))


def test_stopped_at_any_step_of_the_commit_the_folder_is_old_or_new_or_empty(tmp_path):
    """The run stopped (as by SIGKILL) before each of its file operations in turn (the
    claim makes 3, the commit 6): the folder holds the old result, no result, or the new
    one, in that order, never a mixture (`_state`)."""
    states = []
    for call in range(12):
        out = tmp_path / str(call)
        _run(out, "old", PLOTS)
        calls = [0]
        with pytest.MonkeyPatch.context() as patch:
            for name in ("replace", "unlink"):
                real = getattr(os, name)

                def counting(*args, real=real, **kwargs):
                    calls[0] += 1
                    if calls[0] > call:
                        raise SystemExit("killed")
                    return real(*args, **kwargs)

                patch.setattr(folder_module.os, name, counting)
            try:
                _run(out, "new", PLOTS[:2])
            except SystemExit:
                pass
        states.append(_state(out))
    assert states[0] == "old" and "none" in states and states[-1] == "new", states
    assert states == sorted(states, key=["old", "none", "new"].index), states


def test_a_second_run_is_refused_while_the_first_holds_the_folder(tmp_path):
    out = tmp_path / "out"
    with OutputFolder.claim(out, [], force=False):
        with pytest.raises(_Refused, match=r"another identify run is writing there \(pid \d+, since "):
            OutputFolder.claim(out, [], force=False)
    OutputFolder.claim(out, [], force=False).release()  # released: claimable again


def test_a_folder_left_by_a_run_killed_before_its_marker_is_claimable(tmp_path):
    """SIGKILL between the claim's lock and its marker leaves the folder holding only the
    lock file (seen in `test_cli_kill` under load); the next run may write there, and a
    folder with our names but neither marker nor lock is still refused."""
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_FILE).write_text("pid 1, since 2026-12-07 16:00:00\n")
    OutputFolder.claim(out, [], force=False).release()
    other = tmp_path / "other"
    other.mkdir()
    (other / RESULT_FILE).write_text("not from identify")
    with pytest.raises(_Refused, match=MARKER):
        OutputFolder.claim(other, [], force=False)


def test_abandoning_a_folder_it_created_removes_it(tmp_path):
    out = tmp_path / "new" / "out"
    folder = OutputFolder.claim(out, [], force=False)
    folder.staging()
    folder.abandon("failed")
    assert not out.exists() and (tmp_path / "new").is_dir()


def test_write_atomic_leaves_old_or_new(tmp_path):
    path = tmp_path / "result.json"
    path.write_text("old")

    def killed(*args):
        raise SystemExit("killed")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(folder_module.os, "replace", killed)
        with pytest.raises(SystemExit):
            write_atomic(path, "new")
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["result.json"]
    write_atomic(path, "new")
    assert path.read_text() == "new"


def test_ctrl_c_waits_for_the_renames():
    done = []
    with pytest.raises(KeyboardInterrupt):
        with deferred_interrupt():
            os.kill(os.getpid(), signal.SIGINT)
            done.append("renamed")
    assert done == ["renamed"]


def test_a_folder_that_cannot_be_written_is_refused_at_the_claim(tmp_path, monkeypatch):
    """(A read-only folder, as a user other than root meets it: `test_cli` checks it for real.)"""

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(folder_module.tempfile, "mkstemp", denied)
    with pytest.raises(_Refused, match=r"cannot write into .*out: Permission denied. Choose another folder"):
        OutputFolder.claim(tmp_path / "out", [], force=False)


def test_an_out_folder_that_is_a_symlink_loop_is_refused_with_a_message(tmp_path):
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    with pytest.raises(_Refused, match="cannot use --out .*loop: it exists and is not a folder"):
        OutputFolder.claim(loop, [tmp_path / "experiment.toml"], force=False)
