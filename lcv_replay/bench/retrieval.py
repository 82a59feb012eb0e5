"""Retrieval benchmark on an ordered image folder with a loop-closure truth matrix.

``lcv-replay bench retrieval IMAGES_DIR --truth-matrix FILE`` runs the whole front end (descriptor,
PCA, binary codes, Hamming prefilter, L2 re-rank) with the PCA/ITQ fit on the whole set, then
scores each backend:

* a **query** is a frame ``q`` with at least one true match ``m`` (truth matrix, either triangle)
  with ``q - m > Δt``; frames without one are not queries for recall;
* **recall@1** / **recall@N_r**: fraction of queries whose best / any of the top ``N_r`` candidates
  is a true match;
* **candidate precision**: true candidates / all candidates emitted (every frame's list);
* ``exhaustive_recall_at_*``: the same recall from a plain L2 nearest-neighbour search over every
  eligible frame, without the Hamming prefilter (what the prefilter costs);
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


def exhaustive_candidates(descriptors: np.ndarray, *, exclusion_frames: int, top_k: int) -> dict[int, list[int]]:
    """Plain L2 top-``top_k`` over every eligible earlier frame (no prefilter): the reference."""
    x = np.asarray(descriptors, dtype=np.float32)
    sq = np.einsum("ij,ij->i", x, x)
    d2 = sq[:, None] + sq[None, :] - 2.0 * x @ x.T
    out = {}
    for q in range(x.shape[0]):
        eligible = np.arange(0, max(0, q - exclusion_frames))
        if eligible.size:
            order = np.lexsort((eligible, d2[q, eligible]))[:top_k]
            out[q] = eligible[order].tolist()
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
    ``false_candidate_fraction`` = 1 - candidate precision.
    """

    log: str
    backend: str
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
    truth = truth_from_poses(np.asarray(gt)[:, :2], radius_m)
    scores = score_candidates(candidates, truth, exclusion_frames=config.exclusion_frames, top_k=config.top_k)
    return LogReport(
        log=str(path),
        backend=backend_name,
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
    )


# --- index query cost vs library size ---------------------------------------------------------------


def index_query_times(
    sizes: Sequence[int] = (1_000, 10_000, 100_000),
    *,
    strategies: Sequence[str] = ("scan", "table"),
    vector_dim: int = 128,
    code_bits: int = 20,
    hamming_threshold: int = 3,
    top_k: int = 10,
    queries: int = 500,
    seed: int = 0,
) -> list[dict]:
    """Median time of one query (prefilter + re-rank) and one add, at each library size.

    Synthetic library: uniformly random ``code_bits`` codes (the ITQ target: balanced, uncorrelated
    bits) and Gaussian vectors, frames ``0..size-1``; queries are random codes with every frame
    eligible, so the prefilter returns ``~size * P / 2^N_b`` frames (``P`` probes) as it would for
    well-spread real codes.
    """
    from lcv_replay.retrieval.index import CodeIndex

    rng = np.random.default_rng(seed)
    rows = []
    for size in sizes:
        codes = rng.integers(0, 1 << code_bits, size=size)
        vectors = rng.normal(size=(size, vector_dim)).astype(np.float32)
        q_codes = rng.integers(0, 1 << code_bits, size=queries)
        q_vectors = rng.normal(size=(queries, vector_dim)).astype(np.float32)
        for strategy in strategies:
            index = CodeIndex(code_bits=code_bits, vector_dim=vector_dim, hamming_threshold=hamming_threshold, strategy=strategy)
            start = time.perf_counter()
            for f in range(size):
                index.add(f, int(codes[f]), vectors[f])
            add_us = 1e6 * (time.perf_counter() - start) / size
            times, hits = [], []
            for c, v in zip(q_codes, q_vectors):
                t0 = time.perf_counter()
                result = index.search(int(c), v, max_frame_index=size, top_k=top_k)
                times.append(time.perf_counter() - t0)
                hits.append(result.prefilter_size)
            rows.append(
                {
                    "library_frames": size,
                    "strategy": strategy,
                    "vector_dim": vector_dim,
                    "query_us_median": 1e6 * statistics.median(times),
                    "query_us_p90": 1e6 * float(np.percentile(times, 90)),
                    "add_us_mean": add_us,
                    "mean_prefilter_size": float(np.mean(hits)),
                }
            )
    return rows
