"""Incremental vocabulary: nearest-neighbour index choice (2013 §III-A, Alg. 2 lines 4-5).

Reproduces the LIBRARIES.md table on this machine, with real-ish ORB descriptors: GFTT+ORB
(the default extractor, up to 1,000 features) on rotated / scaled / shifted crops of the photos
bundled with scikit-image (nothing is downloaded). The vocabulary is grown the way the mapper grows
it (``Vocabulary.quantize`` frame after frame, each frame also a location of the inverted index),
until 20 k and 200 k words. Queries: frames of held-out warps (400 descriptors each, 2-NN + NNDR).

Compared, in the same run, one thread unless said:

* baseline: faiss ``IndexBinaryFlat`` (exact) with the NNDR test;
* ``Vocabulary(index=flat)``: exact brute force over the word buffer;
* ``Vocabulary(index=kdtree)``: FLANN's randomized kd-trees (4 trees, 32 checks; the default), its
  search on one thread (RTAB-Map's) and on two (``vocabulary.kdtree_search_threads``, the default);
* the paper's baseline: rebuilding a FLANN index (LSH, binary) over all words, at 200 k.

Reported: query ms (median over query frames), add 400 / remove 400 ms, agreement of the
match/new decision and matched id with the exact search (``agreement``; ``match``: share of queries
the exact search matches; ``recall``: share of those given the same word), and ``scores()`` ms.

Growth run (``growth_frames``): the mapper's per-frame cost. Frames of 400 GFTT+ORB descriptors
(alternately new views and revisits) are quantised from 0 to ~100 k words; reported: max, p99 and
median ``quantize`` ms per frame, for the exact search, the kd-trees rebuilt in the frame that
doubles them (RTAB-Map's) and rebuilt in the background (the default).

Usage: ``python bench/bench_vocabulary.py [--quick] [--growth-only]`` (quick: 20 k words only;
growth-only: skip the index tables). Writes ``bench/results/vocabulary.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import faiss
import numpy as np
import skimage.data

from rtabmap_ros2.core.features import FeatureExtractor
from rtabmap_ros2.core.params import FeatureParams, VocabularyParams
from rtabmap_ros2.core.vocabulary import Vocabulary

RESULTS = Path(__file__).resolve().parent / "results" / "vocabulary.json"
PHOTOS = ("astronaut", "camera", "coffee", "chelsea", "rocket", "brick", "grass", "gravel", "moon",
          "clock", "coins", "hubble_deep_field", "immunohistochemistry", "retina", "stereo_motorcycle",
          "cell", "page", "text", "colorwheel")
WARP_SIZE = (480, 640)  # rows, cols of a synthetic frame
FEATURES_PER_FRAME = 1000
QUERY_SIZE = 400
QUERY_FRAMES = 16
REPEATS = 15
FLANN_INDEX_LSH = 6
FLANN_LSH = dict(algorithm=FLANN_INDEX_LSH, table_number=12, key_size=20, multi_probe_level=2)


def load_photos() -> list[np.ndarray]:
    """Grey uint8 versions of the scikit-image sample photos available offline."""
    photos = []
    for name in PHOTOS:
        image = getattr(skimage.data, name)()
        if isinstance(image, tuple):
            image = image[0]
        if image.ndim == 3:
            image = cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY)
        photos.append(np.ascontiguousarray(image, np.uint8))
    return photos


def random_view(rng: np.random.Generator, n_photos: int) -> tuple[int, float, float, float, float]:
    """A view of a photo: (photo index, rotation deg, scale factor, shift x, shift y as image ratios)."""
    return (int(rng.integers(n_photos)), rng.uniform(-30.0, 30.0), rng.uniform(0.8, 2.5),
            rng.uniform(-0.25, 0.25), rng.uniform(-0.25, 0.25))


def nearby_view(view, rng: np.random.Generator):
    """The same place seen again: +-3 deg, +-5 % scale, +-2 % shift (a revisit, or the next frame)."""
    photo, angle, scale, dx, dy = view
    return (photo, angle + rng.uniform(-3, 3), scale * rng.uniform(0.95, 1.05),
            dx + rng.uniform(-0.02, 0.02), dy + rng.uniform(-0.02, 0.02))


def render(photos, view) -> np.ndarray:
    """The 480x640 frame of a view (reflected borders)."""
    rows, cols = WARP_SIZE
    index, angle, scale, dx, dy = view
    photo = photos[index]
    h, w = photo.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), angle, scale * max(rows / h, cols / w) * 0.8)
    M[:, 2] += (cols / 2 - w / 2 + dx * cols, rows / 2 - h / 2 + dy * rows)
    return cv2.warpAffine(photo, M, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)


def warped_frames(photos, rng: np.random.Generator, views: list | None = None):
    """Endless frames of random views; the views are appended to ``views`` when given."""
    while True:
        view = random_view(rng, len(photos))
        if views is not None:
            views.append(view)
        yield render(photos, view)


def grow_vocabulary(frames, extractor, target_sizes):
    """Quantise frames (each one a location) until each target size; yield (size, snapshot, stats)."""
    vocab = Vocabulary(VocabularyParams(), binary=True, background_rebuild=False)
    times, location = [], 0
    targets = list(target_sizes)
    while targets:
        descriptors = extractor.extract(next(frames)).descriptors
        t0 = time.perf_counter()
        word_ids, _ = vocab.quantize(descriptors)
        times.append(time.perf_counter() - t0)
        location += 1
        vocab.add_references(location, word_ids)
        if len(vocab) >= targets[0]:
            size = targets.pop(0)
            ids = vocab.word_ids()[:size]
            words = vocab.descriptors_of(ids)
            yield size, ids, words, vocab, {"frames": location, "quantize_ms_median": 1e3 * float(np.median(times)),
                                            "quantize_ms_max": 1e3 * float(np.max(times))}


def exact_decisions(words, ids, queries, nndr):
    """Exact 2-NN + NNDR with IndexBinaryFlat (baseline): word id or -1 per query row."""
    index = faiss.IndexBinaryFlat(8 * words.shape[1])
    index.add(words)
    distances, slots = index.search(queries, 2)
    ok = distances[:, 0] < nndr * distances[:, 1]
    return np.where(ok, ids[slots[:, 0]], -1)


def median_ms(fn, repeats=REPEATS) -> float:
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(samples))


def add_remove_ms(vocab: Vocabulary, extra: np.ndarray) -> tuple[float, float]:
    """Median ms of add_words(400) and remove_words(400) (the same words, added then removed)."""
    adds, removes = [], []
    for _ in range(REPEATS):
        ids = np.arange(vocab.next_word_id, vocab.next_word_id + extra.shape[0], dtype=np.int64)
        t0 = time.perf_counter()
        vocab.add_words(ids, extra)
        t1 = time.perf_counter()
        vocab.remove_words(ids)
        t2 = time.perf_counter()
        adds.append(t1 - t0)
        removes.append(t2 - t1)
    return 1e3 * float(np.median(adds)), 1e3 * float(np.median(removes))


def bench_size(size, ids, words, queries, extra, quick) -> list[dict]:
    """All index configurations on one vocabulary snapshot."""
    nndr = VocabularyParams().nndr
    rows = []
    exact = [exact_decisions(words, ids, q, nndr) for q in queries]
    match_rate = float(np.mean(np.concatenate(exact) >= 0))

    # Baseline: faiss IndexBinaryFlat (exact), add via add(), remove via remove_ids (O(n) shift).
    flat = faiss.IndexBinaryFlat(8 * words.shape[1])
    flat.add(words)
    query_ms = float(np.median([median_ms(lambda q=q: flat.search(q, 2), 3) for q in queries]))
    add_ms = median_ms(lambda: flat.add(extra))
    n0 = size
    remove = np.arange(n0, n0 + extra.shape[0], dtype=np.int64)

    def remove_tail():
        flat.remove_ids(faiss.IDSelectorArray(remove.size, faiss.swig_ptr(remove)))
    flat.reset()
    flat.add(words)
    removes = []
    for _ in range(REPEATS):
        flat.add(extra)
        t0 = time.perf_counter()
        remove_tail()
        removes.append(time.perf_counter() - t0)
    rows.append(dict(words=size, index="faiss IndexBinaryFlat (baseline)", lists=0, nprobe=0, build_s=0.0,
                     query_ms=query_ms, add_ms=add_ms, remove_ms=1e3 * float(np.median(removes)),
                     agreement=1.0, match_rate=match_rate, match_recall=1.0))
    print_row(rows[-1])

    for kind, threads in (("flat", 1), ("kdtree", 1), ("kdtree", 2)):
        params = replace(VocabularyParams(), index=kind, kdtree_search_threads=threads)
        vocab = Vocabulary(params, binary=True, next_word_id=int(ids.max()) + 1, background_rebuild=False)
        t0 = time.perf_counter()
        vocab.add_words(ids, words)
        vocab.match(queries[0][:1])  # kdtree: the words enter the trees (a build) at the first search
        build_s = time.perf_counter() - t0
        decisions = [vocab.match(q) for q in queries]
        agreement = float(np.mean(np.concatenate(decisions) == np.concatenate(exact)))
        matched = np.concatenate(exact) >= 0
        recall = float(np.mean(np.concatenate(decisions)[matched] == np.concatenate(exact)[matched]))
        query_ms = float(np.median([median_ms(lambda q=q: vocab.match(q), 3) for q in queries]))
        add_ms, remove_ms = add_remove_ms(vocab, extra)
        label = f"Vocabulary {kind}" + (f", {threads} search thread{'s' * (threads > 1)}" if kind == "kdtree" else "")
        rows.append(dict(words=size, index=label, lists=0, nprobe=0,
                         build_s=build_s, query_ms=query_ms, add_ms=add_ms, remove_ms=remove_ms,
                         agreement=agreement, match_rate=match_rate, match_recall=recall))
        print_row(rows[-1])
        vocab.close()
    return rows


def bench_flann(size, words, ids, queries) -> dict:
    """The paper's approach: rebuild a FLANN index (LSH for binary words) before every frame."""
    nndr = VocabularyParams().nndr
    t0 = time.perf_counter()
    index = cv2.flann_Index(words, FLANN_LSH)
    build_s = time.perf_counter() - t0
    exact = np.concatenate([exact_decisions(words, ids, q, nndr) for q in queries])
    decisions, times = [], []
    for q in queries:
        t0 = time.perf_counter()
        slots, distances = index.knnSearch(q, 2, params={})
        times.append(time.perf_counter() - t0)
        distances = distances.astype(np.float64)
        ok = (slots[:, 1] >= 0) & (distances[:, 0] < nndr * distances[:, 1])
        decisions.append(np.where(ok, ids[np.maximum(slots[:, 0], 0)], -1))
    decisions = np.concatenate(decisions)
    agreement = float(np.mean(decisions == exact))
    recall = float(np.mean(decisions[exact >= 0] == exact[exact >= 0]))
    return dict(words=size, index="cv2.flann LSH rebuilt per frame (paper)", lists=0, nprobe=0,
                build_s=build_s, query_ms=1e3 * float(np.median(times)), add_ms=1e3 * build_s,
                remove_ms=1e3 * build_s, agreement=agreement, match_rate=float(np.mean(exact >= 0)),
                match_recall=recall)


