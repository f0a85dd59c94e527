"""Run every benchmark (``bench/bench_*.py``) and collect the results into one markdown table.

Usage (from anywhere; paths are relative to the repository)::

    python bench/run_all.py --quick          # every bench with --quick (minutes)
    python bench/run_all.py                  # full runs (long: see each bench's docstring)
    python bench/run_all.py --only slam vocabulary --quick
    python bench/run_all.py --summary-only   # no run: rebuild summary.md from bench/results/*.json

Each ``bench/bench_<topic>.py`` runs in its own process (``python bench/bench_<topic>.py
[--quick]``) and writes ``bench/results/<topic>.json``; its output goes to
``bench/results/logs/<topic>.log``. A bench that fails or times out is recorded and the others
still run; the command then exits with status 1. Afterwards ``bench/results/summary.md`` holds a
table of the runs (status, mode, wall time) and, per topic, the numbers of its JSON file: scalars
as a name / value table, lists of records as tables (one row per record), dicts of records as
tables keyed by name. ``bench/results/run_all.json`` keeps the last run's statuses.

The machine's other load matters for timings: the summary records the load average at the start.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from rtabmap_ros2.core.params import flatten

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"
LOG_DIR = RESULTS_DIR / "logs"
SUMMARY = RESULTS_DIR / "summary.md"
RUN_RECORD = RESULTS_DIR / "run_all.json"
DEFAULT_TIMEOUT_S = 3600.0
# Summary tables: rows and columns shown per table (the JSON file has everything).
MAX_ROWS = 30
MAX_COLUMNS = 12
MAX_CELL_CHARS = 60


def bench_scripts(only: list[str] | None = None) -> list[Path]:
    """``bench_*.py`` files, sorted; ``only`` filters by topic (``slam`` or ``bench_slam``)."""
    scripts = sorted(BENCH_DIR.glob("bench_*.py"))
    if only:
        wanted = {name.removeprefix("bench_").removesuffix(".py") for name in only}
        missing = wanted - {topic(s) for s in scripts}
        if missing:
            raise SystemExit(f"no bench script for {sorted(missing)}; found {[topic(s) for s in scripts]}")
        scripts = [s for s in scripts if topic(s) in wanted]
    return scripts


def topic(script: Path) -> str:
    return script.stem.removeprefix("bench_")


def run_bench(script: Path, quick: bool, timeout_s: float) -> dict:
    """Run one bench in a subprocess; never raises. Returns its status record."""
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    log_path = LOG_DIR / f"{topic(script)}.log"
    cmd = [sys.executable, str(script)] + (["--quick"] if quick else [])
    t0 = time.perf_counter()
    record = {"topic": topic(script), "mode": "quick" if quick else "full", "command": " ".join(cmd),
              "log": str(log_path.relative_to(BENCH_DIR.parent))}
    with open(log_path, "w") as log:
        try:
            proc = subprocess.run(cmd, cwd=BENCH_DIR.parent, stdout=log, stderr=subprocess.STDOUT,
                                  timeout=timeout_s, check=False)
            record["returncode"] = proc.returncode
            record["status"] = "ok" if proc.returncode == 0 else f"failed (exit {proc.returncode})"
        except subprocess.TimeoutExpired:
            record["returncode"] = None
            record["status"] = f"timeout after {timeout_s:.0f} s"
    record["wall_s"] = round(time.perf_counter() - t0, 1)
    return record


# -- summary -----------------------------------------------------------------------------------
def _fmt(value) -> str:
    """A table cell: numbers with 3-4 significant digits, long text shortened."""
    if isinstance(value, bool) or value is None:
        text = str(value)
    elif isinstance(value, int):
        text = f"{value:,}" if abs(value) >= 10_000 else str(value)
    elif isinstance(value, float):
        if value != value:
            text = "nan"
        elif value == 0 or 1e-3 <= abs(value) < 1e4:
            text = f"{value:.4g}"
        elif abs(value) >= 1e4:
            text = f"{value:,.0f}"
        else:
            text = f"{value:.2e}"
    elif isinstance(value, (list, tuple)):
        text = "[" + ", ".join(_fmt(v) for v in value) + "]"
    else:
        text = str(value)
    text = text.replace("|", "\\|").replace("\n", " ")
    return text if len(text) <= MAX_CELL_CHARS else text[:MAX_CELL_CHARS - 1] + "…"


def _is_records(value) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _is_keyed_records(value) -> bool:
    return (isinstance(value, dict) and len(value) > 1
            and all(isinstance(v, dict) and v and not any(isinstance(x, (dict, list)) and x for x in v.values())
                    for v in value.values()))


def _table(header: list[str], rows: list[list]) -> list[str]:
    header = header[:MAX_COLUMNS]
    lines = ["| " + " | ".join(_fmt(h) for h in header) + " |", "|" + "---|" * len(header)]
    for row in rows[:MAX_ROWS]:
        lines.append("| " + " | ".join(_fmt(c) for c in row[:MAX_COLUMNS]) + " |")
    if len(rows) > MAX_ROWS:
        lines.append(f"\n({len(rows) - MAX_ROWS} more rows in the JSON file)")
    return lines


def _records_table(records: list[dict]) -> list[str]:
    flat = [flatten(r) for r in records]
    columns: list[str] = []
    for r in flat:
        columns += [k for k in r if k not in columns and not _is_records(r[k])]
    lines = _table(columns, [[r.get(c, "") for c in columns] for r in flat])
    if len(columns) > MAX_COLUMNS:
        lines.append(f"\n(columns not shown: {', '.join(columns[MAX_COLUMNS:])})")
    return lines


def topic_section(name: str, data) -> list[str]:
    """Markdown for one results file: scalars first, then one table per list / dict of records."""
    lines: list[str] = []
    if _is_records(data):
        return _records_table(data)
    if not isinstance(data, dict):
        return [f"`{_fmt(data)}`"]
    scalars, tables = {}, []

    def visit(value, path: str) -> None:
        if _is_records(value):
            tables.append((path, _records_table(value)))
        elif _is_keyed_records(value):
            tables.append((path, _records_table([{"name": k, **flatten(v)} for k, v in value.items()])))
        elif isinstance(value, dict):
            for k, v in value.items():
                visit(v, f"{path}.{k}" if path else str(k))
        else:
            scalars[path] = value

    visit(data, "")
    if scalars:
        lines += _table(["result", "value"], [[k, v] for k, v in scalars.items()])
    for path, table in tables:
        lines += ["", f"**{path}**", ""] + table
    return lines


def _written(path: Path, data) -> str:
    """When a result was written: its own ``written`` field, else the time of the last commit of
    the file when it is unchanged since (a checkout sets every file's mtime to the clone's time),
    else the file's mtime."""
    if isinstance(data, dict) and isinstance(data.get("written"), str):
        return data["written"]
    git = ["git", "-C", str(path.parent)]
    try:
        unchanged = subprocess.run([*git, "diff", "--quiet", "HEAD", "--", path.name], capture_output=True).returncode == 0
        stamp = subprocess.run([*git, "log", "-1", "--format=%ct", "--", path.name],
                               capture_output=True, text=True).stdout.strip() if unchanged else ""
    except OSError:  # no git
        stamp = ""
    seconds = int(stamp) if stamp else path.stat().st_mtime
    return f"{datetime.fromtimestamp(seconds, timezone.utc):%Y-%m-%d %H:%M} UTC"


