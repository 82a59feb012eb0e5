"""Retrieval benchmark on an ordered image folder with a loop-closure truth matrix.

``lcv-replay bench retrieval IMAGES_DIR --truth-matrix FILE`` runs the whole front end (descriptor,
PCA, binary codes, Hamming prefilter, L2 re-rank) with the PCA/ITQ fit on the whole set, then
scores each backend in each retrieval mode (``--mode paper --mode ranked``; each mode describes
with the engine it selects):

* a **query** is a frame ``q`` with at least one true match ``m`` (truth matrix, either triangle)
  with ``q - m > Δt``; frames without one are not queries for recall;
* **recall@1** / **recall@N_r**: fraction of queries whose best / any of the top ``N_r`` candidates
  is a true match;
* **candidate precision**: true candidates / all candidates emitted (every frame's list);
* ``exhaustive_recall_at_*``: the same recall from a plain L2 nearest-neighbour search over every
  eligible frame, without the Hamming prefilter (what the prefilter costs: the ceiling);
* **speed**: ``descriptor_warmup_s`` (build + first call) and ``descriptor_frames_per_s``, the
  median over several timed passes, after warm-up, of ``describe()`` on decoded images (resize,
  normalisation, network, pooling).
"""

from __future__ import annotations

import dataclasses
import logging
import re
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from lcv_replay.errors import RetrievalError
from lcv_replay.records import LoopCandidate
from lcv_replay.retrieval.config import RetrievalConfig

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff")


@dataclass(frozen=True)
class RetrievalScores:
    """Recall and precision of one run (see the module docstring)."""

    queries: int
    recall_at_1: float
    recall_at_k: float
    candidate_precision: float
    candidates: int
    true_candidates: int


@dataclass(frozen=True)
class BackendReport:
    """One backend's row of the benchmark (the JSON object written per backend)."""

    backend: str
    mode: str
    engine: str
    dim: int
    queries: int
    recall_at_1: float
    recall_at_10: float
    candidate_precision: float
    candidates: int
    true_candidates: int
    mean_prefilter_size: float
    exhaustive_recall_at_1: float
    exhaustive_recall_at_10: float
    descriptor_frames_per_s: float
    descriptor_ms_per_frame: float
    descriptor_warmup_s: float
    timing_runs: int
    top_k: int
    exclusion_frames: int
    config: dict

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def natural_key(path: Path) -> tuple:
    """Sort key ordering ``2.jpg`` before ``10.jpg``."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name))


def list_images(folder: Path, *, exclude: Sequence[Path] = ()) -> list[Path]:
    """Image files of ``folder`` in natural order, without the files in ``exclude``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise RetrievalError("image folder not found", path=folder, fix="pass a folder of images")
    skip = {Path(p).resolve() for p in exclude}
    images = [
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file() and p.resolve() not in skip
    ]
    if not images:
        raise RetrievalError("no images in the folder", path=folder, fix=f"use a folder of {', '.join(IMAGE_SUFFIXES)} files")
    return sorted(images, key=natural_key)


def read_image(path: Path) -> np.ndarray:
    """``(H, W)`` grey or ``(H, W, 3)`` RGB uint8; raises :class:`RetrievalError` if unreadable."""
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise RetrievalError("cannot decode the image", path=path, fix="remove or replace the file")
    if image.ndim == 3 and image.shape[2] >= 3:
        image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_BGR2RGB)
    return image


def load_truth_matrix(path: Path, n_images: int) -> np.ndarray:
    """The ``(N, N)`` bool truth matrix from an image (nonzero = same place) or a text file of 0/1.

    The matrix is symmetrised (either triangle may be given) and its diagonal cleared.
    """
    path = Path(path)
    if not path.is_file():
        raise RetrievalError("truth matrix not found", path=path, fix="pass --truth-matrix FILE")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        import cv2

        matrix = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if matrix is None:
            raise RetrievalError("cannot decode the truth-matrix image", path=path)
    else:
        try:
            text = path.read_text(encoding="utf-8").replace(",", " ")
            matrix = np.loadtxt(text.splitlines(), ndmin=2)
        except (ValueError, UnicodeDecodeError) as exc:
            raise RetrievalError(f"cannot read the truth matrix: {exc}", path=path, fix="use an image or a 0/1 text matrix") from None
    truth = np.asarray(matrix) > 0
    if truth.shape != (n_images, n_images):
        raise RetrievalError(
            f"truth matrix is {truth.shape[0]}x{truth.shape[1]} but the folder has {n_images} images",
            path=path,
            fix="pass the matrix that belongs to this image folder (every image file in it but the matrix counts)",
        )
    truth = truth | truth.T
    np.fill_diagonal(truth, False)
    return truth


