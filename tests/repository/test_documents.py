"""The documents in the repository say what the code does: the command-line reference is what the
parsers print (generated, and kept equal to them here), every page the README points at exists, and
nothing points outside the repository."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]


def generator():
    spec = importlib.util.spec_from_file_location("cli_reference", REPOSITORY / "tools" / "cli_reference.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cli_reference_is_what_the_parsers_print(monkeypatch):
    monkeypatch.setenv("COLUMNS", "37")  # the reference is made at its own width, whatever the terminal's
    written = (REPOSITORY / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    assert written == generator().text(), \
        "docs/reference/cli.md differs from the parsers: run python tools/cli_reference.py"


def test_the_cli_reference_has_every_command_of_the_listing():
    from labcal.commands import COMMANDS

    written = (REPOSITORY / "docs" / "reference" / "cli.md").read_text(encoding="utf-8")
    titled = set(re.findall(r"^## labcal (\S+)", written, re.M))
    assert titled >= set(COMMANDS)


def test_every_page_the_readme_points_at_exists():
    readme = (REPOSITORY / "README.md").read_text(encoding="utf-8")
    targets = re.findall(r"\]\(((?:docs|schemas)/[^)#]+)", readme)
    assert len(targets) >= 10
    missing = [target for target in targets if not (REPOSITORY / target).exists()]
    assert not missing


def test_no_document_points_outside_the_repository():
    pages = [REPOSITORY / "README.md", *sorted((REPOSITORY / "docs").rglob("*.md"))]
    outside = [page.name for page in pages if "../shared" in page.read_text(encoding="utf-8")]
    assert not outside


def test_no_code_cites_an_issue_number_a_clone_cannot_read():
    import labcal
    import labcal.drivers
    import labcal.sim

    folders = {Path(package.__file__).resolve().parent for package in (labcal, labcal.drivers, labcal.sim)}
    files = [path for folder in folders for path in folder.rglob("*.py")]
    files += [path for folder in ("tests", "benchmarks", "tools")
              for path in (REPOSITORY / folder).rglob("*.py")]
    cited = [f"{path.name}:{number}" for path in files
             for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if re.search(r"\bissues? \d+", line) and path.name != "test_documents.py"]
    assert not cited, "cite the paper, the manual or docs/ instead: " + ", ".join(cited)