def bench_scores(vocab: Vocabulary, frames, extractor, n_locations: int) -> dict:
    """scores() over n_locations locations: the real ones of the build plus synthetic ones.

    Synthetic locations reuse the words of real frames (frame t shares most of its words with
    frames t-1..t-5, like a robot seeing the same place), so words are referenced several times.
    """
    rng = np.random.default_rng(7)
    all_ids = vocab.word_ids()
    location = 10_000_000
    base = rng.choice(all_ids, QUERY_SIZE)
    for _ in range(n_locations):
        keep = rng.random(QUERY_SIZE) < 0.8
        base = np.where(keep, base, rng.choice(all_ids, QUERY_SIZE))
        location += 1
        vocab.add_references(location, base)
    queries = []
    for _ in range(QUERY_FRAMES):
        word_ids = vocab.match(extractor.extract(next(frames)).descriptors[:QUERY_SIZE])
        word_ids = np.concatenate([word_ids[word_ids >= 0], base[: QUERY_SIZE // 2]])
        ids, counts = np.unique(word_ids, return_counts=True)
        queries.append(dict(zip(ids.tolist(), counts.tolist())))
    ms = float(np.median([median_ms(lambda q=q: vocab.scores(q), 3) for q in queries]))
    candidates = set(range(10_000_001, 10_000_001 + n_locations // 2))
    ms_candidates = float(np.median([median_ms(lambda q=q: vocab.scores(q, candidates), 3) for q in queries]))
    hits = float(np.median([len(vocab.scores(q)) for q in queries]))
    refs = [len(vocab.references(w)) for w in all_ids[:: max(1, all_ids.size // 5000)]]
    return dict(locations=n_locations, query_words=QUERY_SIZE, scores_ms=ms, scores_candidates_ms=ms_candidates,
                locations_scored=hits, mean_references_per_word=float(np.mean(refs)))


GROWTH_WORDS = 100_000
GROWTH_FRAMES = 600  # descriptor frames prepared (enough to reach GROWTH_WORDS)
# (label, vocabulary.index, kd-trees rebuilt in the background)
GROWTH_CONFIGS = (  # label, index, background rebuild, search threads
    ("exact search (flat)", "flat", False, 1),
    ("kdtree, rebuilt in the frame, 1 thread (RTAB-Map)", "kdtree", False, 1),
    ("kdtree, rebuilt in the background, 1 thread", "kdtree", True, 1),
    ("kdtree, rebuilt in the background, 2 threads (default)", "kdtree", True, 2),
)


def growth_descriptors(photos, extractor) -> list[np.ndarray]:
    """QUERY_SIZE descriptors per frame, alternately a new view and a revisit of a mapped one."""
    rng = np.random.default_rng(11)
    views: list = []
    frames = warped_frames(photos, rng, views)
    out = []
    for i in range(GROWTH_FRAMES):
        if i % 2 and views:
            image = render(photos, nearby_view(views[rng.integers(len(views))], rng))
        else:
            image = next(frames)
        out.append(extractor.extract(image).descriptors[:QUERY_SIZE])
    return out


def growth_frames(frames: list[np.ndarray], index: str, background: bool, threads: int) -> dict:
    """Per-frame quantize ms while the vocabulary grows from 0 to GROWTH_WORDS words."""
    vocab = Vocabulary(replace(VocabularyParams(), index=index, kdtree_search_threads=threads), binary=True,
                       background_rebuild=background)
    times = []
    for location, descriptors in enumerate(frames, 1):
        t0 = time.perf_counter()
        word_ids, _ = vocab.quantize(descriptors)
        times.append(time.perf_counter() - t0)
        vocab.add_references(location, word_ids)
        if len(vocab) >= GROWTH_WORDS:
            break
    rebuilds = vocab._kdtree.rebuilds if vocab._kdtree is not None else 0
    vocab.close()
    ms = 1e3 * np.asarray(times)
    slowest = np.argsort(ms)[::-1][:5]
    return dict(frames=len(times), words=len(vocab), rebuilds=rebuilds,
                quantize_ms_max=float(ms.max()), quantize_ms_p99=float(np.percentile(ms, 99)),
                quantize_ms_median=float(np.median(ms)), frames_over_100ms=int((ms > 100).sum()),
                slowest=[(int(i) + 1, round(float(ms[i]), 1)) for i in slowest])


def rss_mb() -> dict:
    current = 0.0
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                current = float(line.split()[1]) / 1024
    return dict(rss_mb=current, max_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def print_row(r: dict) -> None:
    print(f"{r['words']:>7} {r['index']:<40} {r['lists']:>5} {r['nprobe']:>6} {r['build_s']:>7.2f} "
          f"{r['query_ms']:>8.2f} {r['add_ms']:>8.2f} {r['remove_ms']:>9.2f} {r['agreement']:>9.4f} "
          f"{r['match_rate']:>6.2f} {r['match_recall']:>7.4f}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="20 k words only")
    parser.add_argument("--growth-only", action="store_true", help="growth run only")
    args = parser.parse_args(argv)
    default_threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)  # the node runs one quantisation at a time, on a shared machine

    photos = load_photos()
    extractor = FeatureExtractor(FeatureParams(max_features=FEATURES_PER_FRAME))
    t_start = time.perf_counter()
    frames = growth_descriptors(photos, extractor)
    print(f"growth run: {QUERY_SIZE} descriptors per frame up to {GROWTH_WORDS} words "
          f"(default OpenMP threads: {default_threads})")
    print(f"{'configuration':<56} {'frames':>6} {'rebuilds':>8} {'max_ms':>8} {'p99_ms':>8} {'median':>7} {'>100ms':>6}")
    growth_runs = []
    for label, index, background, threads in GROWTH_CONFIGS:
        run = growth_frames(frames, index, background, threads)
        run.update(config=label, index=index, background_rebuild=background, search_threads=threads)
        growth_runs.append(run)
        print(f"{label:<56} {run['frames']:>6} {run['rebuilds']:>8} {run['quantize_ms_max']:>8.1f} "
              f"{run['quantize_ms_p99']:>8.1f} {run['quantize_ms_median']:>7.1f} {run['frames_over_100ms']:>6}"
              f"  slowest {run['slowest'][:3]}", flush=True)
    if args.growth_only:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(dict(
            machine=dict(python=sys.version.split()[0], faiss=faiss.__version__, opencv=cv2.__version__,
                         processor=platform.processor(), default_threads=default_threads,
                         load_average=list(os.getloadavg())),
            growth_only=True, query_size=QUERY_SIZE, growth_runs=growth_runs), indent=2))
        print(f"total {time.perf_counter() - t_start:.0f} s; wrote {RESULTS}")
        return 0
    query_rng = np.random.default_rng(99)
    new_frames = warped_frames(photos, query_rng)
    extra = extractor.extract(next(new_frames)).descriptors[:QUERY_SIZE]
    build_views: list = []
    sizes = (20_000,) if args.quick else (20_000, 200_000)

    header = (f"{'words':>7} {'index':<40} {'lists':>5} {'nprobe':>6} {'build_s':>7} {'query_ms':>8} "
              f"{'add_ms':>8} {'remove_ms':>9} {'agreement':>9} {'match':>6} {'recall':>7}")
    rows, growth, scores = [], [], {}
    for size, ids, words, vocab, stats in grow_vocabulary(
            warped_frames(photos, np.random.default_rng(1), build_views), extractor, sizes):
        # Queries: half revisits (a view near one already mapped), half never-seen views.
        revisits = [render(photos, nearby_view(build_views[query_rng.integers(len(build_views))], query_rng))
                    for _ in range(QUERY_FRAMES - QUERY_FRAMES // 2)]
        unseen = [next(new_frames) for _ in range(QUERY_FRAMES // 2)]
        queries = [extractor.extract(frame).descriptors[:QUERY_SIZE] for frame in revisits + unseen]
        stats.update(words=size, **rss_mb())
        growth.append(stats)
        print(f"\nvocabulary grown to {size} words in {stats['frames']} frames: quantize median "
              f"{stats['quantize_ms_median']:.1f} ms, max {stats['quantize_ms_max']:.0f} ms")
        print(header)
        rows += bench_size(size, ids, words, queries, extra, args.quick)
        if size == sizes[-1]:
            if not args.quick:
                rows.append(bench_flann(size, words, ids, queries))
                print_row(rows[-1])
            scores = bench_scores(vocab, warped_frames(photos, np.random.default_rng(5)), extractor,
                                  2000 if args.quick else 5000)
    print(f"\nscores() (Eq. 1 numerator): {scores}")
    memory = rss_mb()
    print(f"process RSS {memory['rss_mb']:.0f} MB (max {memory['max_rss_mb']:.0f} MB); "
          f"total {time.perf_counter() - t_start:.0f} s")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(dict(
        machine=dict(python=sys.version.split()[0], faiss=faiss.__version__, opencv=cv2.__version__,
                     processor=platform.processor(), threads=1, default_threads=default_threads,
                     load_average=list(os.getloadavg())),
        quick=args.quick, query_size=QUERY_SIZE, query_frames=QUERY_FRAMES, growth_runs=growth_runs,
        growth=growth,
        rows=rows, scores=scores, memory=memory), indent=2))
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