def query_frames(truth: np.ndarray, exclusion_frames: int) -> np.ndarray:
    """Frames with at least one true match more than ``exclusion_frames`` earlier."""
    n = truth.shape[0]
    q, m = np.nonzero(np.tril(truth, k=-1))
    return np.unique(q[q - m > exclusion_frames]).astype(np.int64) if n else np.zeros(0, np.int64)


def score_candidates(
    candidates: dict[int, Sequence[LoopCandidate]] | dict[int, Sequence[int]],
    truth: np.ndarray,
    *,
    exclusion_frames: int,
    top_k: int,
) -> RetrievalScores:
    """Recall@1, recall@top_k and precision of per-frame candidate lists (best first)."""
    def matches(items) -> list[int]:
        return [c.match_frame if isinstance(c, LoopCandidate) else int(c) for c in items]

    queries = query_frames(truth, exclusion_frames)
    hit1 = hitk = 0
    for q in queries:
        found = matches(candidates.get(int(q), ()))[:top_k]
        hit1 += bool(found) and bool(truth[q, found[0]])
        hitk += any(truth[q, m] for m in found)
    total = sum(len(v) for v in candidates.values())
    true = sum(bool(truth[q, m]) for q, items in candidates.items() for m in matches(items))
    n = len(queries)
    return RetrievalScores(
        queries=n,
        recall_at_1=hit1 / n if n else float("nan"),
        recall_at_k=hitk / n if n else float("nan"),
        candidate_precision=true / total if total else float("nan"),
        candidates=total,
        true_candidates=true,
    )


def exhaustive_candidates(
    descriptors: np.ndarray, *, exclusion_frames: int, top_k: int, frames: np.ndarray | None = None, chunk_rows: int = 1024
) -> dict[int, list[int]]:
    """Plain L2 top-``top_k`` over every eligible earlier frame (no prefilter): the reference.

    Args:
        descriptors: ``(N, D)`` in frame order.
        frames: ``(N,)`` increasing frame indices of the rows (default ``0..N-1``); a frame ``m`` is
            eligible for query ``q`` when ``q - m > exclusion_frames``.
        chunk_rows: queries per distance block (memory ``chunk_rows x N``).
    """
    x = np.asarray(descriptors, dtype=np.float32)
    frames = np.arange(x.shape[0]) if frames is None else np.asarray(frames, dtype=np.int64)
    sq = np.einsum("ij,ij->i", x, x)
    out = {}
    for start in range(0, x.shape[0], chunk_rows):
        block = slice(start, min(start + chunk_rows, x.shape[0]))
        d2 = sq[block, None] + sq[None, :] - 2.0 * x[block] @ x.T
        for row, q in enumerate(range(block.start, block.stop)):
            eligible = np.arange(0, int(np.searchsorted(frames, frames[q] - exclusion_frames, side="left")))
            if eligible.size:
                order = np.lexsort((eligible, d2[row, eligible]))[:top_k]
                out[int(frames[q])] = frames[eligible[order]].tolist()
    return out


def retrieve_all(descriptors: np.ndarray, config: RetrievalConfig) -> tuple[dict[int, tuple[LoopCandidate, ...]], list[int]]:
    """Run the whole-log-fit :class:`Retriever` over ``(N, D)`` descriptors (frames 0..N-1).

    Returns:
        ``(candidates by query frame, prefilter size of every query)``.
    """
    from lcv_replay.retrieval.retriever import Retriever

    retriever = Retriever(dataclasses.replace(config, fit="whole-log"), dim=descriptors.shape[1])
    retriever.fit(descriptors)
    candidates: dict[int, tuple[LoopCandidate, ...]] = {}
    prefilter = []
    for i, d in enumerate(descriptors):
        out = retriever.add(i, d)
        if out.diagnostics is not None:
            prefilter.append(out.diagnostics.prefilter_size)
        if out.candidates:
            candidates[i] = out.candidates
    return candidates, prefilter