def write_summary(records: list[dict] | None = None) -> Path:
    """``summary.md`` from every ``results/*.json`` (and the run records, if any)."""
    if records is None and RUN_RECORD.is_file():
        records = json.loads(RUN_RECORD.read_text()).get("runs", [])
    records = records or []
    by_topic = {r["topic"]: r for r in records}
    lines = ["# Benchmark results", "",
             f"Collected by `python bench/run_all.py` on {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC "
             f"({platform.platform()}, Python {platform.python_version()}, {os.cpu_count()} CPUs). "
             "Medians unless named otherwise; each topic's JSON file has every number.", ""]
    if records:
        load = records[0].get("load_average_at_start")
        lines += ["## Runs", ""]
        if load is not None:
            lines += [f"Load average (1 min) when the runs started: {load:.1f} on {os.cpu_count()} CPUs.", ""]
        lines += _table(
            ["bench", "mode", "status", "wall (s)", "log"],
            [[r["topic"], r["mode"], r["status"], r["wall_s"], r["log"]] for r in records]) + [""]
    for path in sorted(RESULTS_DIR.glob("*.json")):
        if path == RUN_RECORD:
            continue
        name = path.stem
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            lines += [f"## {name}", "", f"unreadable: {exc}", ""]
            continue
        written = _written(path, data)
        status = by_topic.get(name, {}).get("status")
        note = f"; last run: {status}" if status else ""
        lines += [f"## {name}", "", f"`bench/results/{path.name}`, written {written}{note}.", ""]
        lines += topic_section(name, data) + [""]
    SUMMARY.write_text("\n".join(lines))
    return SUMMARY


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="pass --quick to every bench")
    parser.add_argument("--only", nargs="+", metavar="TOPIC", help="run these benches only (e.g. slam vocabulary)")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                        help=f"per-bench time limit (default {DEFAULT_TIMEOUT_S:.0f} s)")
    parser.add_argument("--summary-only", action="store_true", help="run nothing, rebuild summary.md")
    args = parser.parse_args(argv)
    if args.summary_only:
        print(f"wrote {write_summary()}")
        return 0
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    records = []
    for script in bench_scripts(args.only):
        print(f"{topic(script)}: running {'--quick' if args.quick else 'full'} ...", flush=True)
        record = run_bench(script, args.quick, args.timeout)
        record["load_average_at_start"] = load
        records.append(record)
        print(f"{topic(script)}: {record['status']} in {record['wall_s']:.0f} s (log {record['log']})", flush=True)
    RUN_RECORD.write_text(json.dumps({"quick": args.quick, "load_average_at_start": load, "runs": records},
                                     indent=2) + "\n")
    print(f"wrote {write_summary(records)}")
    failed = [r["topic"] for r in records if r["status"] != "ok"]
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
