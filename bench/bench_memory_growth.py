"""Where RSS grows at a constant WM (issue 14): the sessions of DIR mapped with WM fixed at
``--wm`` locations (Rtabmap/MemoryThr, no T_time: deterministic), sampled every ``--every`` frames.

Each sample: RSS and its split (``process_memory.memory_breakdown_mb``), the vocabulary's size,
the inverted index's words held by two or more locations and their location entries, the links
in RAM (those touching STM/WM) and the gtsam objects cached for them, and the kept poses. With
``--trim``, glibc's ``malloc_trim(0)`` runs at each sample and RSS is given before and after it
(how much of RSS is freed memory glibc holds).

Usage: ``python bench/bench_memory_growth.py --data DIR [--wm 1500] [--every 300] [--trim]
[--out FILE.json]`` (DIR: ``rtabmap-ros2 simulate --sessions 10``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from process_memory import memory_breakdown_mb, rss_mb
from rtabmap_ros2.cli.cmd_map import map_datasets
from rtabmap_ros2.core import optimizer
from rtabmap_ros2.core.heap import release_free_heap
from rtabmap_ros2.core.params import Params, default_config_path
from rtabmap_ros2.core.rtabmap import Rtabmap
from rtabmap_ros2.io.bag import BagDataset


def sample(rtabmap: Rtabmap, frame: int, wm_size: int) -> dict:
    """One sample of the figures above."""
    vocabulary = rtabmap.memory.vocabulary
    shared = vocabulary._shared
    return {"frame": frame, "wm_size": wm_size, "rss_mb": round(rss_mb(), 1), **memory_breakdown_mb(),
            "vocabulary_words": len(vocabulary), "shared_words": len(shared),
            "shared_word_entries": sum(len(locations) for locations in shared.values()),
            "links_in_ram": len(rtabmap.memory.graph.links()), "gtsam_cached": len(optimizer._GTSAM_CACHE),
            "kept_poses": len(rtabmap.local.kept_poses)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="folder of session bags (session_1, ...)")
    parser.add_argument("--wm", type=int, default=1500, help="WM size (Rtabmap/MemoryThr)")
    parser.add_argument("--every", type=int, default=300, help="frames between samples")
    parser.add_argument("--trim", action="store_true", help="malloc_trim(0) at each sample (glibc)")
    parser.add_argument("--out", type=Path, default=None, help="results JSON")
    args = parser.parse_args()
    params = (Params.from_yaml(default_config_path()).with_value("memory.time_threshold_ms", 0)
              .with_value("memory.max_wm_size", args.wm))
    bags = sorted((b for b in args.data.iterdir() if b.is_dir() and b.name.startswith("session_")),
                  key=lambda b: int(b.name.rsplit("_", 1)[1]))
    samples: list[dict] = []
    frames = [0]
    with tempfile.TemporaryDirectory() as work, Rtabmap(params, Path(work) / "map.db") as rtabmap:
        def on_stats(stats) -> None:
            frames[0] += 1
            if frames[0] % args.every:
                return
            row = sample(rtabmap, frames[0], stats.wm_size)
            if args.trim:
                release_free_heap()
                row["rss_mb_after_trim"] = round(rss_mb(), 1)
            samples.append(row)
            print(json.dumps(row), flush=True)

        map_datasets(rtabmap, [(b.name, BagDataset(b, sync=params.sync)) for b in bags], progress=False,
                     on_statistics=on_stats, print_line=lambda line: print(line, flush=True))
    result = {"data": str(args.data), "wm": args.wm, "every": args.every, "trim": args.trim,
              "samples": samples}
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
