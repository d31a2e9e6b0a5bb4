"""The documentation cannot rot: the site (mkdocs.yml, docs/, the API reference generated from
the docstrings) builds with `mkdocs build --strict` (any warning fails: a broken link or
anchor, a page missing from the nav, a docstring that does not render), README.md stays
short, every relative link of the Markdown pages points to a file that exists, and every
public name of `flexdyn` and `identify` has its entry in the API reference."""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: README.md's budget: what the package is, the Quickstart, a usage example, the command
#: line, the layout and links; everything else lives in docs/
README_MAX_BYTES = 12 * 1024

#: the two Quickstart commands, byte for byte (CI runs the second: .ci/run)
QUICKSTART = (
    "python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/identify diagnose "
    "identify/examples/pendulum_friction/experiment.toml",
    "python3 -m venv .venv && .venv/bin/pip install -e '.[test]' && .venv/bin/python -m pytest",
)


def markdown_pages() -> list[Path]:
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "benchmarks" / "README.md"]
    return pages + sorted((ROOT / "docs").rglob("*.md"))


def test_site_builds_strict(tmp_path):
    pytest.importorskip("mkdocs", reason="the test extra installs mkdocs: pip install -e '.[test]'")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # (mkdocs-material's notice, not a warning of ours)
    run = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT,  # mkdocs.yml's snippet paths are relative to the repository root
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, f"mkdocs build --strict failed:\n{run.stdout}\n{run.stderr}"
    assert (tmp_path / "site" / "api" / "flexdyn" / "index.html").is_file()


def test_readme_is_short_and_keeps_the_quickstart():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    size = len(text.encode("utf-8"))
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes (at most {README_MAX_BYTES}): move detail to docs/"
    for command in QUICKSTART:
        assert f"```bash\n{command}\n```" in text, command
    assert QUICKSTART[1] in (ROOT / ".ci" / "run").read_text(encoding="utf-8")


def _links(text: str) -> list[str]:
    """The targets of a Markdown page's inline links and images, outside code."""
    text = re.sub(r"^(```|~~~).*?^\1", "", text, flags=re.S | re.M)  # fenced blocks
    text = re.sub(r"`[^`\n]*`", "", text)  # code spans
    return re.findall(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)


@pytest.mark.parametrize("page", markdown_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_existing_files(page):
    assert page.is_file(), page
    missing = []
    for target in _links(page.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (https:, mailto:) or an anchor on the page itself
        path = target.split("#", 1)[0]
        if not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)}: links to missing files: {missing}"


#: a repository path named in the text (`identify/_model/residuals.py`, `tests/diagnose_cases.py`)
REPO_PATH = re.compile(r"`((?:flexdyn|identify|tests|benchmarks|notebooks|docs)/[\w/.-]*\w)`")


@pytest.mark.parametrize(
    "page",
    [p for p in markdown_pages() if p.name != "CHANGELOG.md"],  # (history names old paths)
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_named_repository_paths_exist(page):
    """The docs say where things are (`identify/_diagnose/split.py`): those files must exist,
    so that a moved module shows up here."""
    text = page.read_text(encoding="utf-8")
    missing = sorted({m for m in REPO_PATH.findall(text) if not (ROOT / m.split("::")[0]).exists()})
    assert not missing, f"{page.relative_to(ROOT)} names paths that do not exist: {missing}"


def _public_names(package: str) -> list[str]:
    """The names `package/__init__.py` re-exports (`from .x import name as name`, at the top
    level or, for a lazily imported package, under `if TYPE_CHECKING:`)."""
    tree = ast.parse((ROOT / package / "__init__.py").read_text(encoding="utf-8"))
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level >= 1:
            names += [a.asname for a in node.names if a.asname and not a.asname.startswith("_")]
    return names


@pytest.mark.parametrize("package", ["flexdyn", "identify"])
def test_api_reference_lists_every_public_name(package):
    api = "\n".join(p.read_text(encoding="utf-8") for p in sorted((ROOT / "docs" / "api").glob("*.md")))
    # (an entry rendered from another object names the public one as its `heading`)
    missing = [
        n
        for n in _public_names(package)
        if not re.search(rf"^::: {package}(\.\w+)*\.{n}\b", api, re.M)
        and not re.search(rf'^\s+heading: "{package}\.{n}"$', api, re.M)
    ]
    assert not missing, f"docs/api/ has no '::: {package}.NAME' entry for {missing}"
