"""Generate ``retrieval_paper_golden.json``: the paper pipeline's output before issue 15 changed retrieval.

Run from the repository root: ``python tests/data/make_retrieval_golden.py``. It was run once, on the
code as it stood before the improved prefilter was added (commit 4f6e6e7), and its output is
committed; ``tests/retrieval/test_paper_mode.py`` checks that ``retrieval.mode = "paper"`` still
gives exactly these candidates.

The descriptors are multiples of 1/16 in [-4, 4], so every squared L2 distance, and hence every
similarity, is exact in float32 whatever the summation order of the CPU's SIMD kernels; and no
projection onto a code axis lies within 1e-3 of zero, so the binary codes do not depend on the last
bits of the PCA/ITQ fit either. The golden therefore holds bit for bit on any machine.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from lcv_replay.retrieval.config import RetrievalConfig
from lcv_replay.retrieval.retriever import Retriever

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "retrieval_paper_golden.json"
DIM = 48
BASE = dict(exclusion_frames=30, code_bits=12, hamming_threshold=3, pca_dims=32, top_k=5)
CASES = {
    "online-descriptor-scan": dict(),
    "online-descriptor-table": dict(index_strategy="table"),
    "whole-log-descriptor-scan": dict(fit="whole-log"),
    "online-20bit": dict(code_bits=20, pca_dims=40, exclusion_frames=40),
}


def golden_descriptors() -> np.ndarray:
    """``(150, 48)`` float32 descriptors of a route walked once (100 places) and partly again (50)."""
    rng = np.random.default_rng(10)
    places = np.cumsum(rng.normal(size=(100, DIM)), axis=0) * 0.3 + rng.normal(size=(100, DIM))
    rows = [places[i] + 0.05 * rng.normal(size=DIM) for i in range(100)]
    rows += [places[i] + 0.05 * rng.normal(size=DIM) for i in range(50)]
    x = np.asarray(rows)
    x = x / np.abs(x).max() * 4.0
    return (np.round(x * 16.0) / 16.0).astype(np.float32)


def case_config(name: str) -> RetrievalConfig:
    """The case's config in ``mode = "paper"`` (the golden was written before modes existed, at 4f6e6e7)."""
    return RetrievalConfig(**{**BASE, **CASES[name]}, mode="paper")


def run_case(config: RetrievalConfig, descriptors: np.ndarray) -> list[dict]:
    """Every query's diagnostics and candidates, JSON-ready (similarity as a float.hex string)."""
    retriever = Retriever(config, dim=descriptors.shape[1])
    if config.fit == "whole-log":
        retriever.fit(descriptors)
    rows = []
    for i, d in enumerate(descriptors):
        out = retriever.add(i, d)
        if out.diagnostics is None:
            continue
        rows.append(
            {
                "query": i,
                "code": out.diagnostics.code,
                "prefilter_size": out.diagnostics.prefilter_size,
                "candidates": [[c.match_frame, c.hamming, float(c.similarity).hex()] for c in out.candidates],
            }
        )
    return rows


def projection_margin(config: RetrievalConfig, descriptors: np.ndarray) -> float:
    """The smallest |rotated PCA coordinate| of any descriptor: how far every code bit is from flipping."""
    retriever = Retriever(config, dim=descriptors.shape[1])
    fit_rows = descriptors if config.fit == "whole-log" else descriptors[: retriever.warmup_frames]
    retriever.fit(fit_rows)
    h = retriever.hasher
    rotated = h.project(descriptors)[:, : h.code_bits] @ h.rotation
    return float(np.abs(rotated).min())


def main() -> None:
    x = golden_descriptors()
    out = {}
    for name in CASES:
        config = case_config(name)
        margin = projection_margin(config, x)
        if margin < 1e-3:
            raise SystemExit(f"{name}: a code bit is {margin:.2e} from flipping; change the seed")
        out[name] = {"config": dataclasses.asdict(config) | {"margin": margin}, "queries": run_case(config, x)}
    GOLDEN.write_text(json.dumps(out, separators=(",", ":")) + "\n")
    print(f"wrote {GOLDEN}")


if __name__ == "__main__":
    main()
