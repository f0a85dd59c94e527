#!/usr/bin/env python3
"""How far a map's loop closure links are from the truth, by kind, and what the 2D ICP refinement does
to them: a map database made by ``rtabmap-ros2 map ... --stats CSV`` of the simulator's bags (or any
bags with a ground truth file).

Per kind of link (appearance-based: the ``--stats`` rows' ``loop_closure_id``; proximity detection:
the other loop closures; neighbour links) the signed mean error along x (the robot's axis) and y, its standard error,
the RMS, and the errors over the link's own standard deviations. Then every second appearance-based
loop closure registered again from the database's signatures: the visual estimate alone (PnP), with
the ICP refinement (the to node's scan matched onto the from node's), the ICP with the scans' roles
swapped, and the mean of the two ICP ways.

    rtabmap-ros2 map bench/data/sim5_seed77/session_* --db /tmp/m.db --stats /tmp/m.csv \\
        --config config/rtabmap.yaml
    python3 bench/bench_loop_links.py --db /tmp/m.db --stats /tmp/m.csv \\
        --ground-truth bench/data/sim5_seed77/ground_truth.txt
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rtabmap_ros2.core import registration, transforms  # noqa: E402
from rtabmap_ros2.core.database import Database  # noqa: E402
from rtabmap_ros2.core.global_map import load_global_map  # noqa: E402
from rtabmap_ros2.core.icp import icp_fit  # noqa: E402
from rtabmap_ros2.core.params import Params, default_config_path  # noqa: E402
from rtabmap_ros2.errors import RegistrationError  # noqa: E402
from rtabmap_ros2.io.trajectory import read_tum  # noqa: E402


def appearance_pairs(stats_csv: Path) -> set[tuple[int, int]]:
    with open(stats_csv, newline="") as f:
        return {(int(r["location_id"]), int(r["loop_closure_id"])) for r in csv.DictReader(f)
                if int(r["loop_closure_id"] or 0) > 0}


def summary(errors: list[np.ndarray]) -> str:
    e = np.array(errors)
    mean, sem, rms = e.mean(axis=0), e.std(axis=0) / np.sqrt(len(e)), np.sqrt((e ** 2).mean(axis=0))
    return (f"{len(e):>4} links, x / y mean {mean[0]:+.2f} / {mean[1]:+.2f} cm (s.e. {sem[0]:.2f} / {sem[1]:.2f}), "
            f"RMS {rms[0]:.2f} / {rms[1]:.2f} cm, yaw RMS {rms[2]:.3f} deg")


def link_error(truth: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``truth^-1 * T``'s x and y (cm) and yaw (deg)."""
    E = transforms.relative(truth, T)
    return np.array([100 * E[0, 3], 100 * E[1, 3], np.degrees(transforms.yaw_of(E))])


def stored_links(db: Path, appearance: set[tuple[int, int]], at: dict, params: Params) -> None:
    gmap = load_global_map(db, params)
    kinds: dict[str, list] = {"appearance": [], "proximity": [], "neighbour": []}
    normalised: dict[str, list] = {kind: [] for kind in kinds}
    for link in gmap.links:
        a, b = gmap.stamps_ns[link.from_id], gmap.stamps_ns[link.to_id]
        if a not in at or b not in at:
            continue
        if not link.type.is_loop_closure:
            kind = "neighbour"
        elif {(link.from_id, link.to_id), (link.to_id, link.from_id)} & appearance:
            kind = "appearance"
        else:
            kind = "proximity"
        error = link_error(transforms.relative(at[a], at[b]), link.T_from_to)
        kinds[kind].append(error)
        sigma = 1.0 / np.sqrt(np.diag(link.information)[[0, 1, 5]])
        normalised[kind].append(np.abs(error) / (sigma * [100.0, 100.0, 180.0 / np.pi]))
    print("Links of the map against the truth (error = truth^-1 * link):")
    for kind, errors in kinds.items():
        if errors:
            median = np.median(np.array(normalised[kind]), axis=0)
            print(f"  {kind:<11} {summary(errors)}; |error| / std dev median x {median[0]:.2f}, y {median[1]:.2f}, "
                  f"yaw {median[2]:.2f}")


def registered_again(db_path: Path, appearance: set[tuple[int, int]], at: dict, params: Params) -> None:
    reg_params = replace(params.registration, planar=True)
    ways: dict[str, list] = {"visual (PnP) alone": [], "ICP (default)": [], "ICP, scans swapped": [],
                             "ICP, mean of both ways": []}
    with Database(db_path, read_only=True) as db:
        for new_id, old_id in sorted(appearance)[::2]:
            new, old = db.load_signatures([new_id, old_id])
            if new.scan is None or old.scan is None:
                continue
            ids = np.concatenate([new.word_ids, old.word_ids]).tolist()
            words = db.load_words(ids)
            descriptors = (tuple(np.stack([words[w] for w in s.word_ids.tolist()]) for s in (new, old))
                           if all(w in words for w in ids) else None)
            try:
                visual = registration.register(new, old, replace(reg_params, icp_refine=False), descriptors=descriptors)
            except RegistrationError:
                continue
            source, target = old.scan.points_base(), new.scan.points_base()
            gate, iterations = reg_params.icp_max_correspondence_distance, reg_params.icp_iterations
            forward = icp_fit(source, target, visual.T_from_to, None, gate, iterations).T
            swapped = transforms.inverse(icp_fit(target, source, transforms.inverse(forward), None, gate, iterations).T)
            xa, xb = np.array(transforms.to_xy_yaw(forward)), np.array(transforms.to_xy_yaw(swapped))
            yaw_difference = math.remainder(xb[2] - xa[2], 2 * math.pi)
            mean = transforms.from_xy_yaw((xa[0] + xb[0]) / 2, (xa[1] + xb[1]) / 2, xa[2] + yaw_difference / 2)
            truth = transforms.relative(at[new.stamp_ns], at[old.stamp_ns])
            for name, T in zip(ways, (visual.T_from_to, forward, swapped, mean)):
                ways[name].append(link_error(truth, T))
    print("Appearance-based loop closures registered again (every second one):")
    for name, errors in ways.items():
        if errors:
            print(f"  {name:<24} {summary(errors)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--db", type=Path, required=True, help="map database")
    parser.add_argument("--stats", type=Path, required=True, help="the map command's --stats CSV")
    parser.add_argument("--ground-truth", type=Path, required=True, help="TUM trajectory of the base")
    parser.add_argument("--config", type=Path, default=default_config_path(), help="parameters the map was made with")
    args = parser.parse_args(argv)
    params = Params.from_yaml(args.config)
    truth = read_tum(args.ground_truth)
    at = dict(zip(truth.stamps_ns.tolist(), truth.poses))
    appearance = appearance_pairs(args.stats)
    stored_links(args.db, appearance, at, params)
    registered_again(args.db, appearance, at, params)
    return 0


if __name__ == "__main__":
    sys.exit(main())
