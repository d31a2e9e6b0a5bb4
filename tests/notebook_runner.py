"""Execute a notebook of notebooks/ and return its `RESULTS` dict (shared by tests/notebooks/).

The notebook must fill a JSON-serialisable dict `RESULTS`; a cell printing it behind a
marker is appended, the notebook runs in a fresh kernel from the repository root, and
the dict is read back from that cell's output. `env` sets environment variables for the
kernel (e.g. `FLEXDYN_FULL=1` for the full grid) and restores them afterwards.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MARK = "__RESULTS_JSON__"


def notebook_path(name: str) -> Path:
    return ROOT / "notebooks" / name


def assert_stored_without_outputs(path: Path) -> None:
    import nbformat

    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            assert cell.outputs == []
            assert cell.execution_count is None


def run_notebook(path: Path, *, env: dict | None = None, timeout: int = 600) -> dict:
    import nbclient
    import nbformat

    nb = nbformat.read(path, as_version=4)
    nb.cells.append(nbformat.v4.new_code_cell(f"import json as _j\nprint({MARK!r} + _j.dumps(RESULTS))"))
    env = dict(env or {})
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        client = nbclient.NotebookClient(
            nb, kernel_name="python3", timeout=timeout, resources={"metadata": {"path": str(ROOT)}}
        )
        client.execute()
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    for out in nb.cells[-1].outputs:
        if out.get("name") == "stdout" and MARK in out["text"]:
            return json.loads(out["text"].split(MARK, 1)[1])
    raise AssertionError(f"{path.name}: RESULTS not printed")
