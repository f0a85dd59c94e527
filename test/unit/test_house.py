"""Bounds that keep the tree readable (issues 34 and 51).

- No module of ``rtabmap_ros2/`` longer than :data:`MAX_MODULE_LINES` lines: a module that grows
  past it is split along what it holds (as ``core/database.py`` was into its schema, batch and
  sensor blob modules).
- No import cycle among the modules of ``rtabmap_ros2/``, through any chain of modules, with
  imports under ``if TYPE_CHECKING:`` and imports inside functions counted: two steps that import
  each other cannot be read apart.
- ``bench/results/`` holds at most :data:`MAX_RESULTS_FILES` files: the latest run of each bench
  and the runs a README or docs figure rests on; earlier runs are listed in docs/benchmarks.md
  ("Earlier runs") and live in git history.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Optional

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = "rtabmap_ros2"
RESULTS = ROOT / "bench" / "results"

MAX_MODULE_LINES = 1100
MAX_RESULTS_FILES = 25


def module_names(root: Path, package: str) -> dict[str, Path]:
    """Dotted module name -> file of every module of ``package`` under ``root`` (a package by
    the name of its folder, from its ``__init__.py``)."""
    modules = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def _resolve(name: str, modules: dict[str, Path]) -> Optional[str]:
    """The module of ``modules`` that importing ``name`` runs last: ``name`` itself or the longest
    of its prefixes that is a module (None outside ``modules``)."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def imported_modules(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Modules of ``modules`` that module ``name`` (file ``path``) imports anywhere in its body:
    top level, under ``if TYPE_CHECKING:``, inside functions; absolute and relative imports.
    ``from P import x`` counts as an import of module ``P.x`` when there is one, else of ``P``."""
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = name.split(".") if is_package else name.split(".")[:-1]
                base_parts = base_parts[:len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base
                       for alias in node.names]
        else:
            continue
        found.update(t for t in (_resolve(target, modules) for target in targets) if t is not None)
    found.discard(name)
    return found


def import_cycle(graph: dict[str, set[str]]) -> Optional[list[str]]:
    """One cycle of the directed ``graph`` (module -> modules it imports) as [m0, m1, ..., m0],
    or None when it has none. Depth-first search: an edge back to a module still on the path
    closes a cycle, however many modules the chain goes through."""
    on_path: list[str] = []
    position: dict[str, int] = {}
    done: set[str] = set()

    def visit(node: str) -> Optional[list[str]]:
        position[node] = len(on_path)
        on_path.append(node)
        for target in sorted(graph.get(node, ())):
            if target in position:
                return on_path[position[target]:] + [target]
            if target not in done:
                cycle = visit(target)
                if cycle is not None:
                    return cycle
        on_path.pop()
        del position[node]
        done.add(node)
        return None

    for start in sorted(graph):
        if start not in done:
            cycle = visit(start)
            if cycle is not None:
                return cycle
    return None


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module -> modules of ``package`` it imports, for every module of ``package``."""
    modules = module_names(root, package)
    return {name: imported_modules(name, path, modules) for name, path in modules.items()}


def test_no_module_is_longer_than_the_bound():
    lengths = {path.relative_to(ROOT).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
               for path in module_names(ROOT, PACKAGE).values()}
    assert len(lengths) > 50  # the package was found
    too_long = {module: n for module, n in lengths.items() if n > MAX_MODULE_LINES}
    assert not too_long, (f"modules over MAX_MODULE_LINES = {MAX_MODULE_LINES} lines: {too_long}; split each "
                          "along what it holds")


def test_no_import_cycle_among_the_package_modules():
    graph = import_graph(ROOT, PACKAGE)
    assert "rtabmap_ros2.core.memory" in graph["rtabmap_ros2.core.local_map"]  # edges are found
    cycle = import_cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


def test_results_folder_holds_at_most_the_bound():
    files = sorted(p.name for p in RESULTS.rglob("*") if p.is_file())
    assert "summary.md" in files  # the folder was found
    assert len(files) <= MAX_RESULTS_FILES, (
        f"bench/results holds {len(files)} files, more than MAX_RESULTS_FILES = {MAX_RESULTS_FILES}: keep the "
        "latest run of each bench and those a README or docs figure rests on, list the rest in docs/benchmarks.md "
        f"'Earlier runs' and git rm them ({files})")


def test_import_cycle_is_found_through_a_chain_of_type_checking_and_relative_imports(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg.sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from . import c\n")
    (pkg / "sub" / "c.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..a import thing\n")
    graph = import_graph(tmp_path, "pkg")
    assert graph["pkg.a"] == {"pkg.sub.b"} and graph["pkg.sub.b"] == {"pkg.sub.c"}
    assert graph["pkg.sub.c"] == {"pkg.a"}
    assert import_cycle(graph) == ["pkg.a", "pkg.sub.b", "pkg.sub.c", "pkg.a"]
    (pkg / "sub" / "c.py").write_text("import pkg.sub\n")  # the chain broken: no cycle
    assert import_cycle(import_graph(tmp_path, "pkg")) is None


def test_the_local_mapper_is_what_loop_validation_reads_of_the_local_map(tmp_path):
    # The local_map <-> loop_validation circle was cut by a Protocol: loop_validation names what it
    # reads of the local map, local_map's LocalMapper must keep providing it.
    from rtabmap_ros2.core.database import Database
    from rtabmap_ros2.core.local_map import LocalMapper
    from rtabmap_ros2.core.loop_validation import LocalMapView
    from rtabmap_ros2.core.memory import Memory
    from rtabmap_ros2.core.params import Params

    members = {name for name in vars(LocalMapView) if not name.startswith("_")} | set(LocalMapView.__annotations__)
    assert members == {"planar", "T_world_local", "kept_poses", "map_pose", "new_node_pose"}
    with Database(tmp_path / "map.db") as db:
        memory = Memory(Params(), db, binary_descriptors=True)
        mapper = LocalMapper(Params(), memory)
        assert not [name for name in members if not hasattr(mapper, name)]
        memory.close()


def test_summary_dates_a_result_by_its_own_field_else_its_last_commit_not_the_checkout(tmp_path):
    import json
    import os
    import subprocess
    import sys
    from datetime import datetime, timezone
    sys.path.insert(0, str(ROOT / "bench"))
    from run_all import _written

    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    dated, undated = tmp_path / "dated.json", tmp_path / "undated.json"
    dated.write_text(json.dumps({"written": "2026-01-02 03:04 UTC"}))
    undated.write_text("{}")
    subprocess.run([*git, "add", "."], check=True)
    env = {**os.environ, "GIT_COMMITTER_DATE": "2026-02-03T04:05:00+00:00"}
    subprocess.run([*git, "commit", "-q", "-m", "results"], check=True, env=env)
    os.utime(undated, (0, 0))   # a checkout's mtime: not when the result was written
    assert _written(dated, {"written": "2026-01-02 03:04 UTC"}) == "2026-01-02 03:04 UTC"
    assert _written(undated, {}) == "2026-02-03 04:05 UTC"
    undated.write_text('{"a": 1}')   # changed since its commit: the file's own time
    now = datetime.now(timezone.utc)
    assert abs((datetime.strptime(_written(undated, {"a": 1}), "%Y-%m-%d %H:%M UTC").replace(tzinfo=timezone.utc)
                - now).total_seconds()) < 120
