"""Retrieval configuration: the paper's place-recognition defaults (Tanaka, SII 2016, sec. II-B).

Two modes share the descriptor, the PCA and the L2 re-rank and differ in the binary prefilter
(docs/retrieval.md has the measurements behind the choice):

* ``"paper"``: the paper's ``N_b = 20``-bit codes, frames within Hamming ``T_b = 3`` go to the re-rank
  (``code_bits``, ``hamming_threshold``);
* ``"ranked"`` (the default; not in the paper): longer codes, and the ``M`` Hamming-nearest eligible
  frames go to the re-rank, however far they are (``retrieval.ranked``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from lcv_replay.errors import require, require_seed

MODES = ("ranked", "paper")
ENGINES = ("auto", "onnxruntime", "torch")


@dataclass(frozen=True)
class RankedConfig:
    """The improved prefilter (``retrieval.mode = "ranked"``, the default); not in the paper.

    The query's ``code_bits``-bit ITQ code is compared with every eligible library code (exact
    Hamming k-nearest-neighbour search) and the ``candidates`` nearest, ties to the earlier frame,
    go to the L2 re-rank; the best ``N_r`` of them are the loop candidates.
    """

    code_bits: int = 128  # code length: ITQ on all 128 PCA axes (a multiple of 8, at most pca_dims)
    candidates: int = 100  # M: Hamming-nearest eligible frames passed to the L2 re-rank (>= N_r)
    index: Literal["auto", "faiss", "numpy"] = "auto"  # exact Hamming k-NN: faiss IndexBinaryFlat, or a numpy scan; auto = faiss when installed

    def __post_init__(self) -> None:
        require(8 <= self.code_bits <= 128 and self.code_bits % 8 == 0, "retrieval.ranked.code_bits", self.code_bits, "a multiple of 8 in 8..128")
        require(self.candidates >= 1, "retrieval.ranked.candidates", self.candidates, "an integer >= retrieval.top_k")
        require(self.index in ("auto", "faiss", "numpy"), "retrieval.ranked.index", self.index, "'auto', 'faiss' or 'numpy'")


@dataclass(frozen=True)
class RetrievalConfig:
    """Place recognition: CNN descriptor -> PCA -> binary code -> Hamming prefilter -> L2 re-rank."""

    mode: Literal["ranked", "paper"] = "ranked"  # prefilter: "paper" = sec. II-B as published (code_bits, hamming_threshold); "ranked" = the improved default (retrieval.ranked)
    backend: str = "efficientnet-lite0"  # descriptor backend name (registry in descriptors.py)
    input_size_px: int = 224  # square network input; a multiple of 32
    batch_size: int = 8  # descriptor batch size
    top_k: int = 10  # N_r: retrieved frames per query (sec. II-B)
    exclusion_frames: int = 200  # Δt: frames within Δt of the query are not eligible (sec. II-B)
    pca_dims: int = 128  # PCA dimension of the CNN feature (sec. II-B)
    code_bits: int = 20  # N_b: binary code length (sec. II-B); mode "paper"
    hamming_threshold: int = 3  # T_b: Hamming prefilter radius, inclusive (sec. II-B); mode "paper"
    fit: Literal["online", "whole-log"] = "online"  # fit PCA/codes on the first Δt frames, or on all
    itq_iterations: int = 50  # ITQ rotation iterations
    seed: int = 0
    # --- descriptor (efficientnet-lite0) ---
    # descriptor pooling: "multi" = GeM of stages 5-7 + head, each L2-normalised, concatenated (1904-D);
    # it beat "avg" (head average, 1280-D) and "gem" on rtabmap_corridor (docs in bench/retrieval.py)
    pooling: Literal["avg", "gem", "multi"] = "multi"
    gem_p: float = 3.0  # GeM exponent (pooling "gem" and "multi")
    engine: Literal["auto", "onnxruntime", "torch"] = "auto"  # CNN runtime; auto = torch in mode "paper" (today's descriptors bit for bit), else ONNX Runtime (exported from the folded torch model, falls back to torch)
    num_threads: int = 0  # torch intra-op threads; 0 = one per available core (use 1 when the verifier shares 2 cores)
    precision: Literal["fp32", "bf16"] = "fp32"  # bf16 autocast: faster on AVX512-BF16 CPUs, descriptors change (cos ~0.998)
    torch_compile: bool = False  # torch.compile (inductor, freezing): needs a C++ compiler, first call takes seconds
    tune_allocator: bool = True  # glibc mallopt for torch activations (see retrieval/efficientnet.py)
    # --- descriptor (thumbnail baseline, SeqSLAM-style) ---
    thumbnail_width_px: int = 64
    thumbnail_height_px: int = 32
    thumbnail_patch_px: int = 8  # patch normalisation window
    # --- index and cache ---
    rerank: Literal["descriptor", "pca"] = "descriptor"  # L2 re-rank on full descriptors or PCA vectors
    index_strategy: Literal["auto", "scan", "table"] = "auto"  # Hamming prefilter; auto = scan (retrieval/index.py)
    cache: bool = True  # reuse descriptors across runs (retrieval/cache.py)
    cache_dir: str = ""  # "" = $LCV_CACHE_DIR, else $XDG_CACHE_HOME/lcv-replay/descriptors
    ranked: RankedConfig = field(default_factory=RankedConfig)  # mode "ranked" only

    def __post_init__(self) -> None:
        require(self.mode in MODES, "retrieval.mode", self.mode, "'ranked' (the default) or 'paper'")
        require(self.engine in ENGINES, "retrieval.engine", self.engine, "'auto', 'onnxruntime' or 'torch'")
        require(self.top_k >= 1, "retrieval.top_k", self.top_k, "an integer >= 1")
        require_seed(self.seed, "config key 'retrieval.seed'")
        if self.mode == "ranked":
            require(self.ranked.candidates >= self.top_k, "retrieval.ranked.candidates", self.ranked.candidates, f"an integer >= retrieval.top_k ({self.top_k}): the M re-ranked frames give the N_r candidates")
            require(self.ranked.code_bits <= self.pca_dims, "retrieval.ranked.code_bits", self.ranked.code_bits, f"at most retrieval.pca_dims ({self.pca_dims}): each bit is one rotated PCA axis")
        require(self.exclusion_frames >= 0, "retrieval.exclusion_frames", self.exclusion_frames, "an integer >= 0")
        require(1 <= self.code_bits <= 64, "retrieval.code_bits", self.code_bits, "1..64")
        require(self.pca_dims >= self.code_bits, "retrieval.pca_dims", self.pca_dims, f"an integer >= code_bits ({self.code_bits})")
        require(0 <= self.hamming_threshold <= self.code_bits, "retrieval.hamming_threshold", self.hamming_threshold, "0..code_bits")
        require(self.input_size_px >= 32 and self.input_size_px % 32 == 0, "retrieval.input_size_px", self.input_size_px, "a multiple of 32")
        require(self.batch_size >= 1, "retrieval.batch_size", self.batch_size, "an integer >= 1")
        require(self.itq_iterations >= 0, "retrieval.itq_iterations", self.itq_iterations, "an integer >= 0")
        require(self.gem_p >= 1.0, "retrieval.gem_p", self.gem_p, "a number >= 1")
        require(self.num_threads >= 0, "retrieval.num_threads", self.num_threads, "an integer >= 0 (0 = all cores)")
        require(self.thumbnail_width_px >= 8 and self.thumbnail_height_px >= 8, "retrieval.thumbnail_width_px/height_px", (self.thumbnail_width_px, self.thumbnail_height_px), "sizes >= 8")
        require(1 <= self.thumbnail_patch_px <= min(self.thumbnail_width_px, self.thumbnail_height_px), "retrieval.thumbnail_patch_px", self.thumbnail_patch_px, "1..min(thumbnail width, height)")

    @property
    def active_code_bits(self) -> int:
        """The code length the mode uses: ``code_bits`` (paper) or ``ranked.code_bits``."""
        return self.code_bits if self.mode == "paper" else self.ranked.code_bits

    @property
    def resolved_engine(self) -> str:
        """``engine`` with ``"auto"`` resolved: torch in mode "paper", else ONNX Runtime."""
        if self.engine != "auto":
            return self.engine
        return "torch" if self.mode == "paper" else "onnxruntime"
