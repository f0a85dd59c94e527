"""``rtabmap-ros2 merge A.db B.db [C.db ...] --out merged.db``: maps made apart, merged into one.

Several robots map at the same time, each into its own database (the node on its own computer,
or ``map`` on its bags), or one robot maps on different days into different files: ``merge``
combines them as RTAB-Map's ``rtabmap-reprocess "a.db;b.db" out.db`` does. Every stored node of
every input is replayed through ``map``'s loop (:func:`rtabmap_ros2.cli.cmd_map.map_datasets`:
the same detector, verification and inter-session merge checks), each input session as a session
(map) of the output, inputs in the order given and their sessions by id: nodes keep their stamps
and never overwrite each other, whatever the stamps (robots mapping at once included). Then one
global optimisation, and a summary: per input its sessions and nodes, every node found again,
which pairs of sessions merged with how many loop closures, and for those left apart the best
candidate's reason.

The inputs are opened read-only and checked before the output is created (see
:func:`rtabmap_ros2.io.merge.inspect_inputs`). Their stored features are reused (so their
descriptors and feature / vocabulary parameters must agree, and the merge takes those parameters
from them); ``--reextract`` extracts features again from the stored images with the merge's
parameters instead. Rehearsal is off during the replay: the inputs' nodes were rehearsed when they
were mapped, and each one is kept. The output is written under a temporary name and renamed when
complete; ``--stats FILE.csv`` writes one row per node as ``map --stats`` does.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rtabmap_ros2.cli.common_args import add_param_arguments

# Rehearsal (2013 §III-B) off during the replay: merge a node into the previous one only when
# Eq. 1 reaches 1 (identical words), which the inputs' own rehearsal already did.
REPLAY_REHEARSAL_SIMILARITY = 1.0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "merge", help="merge map databases made apart (several robots or runs) into one",
        description=__doc__.splitlines()[0])
    parser.add_argument("databases", nargs="+", metavar="DB", help="input map databases (read only), in this order")
    parser.add_argument("--out", required=True, metavar="FILE", help="merged database (new)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--reextract", action="store_true",
                        help="extract features again from the stored images, with the merge's parameters "
                        "(inputs made with other descriptors or feature settings)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--stats", metavar="FILE.csv", default=None,
                        help="write one row per replayed node, as map --stats")
    add_param_arguments(parser, default_config="rtabmap.yaml")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os

    from rtabmap_ros2.cli.cmd_map import map_datasets, statistics_csv
    from rtabmap_ros2.cli.common_args import params_from_args
    from rtabmap_ros2.core import files
    from rtabmap_ros2.core.rtabmap import Rtabmap
    from rtabmap_ros2.errors import DatabaseError
    from rtabmap_ros2.io.merge import StoredFeatures, StoredSession, inspect_inputs, merge_report, word_parameters_of

    params = params_from_args(args)
    out = Path(args.out).expanduser().absolute()
    stats_path = Path(args.stats).expanduser() if args.stats else None
    if not out.parent.is_dir():
        raise DatabaseError(f"--out {out}: folder {out.parent} does not exist")
    if stats_path is not None and not stats_path.parent.is_dir():
        raise DatabaseError(f"--stats {stats_path}: folder {stats_path.parent} does not exist")
    inputs = inspect_inputs(args.databases, args.reextract)
    if out.exists():
        if any(os.path.samefile(out, item.path) for item in inputs):
            raise DatabaseError(f"--out {out} is one of the inputs: inputs are never written, choose a new file")
        if not args.overwrite:
            raise DatabaseError(f"--out {out} already exists: choose a new file, or --overwrite to replace it")
    if not args.reextract:
        params, changed = word_parameters_of(inputs, params)
        if changed:
            print("features and vocabulary parameters taken from the inputs (their stored features are reused; "
                  "--reextract to use the config's): " + ", ".join(changed))
    params = params.with_value("memory.rehearsal_similarity", REPLAY_REHEARSAL_SIMILARITY)
    for item in inputs:
        print(f"input {item.label}: {len(item.sessions)} session(s), {item.nodes} nodes")

    features = None if args.reextract else StoredFeatures(params.features)
    datasets = [StoredSession(item, map_id, features) for item in inputs for map_id in item.sessions]
    t0 = time.perf_counter()
    with files.new_path(out, exclusive=not args.overwrite) as tmp:
        with Rtabmap(params, tmp) as rtabmap, statistics_csv(stats_path) as on_statistics:
            if features is not None:
                rtabmap.extractor = features
            sessions = map_datasets(rtabmap, [(d.name, d) for d in datasets], progress=not args.no_progress,
                                    on_statistics=on_statistics)
            rtabmap.flush()
        for suffix in ("-wal", "-shm"):   # an old --out's WAL must not be applied to the new file
            Path(f"{out}{suffix}").unlink(missing_ok=True)
    replay_s = time.perf_counter() - t0
    params.to_yaml(out.with_name(out.stem + ".params.yaml"))

    origins = []
    for dataset in datasets:
        parts = [s for s in sessions if s.source == dataset.name]
        origins.append((dataset, [s.map_id for s in parts], sum(s.frames - s.nodes for s in parts),
                        sum(s.skipped for s in parts)))
    report = merge_report(out, origins, params)
    _print_report(report)
    print(f"total: {len(inputs)} databases, {sum(s.input_nodes for s in report.sessions)} input nodes -> "
          f"{report.nodes} nodes in {len(report.components)} component(s), replay {replay_s:.1f} s, "
          f"{time.perf_counter() - t0:.1f} s in all -> {out}" + (f", statistics -> {stats_path}" if stats_path else ""))
    return 0


def _print_report(report) -> None:
    for s in report.sessions:
        status = "every node present" if s.missing == 0 and not s.merged_by_rehearsal and not s.skipped else (
            f"{s.present} present, {s.merged_by_rehearsal} merged by rehearsal, {s.skipped} skipped as bad data, "
            f"{s.missing} MISSING")
        maps = ", ".join(str(m) for m in s.output_map_ids)
        print(f"{s.source} session {s.input_map_id}: {s.input_nodes} nodes -> output session {maps}: {status}")
    for pair in report.pairs:
        if pair.loop_closures:
            print(f"sessions {pair.map_a} and {pair.map_b}: merged, {pair.loop_closures} inter-session loop closures")
        elif not pair.same_component:
            print(f"sessions {pair.map_a} and {pair.map_b}: not merged: {pair.reason}")
    components = "; ".join("sessions " + ", ".join(map(str, maps)) for maps in report.components)
    print(f"global optimisation: {report.nodes} nodes, {len(report.components)} component(s) ({components}), "
          f"chi2 {report.chi2_initial:.6g} -> {report.chi2_final:.6g} in {report.optimization_time_s:.2f} s")
