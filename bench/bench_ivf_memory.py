"""Does the vocabulary's IVF index hold on to memory at a constant vocabulary size? (issue 14)

At a fixed WM the vocabulary's size is steady, but its content turns over: every frame adds the
new location's words and removes those of the location transferred to LTM. The words come from
places the robot sees, so which inverted lists they land in drifts. faiss keeps every inverted list
in a std::vector. ``remove_ids`` shrinks a list's size but not its capacity, so each list
keeps the largest size it has ever had. The question is whether that adds up.

This benchmark builds the vocabulary's IVF the way ``Vocabulary`` does (``_build_ivf``: binary
256-bit words, hash-table direct map, ``_ivf_lists`` lists). It then replays frames: remove the
oldest ``--turnover`` words and add as many new ones, with the word clusters drifting. It prints
RSS every 1,000 frames and the growth per frame, with the index's word count (constant). Synthetic
words: clusters of random 256-bit centres with ~1/8 of the bits flipped.

Result on this machine (450 k words, 1,342 lists, 170 words per frame, 8,000 frames), two runs:
0.07 and 0.09 KB per frame (RSS ~142 -> ~143 MB). The IVF's turnover is not what makes the long run's RSS grow at a
fixed WM (docs/benchmarks.md).

Usage: ``python bench/bench_ivf_memory.py [--quick] [--words 450000] [--frames 8000] [--turnover 170]``
(quick: 100 k words, 2,000 frames); writes ``bench/results/ivf_memory.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import deque
from pathlib import Path

import numpy as np

from process_memory import rss_mb
from rtabmap_ros2.core.vocabulary import _build_ivf, _ivf_lists, _remove_ids


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--words", type=int, default=450_000, help="vocabulary size (~WM 1,500-2,300)")
    parser.add_argument("--frames", type=int, default=8000)
    parser.add_argument("--turnover", type=int, default=170, help="words removed and added per frame")
    parser.add_argument("--clusters", type=int, default=4000)
    parser.add_argument("--quick", action="store_true", help="100 k words, 2,000 frames")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "ivf_memory.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.words, args.frames = 100_000, 2000

    rng = np.random.default_rng(0)
    centres = rng.integers(0, 256, (args.clusters, 32), dtype=np.uint8)

    def words(n: int) -> np.ndarray:
        flips = (rng.integers(0, 256, (n, 32), dtype=np.uint8) & rng.integers(0, 256, (n, 32), dtype=np.uint8)
                 & rng.integers(0, 256, (n, 32), dtype=np.uint8))  # each bit flipped with p = 1/8
        return centres[rng.integers(0, args.clusters, n)] ^ flips

    ids = np.arange(args.words, dtype=np.int64)
    index, _ = _build_ivf(words(args.words), ids, True, _ivf_lists(args.words), nprobe=32)
    live = deque(ids.tolist())
    next_id = args.words
    start = rss_mb()
    print(f"IVF of {index.ntotal} words, {index.nlist} lists: RSS {start:.1f} MB", flush=True)
    marks = [(0, start)]
    for frame in range(1, args.frames + 1):
        gone = np.array([live.popleft() for _ in range(args.turnover)], np.int64)
        _remove_ids(index, gone)
        if frame % 50 == 0:  # the places seen drift: 1 % of the clusters replaced
            centres[rng.integers(0, args.clusters, args.clusters // 100)] = rng.integers(
                0, 256, (args.clusters // 100, 32), dtype=np.uint8)
        new = np.arange(next_id, next_id + args.turnover, dtype=np.int64)
        next_id += args.turnover
        index.add_with_ids(words(args.turnover), new)
        live.extend(new.tolist())
        if frame % 1000 == 0:
            marks.append((frame, rss_mb()))
            print(f"frame {frame}: {index.ntotal} words, RSS {marks[-1][1]:.1f} MB", flush=True)
    (f0, r0), (f1, r1) = marks[len(marks) // 2], marks[-1]
    result = {"words": args.words, "lists": int(index.nlist), "turnover_per_frame": args.turnover,
              "frames": args.frames, "rss_mb_start": round(start, 1), "rss_mb_end": round(r1, 1),
              "rss_kb_per_frame": round(1000.0 * (r1 - start) / args.frames, 3),
              "rss_kb_per_frame_second_half": round(1000.0 * (r1 - r0) / max(1, f1 - f0), 3),
              "rss_mb_every_1000_frames": [{"frame": f, "rss_mb": round(r, 1)} for f, r in marks]}
    print(f"RSS growth at a constant vocabulary: {result['rss_kb_per_frame']:.2f} KB/frame overall, "
          f"{result['rss_kb_per_frame_second_half']:.2f} KB/frame over the second half")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
