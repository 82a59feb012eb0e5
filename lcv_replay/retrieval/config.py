"""Retrieval configuration: the paper's place-recognition defaults (Tanaka, SII 2016, sec. II-B)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from lcv_replay.errors import require, require_seed


@dataclass(frozen=True)
class RetrievalConfig:
    """Place recognition: CNN descriptor -> PCA -> binary code -> Hamming prefilter -> L2 re-rank."""

    backend: str = "efficientnet-lite0"  # descriptor backend name (registry in descriptors.py)
    input_size_px: int = 224  # square network input; a multiple of 32
    batch_size: int = 8  # descriptor batch size
    top_k: int = 10  # N_r: retrieved frames per query (sec. II-B)
    exclusion_frames: int = 200  # Δt: frames within Δt of the query are not eligible (sec. II-B)
    pca_dims: int = 128  # PCA dimension of the CNN feature (sec. II-B)
    code_bits: int = 20  # N_b: binary code length (sec. II-B)
    hamming_threshold: int = 3  # T_b: Hamming prefilter radius, inclusive (sec. II-B)
    fit: Literal["online", "whole-log"] = "online"  # fit PCA/codes on the first Δt frames, or on all
    itq_iterations: int = 50  # ITQ rotation iterations
    seed: int = 0
    # --- descriptor (efficientnet-lite0) ---
    # descriptor pooling: "multi" = GeM of stages 5-7 + head, each L2-normalised, concatenated (1904-D);
    # it beat "avg" (head average, 1280-D) and "gem" on rtabmap_corridor (docs in bench/retrieval.py)
    pooling: Literal["avg", "gem", "multi"] = "multi"
    gem_p: float = 3.0  # GeM exponent (pooling "gem" and "multi")
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

    def __post_init__(self) -> None:
        require(self.top_k >= 1, "retrieval.top_k", self.top_k, "an integer >= 1")
        require_seed(self.seed, "config key 'retrieval.seed'")
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
