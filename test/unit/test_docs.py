"""The documentation matches the code: the architecture names every module that exists and
nothing that does not, docs/parameters.md is the current `params --markdown` output, and the
README's links lead somewhere."""

from __future__ import annotations

import re
from pathlib import Path

from rtabmap_ros2.cli import cli

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "rtabmap_ros2"


def _architecture_tree() -> str:
    text = (REPO / "docs" / "architecture.md").read_text()
    return text.split("## Modules", 1)[1].split("```")[1]


def test_the_architecture_names_every_module_and_only_modules_that_exist():
    named = set(re.findall(r"[\w.]+\.py", _architecture_tree()))
    modules = {p.name for p in PACKAGE.rglob("*.py")
               if p.name != "__init__.py" and p.name != "__main__.py" and not p.name.startswith("cmd_")}
    shipped = modules | {p.name for p in (REPO / "launch").glob("*.py")}
    assert not named - shipped, f"named in docs/architecture.md but not in the code: {sorted(named - shipped)}"
    assert not modules - named, f"modules missing from docs/architecture.md: {sorted(modules - named)}"


def test_the_parameter_reference_is_current(capsys):
    assert cli.main(["params", "--markdown"]) == 0
    generated = capsys.readouterr().out
    assert (REPO / "docs" / "parameters.md").read_text() == generated, \
        "docs/parameters.md is stale: rtabmap-ros2 params --markdown > docs/parameters.md"


def test_the_readme_and_docs_link_to_files_that_exist():
    for page in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)\)", page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name} links to a missing {target}"
