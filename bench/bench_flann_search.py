"""Does RTAB-Map's approximate word search explain where the conformance setting parts from it? (issue 32)

The reference quantises ORB descriptors with FLANN randomized kd-trees (Kp/NNStrategy 1: the
descriptors' 256 bits as floats, 4 trees, 32 checks, the index rebuilt when the vocabulary doubled,
Kp/FlannRebalancingFactor 2). This bench runs ``detect`` at the conformance setting
(``config/rtabmap_reference.yaml``) with the vocabulary searched that way instead of by our inverted
file: OpenCV's FLANN kd-trees over the words present at the last rebuild, the words added since
searched exactly (OpenCV does not expose FLANN's incremental ``addPoints``, which puts them in the
trees), then the two nearest of both go to the NNDR test as usual. It prints the same comparison with
the reference as ``bench_lcd.py`` (merges, vocabulary, same decisions, P / R / R@100P) and the median
number of WM locations sharing a word with the image (ours and the reference's).

    python bench/bench_flann_search.py --sets lcd ms:31

Results: ``bench/results/flann_search.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_lcd import CONFORMANCE, DEFAULT_DATA, DEFAULT_FRAMES, RESULTS, _f, _rows, prepare, run_reference, summarise  # noqa: E402

TREES, CHECKS, REBALANCING = 4, 32, 2.0


def flann_search(vocabulary, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """2-NN (Hamming distances (N,2), word ids (N,2)): kd-trees over the words at the last rebuild,
    exact search over the words added since."""
    import cv2
    import faiss

    n = len(vocabulary)
    state = vocabulary.__dict__.setdefault("_kd_state", {"built": 0})
    if n >= 2 and n >= REBALANCING * state["built"]:
        words = vocabulary._descriptors[:n]
        state.update(index=cv2.flann_Index(np.unpackbits(words, axis=1).astype(np.float32),
                                           dict(algorithm=1, trees=TREES)),
                     ids=vocabulary._ids[:n].copy(), built=n)
        state["max_id"] = int(state["ids"].max())
    distances, ids = [], []
    recent = np.arange(n)
    if state["built"]:
        # Squared L2 over 0/1 floats is the Hamming distance; 3 neighbours, as words may have left.
        rows, d = state["index"].knnSearch(np.unpackbits(descriptors, axis=1).astype(np.float32), 3,
                                           params=dict(checks=CHECKS))
        found = np.where(rows >= 0, state["ids"][np.maximum(rows, 0)], -1)
        ok = (rows >= 0) & vocabulary.present(found.ravel()).reshape(found.shape)
        distances.append(np.where(ok, d, np.inf))
        ids.append(np.where(ok, found, -1))
        recent = np.flatnonzero(vocabulary._ids[:n] > state["max_id"])
    if recent.size >= 2:
        d, slots = faiss.knn_hamming(descriptors, np.ascontiguousarray(vocabulary._descriptors[recent]), 2)
        distances.append(d.astype(np.float64))
        ids.append(vocabulary._ids[recent][slots])
    if not distances:
        q = len(descriptors)
        return np.full((q, 2), np.inf, np.float32), np.full((q, 2), -1, np.int64)
    d, i = np.hstack(distances), np.hstack(ids)
    order = np.argsort(d, axis=1, kind="stable")[:, :2]
    d, i = np.take_along_axis(d, order, 1), np.take_along_axis(i, order, 1)
    return d.astype(np.float32), np.where(np.isfinite(d), i, -1)


def child(argv: list[str]) -> int:
    """``detect`` with the FLANN-style search (run in a subprocess, as bench_lcd runs detect)."""
    from rtabmap_ros2.cli import cli
    from rtabmap_ros2.core.vocabulary import Vocabulary

    Vocabulary._search = flann_search
    return cli.main(["detect", *argv])


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        return child(sys.argv[2:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", nargs="+", default=["lcd", "ms:31"], help="lcd, ms:SEED, sim:SEED")
    parser.add_argument("--frames", type=int, default=DEFAULT_FRAMES)
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="where sequences and runs are kept (bench_lcd's)")
    args = parser.parse_args()
    results = []
    for spec in args.sets:
        ds = prepare(spec, args.frames, args.data)
        ref = run_reference(ds, args.data, rerun=False)
        out = args.data / f"flann_{spec.replace(':', '_')}"
        subprocess.run([sys.executable, __file__, "--child", str(ds.images), "--out", str(out), "--no-progress",
                        *CONFORMANCE, "--set", "vocabulary.index=flat"], check=True, stdout=subprocess.DEVNULL)
        res = summarise(ds, out, ref)
        nonzero = {side: float(np.median([_f(r, "likelihood_nonzero") for r in _rows(path)]))
                   for side, path in (("ours", out / "detections.csv"), ("reference", ref / "reference_stats.csv"))}
        res["likelihood_nonzero_median"] = nonzero
        results.append(res)
        o, r, c = res["ours"], res["reference"], res["conformance"]
        print(f"{spec}: FLANN-style search P {o['precision']:.3f} R {o['recall']:.3f} R@100P "
              f"{o['recall_at_100_precision']:.3f}, merges {o['merged']} (reference {r['merged']}, "
              f"x{c['merges_ratio'] or 0:.2f}), vocabulary {o['vocabulary_size']} (x{c['vocabulary_ratio']:.2f}), "
              f"same decision {res['decision_agreement']:.3f}, locations sharing a word (median) "
              f"{nonzero['ours']:.0f} vs {nonzero['reference']:.0f}; reference P {r['precision']:.3f} "
              f"R {r['recall']:.3f} R@100P {r['recall_at_100_precision']:.3f}", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / "flann_search.json"
    path.write_text(json.dumps({"sets": args.sets, "frames": args.frames, "results": results}, indent=1))
    print(f"-> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