def time_descriptor(backend, images: Sequence[np.ndarray], *, runs: int) -> list[float]:
    """Seconds per frame of ``backend.describe`` over ``images`` (in batches), one value per run."""
    batch = getattr(backend, "batch_size", 8)
    per_frame = []
    for _ in range(runs):
        start = time.perf_counter()
        for i in range(0, len(images), batch):
            backend.describe(images[i : i + batch])
        per_frame.append((time.perf_counter() - start) / len(images))
    return per_frame


def bench_backend(
    name: str, images: Sequence[np.ndarray], truth: np.ndarray, config: RetrievalConfig, *, timing_runs: int = 5
) -> BackendReport:
    """Describe ``images``, retrieve with a whole-set fit and score against ``truth``."""
    from lcv_replay.config import to_dict
    from lcv_replay.retrieval.descriptors import make_backend

    start = time.perf_counter()
    backend = make_backend(name, config)
    descriptors = backend.describe(images[:1])  # first call inside the warm-up, as a replay sees it
    warmup_s = getattr(backend, "warmup_s", None) or (time.perf_counter() - start)
    descriptors = backend.describe(images)
    per_frame = time_descriptor(backend, images, runs=timing_runs) if timing_runs > 0 else [float("nan")]
    median_s = statistics.median(per_frame)
    candidates, prefilter = retrieve_all(descriptors, config)
    scores = score_candidates(candidates, truth, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    exhaustive = exhaustive_candidates(descriptors, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    ex1 = score_candidates({q: v[:1] for q, v in exhaustive.items()}, truth, exclusion_frames=config.exclusion_frames, top_k=1)
    exk = score_candidates(exhaustive, truth, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    return BackendReport(
        backend=name,
        mode=config.mode,
        engine=getattr(backend, "engine", "numpy"),
        dim=int(descriptors.shape[1]),
        queries=scores.queries,
        recall_at_1=scores.recall_at_1,
        recall_at_10=scores.recall_at_k,
        candidate_precision=scores.candidate_precision,
        candidates=scores.candidates,
        true_candidates=scores.true_candidates,
        mean_prefilter_size=float(np.mean(prefilter)) if prefilter else 0.0,
        exhaustive_recall_at_1=ex1.recall_at_1,
        exhaustive_recall_at_10=exk.recall_at_k,
        descriptor_frames_per_s=1.0 / median_s if median_s > 0 else float("nan"),
        descriptor_ms_per_frame=1000.0 * median_s,
        descriptor_warmup_s=float(warmup_s),
        timing_runs=timing_runs,
        top_k=config.top_k,
        exclusion_frames=config.exclusion_frames,
        config=to_dict(dataclasses.replace(config, backend=name)),
    )


# --- MCAP logs with ground truth ------------------------------------------------------------------


def truth_from_poses(positions_m: np.ndarray, radius_m: float) -> np.ndarray:
    """``(N, N)`` bool: frames whose ground-truth positions are closer than ``radius_m`` (diagonal off).

    Args:
        positions_m: ``(N, 2)`` ground-truth ``x, y`` in metres; rows with NaN match nothing.
    """
    p = np.asarray(positions_m, dtype=np.float64)
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(axis=2)
    truth = np.nan_to_num(d2, nan=np.inf) < radius_m**2
    np.fill_diagonal(truth, False)
    return truth


@dataclass(frozen=True)
class LogReport:
    """Retrieval over a log, scored against ground-truth distances (the synthetic world report).

    ``revisits_found`` = recall@N_r (queries with a true candidate among their list), and
    ``false_candidate_fraction`` = 1 - candidate precision. ``exhaustive_revisits_found`` is the
    same share from the plain L2 top ``N_r`` over every eligible frame (the ceiling of the
    descriptor). ``same_heading_*``: the queries with a true match seen from a similar heading
    (within 45 degrees), the revisits a forward camera can recognise at all.
    """

    log: str
    backend: str
    mode: str
    engine: str
    frames: int
    described: int
    cached: int
    corrupt: int
    radius_m: float
    exclusion_frames: int
    fit: str
    queries: int
    revisits_found: float
    recall_at_1: float
    false_candidate_fraction: float
    candidates: int
    true_candidates: int
    mean_prefilter_size: float
    describe_s: float
    retrieval_ms_per_frame: float
    exhaustive_revisits_found: float
    same_heading_queries: int
    same_heading_found: float
    exhaustive_same_heading_found: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def bench_log(path: Path, backend_name: str, config: RetrievalConfig, *, radius_m: float, cache_dir: Path | None = None) -> LogReport:
    """Run the replay-style front end over an MCAP log (online fit unless ``config.fit``) and score it
    against ground-truth positions: a candidate is true when the frames are within ``radius_m``."""
    from lcv_replay.log.reader import open_log
    from lcv_replay.retrieval.cache import DescribeStats, describe_frames, log_cache_key
    from lcv_replay.retrieval.descriptors import make_backend
    from lcv_replay.retrieval.retriever import Retriever

    backend = make_backend(backend_name, config)
    stats = DescribeStats()
    start = time.perf_counter()
    with open_log(path) as reader:
        gt = reader.ground_truth()
        if gt is None:
            raise RetrievalError("the log has no ground truth to score retrieval against", path=path, fix="use a log with /ground_truth/pose")
        key = log_cache_key(path) if config.cache else None
        rows = [
            (frame.index, d)
            for frame, d in describe_frames(reader.frames(), backend, cache_key=key, cache_dir=cache_dir, batch_size=config.batch_size, stats=stats)
            if d is not None
        ]
    describe_s = time.perf_counter() - start
    if not rows:
        raise RetrievalError("no frame of the log has a usable left image", path=path)
    frames = np.array([f for f, _ in rows])
    descriptors = np.stack([d for _, d in rows])
    retriever = Retriever(config, dim=descriptors.shape[1])
    if config.fit == "whole-log":
        retriever.fit(descriptors)
    candidates: dict[int, tuple[LoopCandidate, ...]] = {}
    prefilter = []
    start = time.perf_counter()
    for f, d in zip(frames, descriptors):
        out = retriever.add(int(f), d)
        if out.diagnostics is not None:
            prefilter.append(out.diagnostics.prefilter_size)
        if out.candidates:
            candidates[int(f)] = out.candidates
    retrieval_s = time.perf_counter() - start
    message = retriever.warmup_message()
    if message:
        log.warning("%s", message)
    gt = np.asarray(gt)
    truth = truth_from_poses(gt[:, :2], radius_m)
    scores = score_candidates(candidates, truth, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    exhaustive = exhaustive_candidates(descriptors, exclusion_frames=config.exclusion_frames, top_k=config.top_k, frames=frames)
    if config.fit == "online":  # the same queries as the retriever's: none during its warm-up
        first = frames[min(retriever.warmup_frames, len(frames)) - 1] if len(frames) else 0
        exhaustive = {q: v for q, v in exhaustive.items() if q > first}
    ceiling = score_candidates(exhaustive, truth, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    heading = same_heading_truth(gt, truth)
    same = score_candidates(candidates, heading, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    same_ceiling = score_candidates(exhaustive, heading, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    return LogReport(
        log=str(path),
        backend=backend_name,
        mode=config.mode,
        engine=getattr(backend, "engine", "numpy"),
        frames=int(truth.shape[0]),
        described=stats.described,
        cached=stats.cached,
        corrupt=stats.corrupt,
        radius_m=radius_m,
        exclusion_frames=config.exclusion_frames,
        fit=config.fit,
        queries=scores.queries,
        revisits_found=scores.recall_at_k,
        recall_at_1=scores.recall_at_1,
        false_candidate_fraction=1.0 - scores.candidate_precision if scores.candidates else float("nan"),
        candidates=scores.candidates,
        true_candidates=scores.true_candidates,
        mean_prefilter_size=float(np.mean(prefilter)) if prefilter else 0.0,
        describe_s=describe_s,
        retrieval_ms_per_frame=1000.0 * retrieval_s / len(frames),
        exhaustive_revisits_found=ceiling.recall_at_k,
        same_heading_queries=same.queries,
        same_heading_found=same.recall_at_k,
        exhaustive_same_heading_found=same_ceiling.recall_at_k,
    )


def same_heading_truth(poses: np.ndarray, truth: np.ndarray, *, max_heading_rad: float = np.pi / 4) -> np.ndarray:
    """``truth`` restricted to pairs whose ground-truth headings differ by at most ``max_heading_rad``.

    Args:
        poses: ``(N, 3)`` ground truth ``x, y, yaw`` (yaw in radians; NaN rows match nothing).
        truth: ``(N, N)`` bool same-place matrix.
    """
    yaw = np.asarray(poses, dtype=np.float64)[:, 2]
    diff = np.abs((yaw[:, None] - yaw[None, :] + np.pi) % (2.0 * np.pi) - np.pi)
    return truth & (np.nan_to_num(diff, nan=np.inf) <= max_heading_rad)


# --- index query cost vs library size ---------------------------------------------------------------


@dataclass(frozen=True)
class IndexVariant:
    """One row kind of :func:`index_query_times`: a mode with its first-stage engine.

    ``product`` variants are what ``retrieval.mode`` / ``ranked.index`` / ``index_strategy`` select;
    the others are faiss's approximate indexes, measured as the first stage of the ranked mode
    (same codes, same ``M``, same re-rank) to decide whether they win.
    """

    name: str
    mode: str
    engine: str
    product: bool = True


INDEX_VARIANTS: dict[str, IndexVariant] = {
    v.name: v
    for v in (
        IndexVariant("paper/scan", "paper", "scan"),
        IndexVariant("paper/table", "paper", "table"),
        IndexVariant("ranked/faiss", "ranked", "faiss"),
        IndexVariant("ranked/numpy", "ranked", "numpy"),
        IndexVariant("ranked/faiss-hnsw", "ranked", "faiss-hnsw", product=False),
        IndexVariant("ranked/faiss-mih", "ranked", "faiss-mih", product=False),
    )
}
_INDEX_BLOCK = 25  # queries a variant runs back to back (as a replay's queries hit one index) before the next takes its turn
DEFAULT_INDEX_VARIANTS = ("paper/scan", "paper/table", "ranked/faiss", "ranked/numpy", "ranked/faiss-hnsw", "ranked/faiss-mih")


def index_query_times(
    sizes: Sequence[int] = (1_000, 10_000, 100_000),
    *,
    variants: Sequence[str] = DEFAULT_INDEX_VARIANTS,
    vector_dim: int = 1904,
    config: RetrievalConfig | None = None,
    queries: int = 500,
    seed: int = 0,
) -> list[dict]:
    """Median time of one query (first stage + L2 re-rank) and one add, at each library size.

    Synthetic library: uniformly random codes (the ITQ target: balanced, uncorrelated bits; for the
    approximate faiss indexes the hardest case) and Gaussian vectors, frames ``0..size-1``; queries
    are random codes with every frame eligible, so the paper's prefilter returns
    ``~size * P / 2^N_b`` frames (``P`` probes) as it would for well-spread real codes. Every size
    measures every variant on the same library; the variants take turns, 25 queries each, so
    background load hits them alike while each runs its queries back to back, as a replay does. ``first_stage_us_median`` is the prefilter alone; ``query_us_median`` adds the
    re-rank. ``recall_vs_exact`` is the share of the exact Hamming top ``M`` that an approximate
    first stage returns (1 for the exact ones; the paper's ball is not a top-M and gets ``None``).
    """
    from lcv_replay.retrieval.index import CodeIndex, RankedIndex, code_words, faiss_available, hamming_nearest, rerank_l2_order

    config = config or RetrievalConfig()
    ranked_bits, paper_bits, m = config.ranked.code_bits, config.code_bits, config.ranked.candidates
    rng = np.random.default_rng(seed)
    rows = []
    for size in sizes:
        vectors = rng.normal(size=(size, vector_dim)).astype(np.float32)
        frames = np.arange(size, dtype=np.int64)
        q_vectors = rng.normal(size=(queries, vector_dim)).astype(np.float32)
        codes = {"paper": rng.integers(0, 1 << paper_bits, size=size), "ranked": [int.from_bytes(rng.bytes(ranked_bits // 8), "little") for _ in range(size)]}
        q_codes = {"paper": rng.integers(0, 1 << paper_bits, size=queries), "ranked": [int.from_bytes(rng.bytes(ranked_bits // 8), "little") for _ in range(queries)]}
        ranked_words = np.stack([code_words(c, -(-ranked_bits // 64)) for c in codes["ranked"]])
        searchers: dict[str, tuple] = {}
        add_us: dict[str, float] = {}
        for name in variants:
            variant = INDEX_VARIANTS[name]
            if variant.engine.startswith("faiss") and not faiss_available():
                log.warning("%s skipped: faiss is not installed", name)
                continue
            start = time.perf_counter()
            if variant.mode == "paper":
                index = CodeIndex(code_bits=paper_bits, vector_dim=vector_dim, hamming_threshold=config.hamming_threshold, strategy=variant.engine)
            elif variant.product:
                index = RankedIndex(code_bits=ranked_bits, vector_dim=vector_dim, candidates=m, engine=variant.engine)
            else:
                index = _ApproximateFirstStage(variant.engine, ranked_bits, vectors, frames)
            if variant.product:
                for f in range(size):
                    index.add(f, int(codes[variant.mode][f]), vectors[f])
            else:
                index.add_all(codes["ranked"])
            add_us[name] = 1e6 * (time.perf_counter() - start) / size
            searchers[name] = (variant, index)
        times = {name: [] for name in searchers}
        first = {name: [] for name in searchers}
        hits = {name: [] for name in searchers}
        recall = {name: [] for name in searchers}
        for block in range(0, queries, _INDEX_BLOCK):  # variants take turns, a block of queries each
            for name, (variant, index) in searchers.items():
                got_block = []
                for qi in range(block, min(block + _INDEX_BLOCK, queries)):
                    code, vector = int(q_codes[variant.mode][qi]), q_vectors[qi]
                    t0 = time.perf_counter()
                    if variant.product:
                        result = index.search(code, vector, max_frame_index=size, top_k=config.top_k)
                        size_passed = result.prefilter_size
                    else:
                        prefiltered = index.search(code, m)
                        rerank_l2_order(vectors, prefiltered, frames, vector, config.top_k)
                        size_passed = prefiltered.size
                    times[name].append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    got = index.prefilter(code, max_frame_index=size)[0] if variant.product else index.search(code, m)
                    first[name].append(time.perf_counter() - t0)
                    hits[name].append(size_passed)
                    got_block.append((code, got))
                if variant.mode == "ranked":  # measured (untimed) for the exact engines too: they must give 1
                    for code, got in got_block:
                        exact = hamming_nearest(ranked_words, code_words(code, ranked_words.shape[1]), m)[0]
                        recall[name].append(len(np.intersect1d(got, exact)) / max(1, exact.size))
        for name, (variant, _) in searchers.items():
            rows.append(
                {
                    "library_frames": size,
                    "variant": name,
                    "mode": variant.mode,
                    "engine": variant.engine,
                    "product": variant.product,
                    "code_bits": paper_bits if variant.mode == "paper" else ranked_bits,
                    "vector_dim": vector_dim,
                    "query_us_median": 1e6 * statistics.median(times[name]),
                    "query_us_p90": 1e6 * float(np.percentile(times[name], 90)),
                    "first_stage_us_median": 1e6 * statistics.median(first[name]),
                    "add_us_mean": add_us[name],
                    "mean_prefilter_size": float(np.mean(hits[name])),
                    "recall_vs_exact": float(np.mean(recall[name])) if recall[name] else None,
                }
            )
        del searchers
    for row in rows:  # growth against the smallest size, per variant
        base = next(r for r in rows if r["variant"] == row["variant"])
        row["query_vs_smallest"] = row["query_us_median"] / base["query_us_median"]
    return rows


class _ApproximateFirstStage:
    """faiss's approximate binary indexes as the ranked first stage (measured, not shipped).

    * ``faiss-hnsw``: ``IndexBinaryHNSW`` (32 links per node, efSearch 2 M);
    * ``faiss-mih``: ``IndexBinaryMultiHash`` (multi-index hashing: ``bits / 16`` tables of 16-bit
      substrings, probing every substring within 1 flip).
    """

    def __init__(self, engine: str, code_bits: int, vectors: np.ndarray, frames: np.ndarray):
        import faiss

        faiss.omp_set_num_threads(1)
        self._bytes = code_bits // 8
        if engine == "faiss-hnsw":
            self._index = faiss.IndexBinaryHNSW(code_bits, 32)
            self._index.hnsw.efSearch = 200
        elif engine == "faiss-mih":
            self._index = faiss.IndexBinaryMultiHash(code_bits, code_bits // 16, 16)
            self._index.nflip = 1
        else:
            raise RetrievalError(f"unknown approximate engine '{engine}'")

    def _pack(self, codes) -> np.ndarray:
        return np.frombuffer(b"".join(int(c).to_bytes(self._bytes, "little") for c in codes), dtype=np.uint8).reshape(-1, self._bytes)

    def add_all(self, codes) -> None:
        self._index.add(self._pack(codes))

    def search(self, code: int, count: int) -> np.ndarray:
        _, labels = self._index.search(self._pack([code]), count)
        return labels[0][labels[0] >= 0].astype(np.int64)
