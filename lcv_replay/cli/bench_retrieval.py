"""`lcv-replay bench retrieval` and `lcv-replay bench descriptor-speed`."""

from __future__ import annotations

import json
import math
import platform
import re
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import bench_app, config_option, force_option

DEFAULT_BACKENDS = ["efficientnet-lite0", "thumbnail"]


@bench_app.command("retrieval")
def bench_retrieval(
    images_dir: Path = typer.Argument(..., help="Folder of images in time order (natural sort: 2.jpg before 10.jpg), or an MCAP log with ground truth."),
    truth_matrix: Optional[Path] = typer.Option(None, "--truth-matrix", help="N x N truth matrix of the folder: an image (white = same place) or a 0/1 text file."),
    radius_m: float = typer.Option(10.0, "--radius-m", help="MCAP logs: frames closer than this (ground truth) are the same place (T_p)."),
    fit: Optional[str] = typer.Option(None, "--fit", help="MCAP logs: 'online' (first Δt frames, default) or 'whole-log'. Folders always fit on the whole set."),
    exclude_frames: Optional[int] = typer.Option(None, "--exclude-frames", help="Δt: frames closer than this are not eligible (default: retrieval.exclusion_frames)."),
    backend: Optional[list[str]] = typer.Option(None, "--backend", metavar="NAME", help="Descriptor backend; repeat for several (default: efficientnet-lite0 and thumbnail)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the per-backend results as JSON."),
    config_file: Optional[Path] = config_option("its [retrieval] table applies"),
    mode: Optional[list[str]] = typer.Option(None, "--mode", metavar="MODE", help="Retrieval mode: ranked (the default) or paper; repeat to compare both in one run."),
    top_k: Optional[int] = typer.Option(None, "--top-k", help="N_r, candidates per query (default 10)."),
    hamming_threshold: Optional[int] = typer.Option(None, "--hamming-threshold", help="T_b of mode paper (default 3)."),
    code_bits: Optional[int] = typer.Option(None, "--code-bits", help="Code length of the mode(s) run: N_b of paper (default 20), ranked.code_bits (default 128)."),
    candidates: Optional[int] = typer.Option(None, "--candidates", help="M of mode ranked: Hamming-nearest frames re-ranked (default 100)."),
    pooling: Optional[str] = typer.Option(None, "--pooling", help="efficientnet-lite0 pooling: avg, gem or multi (default multi)."),
    seed: Optional[int] = typer.Option(None, "--seed", help="ITQ seed (default 0)."),
    precision: Optional[str] = typer.Option(None, "--precision", help="efficientnet-lite0 arithmetic: fp32 (default) or bf16."),
    torch_compile: Optional[bool] = typer.Option(None, "--torch-compile/--no-torch-compile", help="Run efficientnet-lite0 through torch.compile."),
    threads: Optional[int] = typer.Option(None, "--threads", help="torch threads (0 = one per core)."),
    timing_runs: int = typer.Option(5, "--timing-runs", help="Timed passes over the images for descriptor speed (median reported)."),
    force: bool = force_option("the JSON file"),
) -> None:
    """Recall@1, recall@N_r and candidate precision per backend and mode on an image folder with a truth matrix.

    Runs the full retrieval pipeline (descriptor, PCA, binary codes, Hamming prefilter, L2
    re-rank) with PCA/ITQ fitted on the whole folder, e.g. on ../shared/data/rtabmap_corridor
    with --exclude-frames 20 --mode paper --mode ranked. Given an MCAP log instead, it runs the
    replay's front end (online fit, descriptor cache) and scores candidates against ground-truth
    distances (--radius-m).
    """
    from lcv_replay.bench.retrieval import bench_backend, list_images, load_truth_matrix, query_frames, read_image
    from lcv_replay.config import load_config, replace_in
    from lcv_replay.errors import ConfigError, RetrievalError, require_seed
    from lcv_replay.fileio import check_output_path
    from lcv_replay.retrieval.descriptors import available_backends

    if json_out is not None:
        check_output_path(json_out, force=force)
    if timing_runs < 0:
        raise ConfigError(f"--timing-runs {timing_runs} must be >= 0")
    if fit is not None and fit not in ("online", "whole-log"):
        raise ConfigError(f"--fit {fit!r} is not known", fix="use 'online' or 'whole-log'")
    if precision is not None and precision not in ("fp32", "bf16"):
        raise ConfigError(f"--precision {precision!r} is not known", fix="use 'fp32' or 'bf16'")
    if pooling is not None and pooling not in ("avg", "gem", "multi"):
        raise ConfigError(f"--pooling {pooling!r} is not known", fix="use 'avg', 'gem' or 'multi'")
    if seed is not None:
        require_seed(seed, "--seed")
    from lcv_replay.retrieval.config import MODES

    base = load_config(config_file).retrieval
    modes = mode or [base.mode]
    for m in modes:
        if m not in MODES:
            raise ConfigError(f"--mode {m!r} is not known", fix="use 'ranked' or 'paper'")
    configs = []
    for m in modes:
        ranked = replace_in(base.ranked, candidates=candidates, code_bits=code_bits if m == "ranked" else None)
        configs.append(replace_in(
            base,
            mode=m,
            ranked=ranked,
            exclusion_frames=exclude_frames,
            top_k=top_k,
            hamming_threshold=hamming_threshold,
            code_bits=code_bits if m == "paper" else None,
            pooling=pooling,
            seed=seed,
            fit=fit,
            precision=precision,
            torch_compile=torch_compile,
            num_threads=threads,
        ))
    config = configs[0]
    names = backend or DEFAULT_BACKENDS
    known = available_backends()
    for name in names:
        if name not in known:
            raise ConfigError(f"unknown descriptor backend '{name}'", fix=f"use one of {', '.join(sorted(known))}")
    if images_dir.is_file():
        _bench_log(images_dir, names, configs, radius_m=radius_m, json_out=json_out)
        return
    if truth_matrix is None:
        raise ConfigError("an image folder needs --truth-matrix FILE", fix="pass the folder's N x N truth matrix")
    paths = list_images(images_dir, exclude=[truth_matrix])
    truth = load_truth_matrix(truth_matrix, len(paths))
    if len(query_frames(truth, config.exclusion_frames)) == 0:
        raise RetrievalError(
            f"no image has a true match more than Δt = {config.exclusion_frames} frames earlier, so nothing can be scored",
            path=truth_matrix,
            fix="pass a smaller --exclude-frames (e.g. 20 for rtabmap_corridor)",
        )
    images = [read_image(p) for p in paths]
    reports = []
    for name in names:
        for mode_config in configs:
            typer.echo(f"{name} ({mode_config.mode}): describing {len(images)} images ...", err=True)
            reports.append(bench_backend(name, images, truth, mode_config, timing_runs=timing_runs))
    _report(
        FOLDER_COLUMNS,
        [r.as_dict() for r in reports],
        json_out,
        {"images_dir": str(images_dir), "truth_matrix": str(truth_matrix), "images": len(images),
         "exclusion_frames": config.exclusion_frames, "fit": "whole-log"},
        key="backends",
    )


def _bench_log(path: Path, names: list[str], configs: list, *, radius_m: float, json_out: Optional[Path]) -> None:
    from lcv_replay.bench.retrieval import bench_log
    from lcv_replay.errors import ConfigError

    if not radius_m > 0:
        raise ConfigError(f"--radius-m {radius_m} must be > 0")
    reports = []
    for name in names:
        for config in configs:
            typer.echo(f"{name} ({config.mode}): describing {path} ...", err=True)
            reports.append(bench_log(path, name, config, radius_m=radius_m, cache_dir=Path(config.cache_dir) if config.cache_dir else None))
    typer.echo(f"(found = queries with a true revisit, ground truth < {radius_m:g} m, among their candidates; exh = the same without "
               "the prefilter, plain L2 over every eligible frame; same hdg = revisits seen within 45 deg of the first heading; "
               "false = false candidates / all)")
    _report(LOG_COLUMNS, [r.as_dict() for r in reports], json_out, {"log": str(path), "radius_m": radius_m, "fit": configs[0].fit}, key="backends")


@bench_app.command("retrieval-index")
def bench_retrieval_index(
    sizes: str = typer.Option("1000,10000,100000", "--sizes", help="Library sizes (comma-separated)."),
    variant: Optional[list[str]] = typer.Option(None, "--variant", metavar="MODE/ENGINE", help="MODE/ENGINE to measure; repeat for several (default: all: both modes, faiss's approximate indexes beside)."),
    vector_dim: int = typer.Option(1904, "--vector-dim", help="Re-rank vector size (1904 = default descriptor, 128 = PCA)."),
    queries: int = typer.Option(500, "--queries", help="Queries timed per size."),
    config_file: Optional[Path] = config_option("its [retrieval] code bits, T_b and M apply"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the rows as JSON."),
    force: bool = force_option("the JSON file"),
) -> None:
    """Per-query time of the first stage + L2 re-rank as the library grows, both modes in one run (synthetic codes)."""
    from lcv_replay.bench.retrieval import DEFAULT_INDEX_VARIANTS, INDEX_VARIANTS, index_query_times
    from lcv_replay.config import load_config
    from lcv_replay.errors import ConfigError
    from lcv_replay.fileio import check_output_path

    if json_out is not None:
        check_output_path(json_out, force=force)
    try:
        size_list = [int(x) for x in sizes.split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--sizes {sizes!r} must be comma-separated integers") from None
    if not size_list or min(size_list) < 1 or vector_dim < 1 or queries < 1:
        raise ConfigError("--sizes, --vector-dim and --queries must be positive")
    names = variant or list(DEFAULT_INDEX_VARIANTS)
    for name in names:
        if name not in INDEX_VARIANTS:
            raise ConfigError(f"unknown variant '{name}'", fix=f"use one of {', '.join(INDEX_VARIANTS)}")
    config = load_config(config_file).retrieval
    rows = index_query_times(size_list, variants=names, vector_dim=vector_dim, queries=queries, config=config)
    typer.echo("(query = first stage + L2 re-rank of what it passes; ×1st = query time against the smallest size; "
               "recall = share of the exact Hamming top M an approximate first stage returns)", err=True)
    _report(INDEX_COLUMNS, rows, json_out, {"queries": queries, "vector_dim": vector_dim, "uptime_load": _machine()["loadavg_1min"]}, key="rows")


@bench_app.command("descriptor-speed")
def bench_descriptor_speed(
    variant: Optional[list[str]] = typer.Option(None, "--variant", metavar="RUNG", help="Ladder rung; repeat for several (default: all)."),
    batch: int = typer.Option(8, "--batch", help="Images per forward pass."),
    runs: int = typer.Option(20, "--runs", help="Timed forward passes per process."),
    repeats: int = typer.Option(3, "--repeats", help="Fresh processes per variant (median of their medians is reported)."),
    size: int = typer.Option(224, "--size", help="Input size in pixels (a multiple of 32)."),
    threads: int = typer.Option(0, "--threads", help="torch threads for tuned variants (0 = one per core)."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Write the ladder as JSON."),
    force: bool = force_option("the JSON file"),
) -> None:
    """EfficientNet-Lite0 ms/image for each optimisation step (untuned eager ... folded + channels_last ...)."""
    from lcv_replay.bench.descriptor_speed import VARIANTS, speed_ladder
    from lcv_replay.errors import ConfigError
    from lcv_replay.fileio import check_output_path

    if json_out is not None:
        check_output_path(json_out, force=force)
    names = variant or list(VARIANTS)
    for name in names:
        if name not in VARIANTS:
            raise ConfigError(f"unknown variant '{name}'", fix=f"use one of {', '.join(VARIANTS)}")
    if batch < 1 or runs < 1 or repeats < 1 or size % 32 or size < 32:
        raise ConfigError("--batch, --runs and --repeats must be >= 1 and --size a multiple of 32")
    rows = speed_ladder(names, batch=batch, runs=runs, size_px=size, repeats=repeats, threads=threads)
    _report(SPEED_COLUMNS, rows, json_out, {}, key="variants")


Column = tuple[str, str, str]  # (row key, title, format spec)

FOLDER_COLUMNS: list[Column] = [
    ("backend", "backend", "20s"), ("mode", "mode", "7s"), ("dim", "dim", "5d"), ("queries", "queries", "7d"), ("recall_at_1", "R@1", "6.3f"),
    ("recall_at_10", "R@N_r", "6.3f"), ("candidate_precision", "prec", "6.3f"), ("candidates", "cands", "6d"),
    ("mean_prefilter_size", "prefilt", "7.2f"), ("exhaustive_recall_at_1", "exh R@1", "7.3f"),
    ("descriptor_frames_per_s", "img/s", "7.1f"), ("descriptor_warmup_s", "warm-up s", "9.2f"),
]
LOG_COLUMNS: list[Column] = [
    ("backend", "backend", "20s"), ("mode", "mode", "7s"), ("frames", "frames", "6d"), ("queries", "queries", "7d"),
    ("revisits_found", "found", "6.3f"), ("exhaustive_revisits_found", "exh", "6.3f"), ("same_heading_found", "same hdg", "8.3f"),
    ("recall_at_1", "R@1", "6.3f"), ("false_candidate_fraction", "false", "6.3f"), ("candidates", "cands", "6d"),
    ("mean_prefilter_size", "prefilt", "7.2f"), ("describe_s", "describe s", "10.1f"),
]
INDEX_COLUMNS: list[Column] = [
    ("library_frames", "library", "8d"), ("variant", "variant", "18s"), ("code_bits", "bits", "4d"),
    ("first_stage_us_median", "1st stage µs", "12.1f"), ("query_us_median", "query µs", "9.1f"), ("query_vs_smallest", "×1st", "5.2f"),
    ("query_us_p90", "p90 µs", "8.1f"), ("add_us_mean", "add µs", "7.1f"), ("mean_prefilter_size", "re-ranked", "9.1f"),
    ("recall_vs_exact", "recall", "6.3f"),
]
SPEED_COLUMNS: list[Column] = [
    ("variant", "variant", "26s"), ("ms_per_image_median", "ms/img", "8.2f"), ("ms_per_image_min", "min", "7.2f"),
    ("frames_per_s_median", "img/s", "7.1f"), ("warmup_s_median", "warm-up s", "9.1f"), ("cosine_min", "cos min", "9.6f"),
    ("max_abs_diff", "max|Δ|", "9.2e"), ("loadavg_1min_median", "load", "5.1f"), ("default", "default", "7s"),
]


def _cell(text_or_value, spec: str, *, title: bool = False) -> str:
    width = int(re.match(r"\d+", spec).group())
    left = spec.endswith("s")
    if isinstance(text_or_value, bool) and not title:
        text = "yes" if text_or_value else ""
    elif title or left:
        text = str(text_or_value)
    elif text_or_value is None or (isinstance(text_or_value, float) and math.isnan(text_or_value)):
        text = "n/a"
    else:
        text = format(text_or_value, spec)
    return text.ljust(width) if left else text.rjust(width)


def _report(columns: list[Column], rows: list[dict], json_out: Optional[Path], meta: dict, *, key: str) -> None:
    """Print ``rows`` as an aligned table and, with ``json_out``, write ``meta`` + machine + rows."""
    from lcv_replay.fileio import write_text_atomic

    header = " ".join(_cell(title, spec, title=True) for _, title, spec in columns)
    lines = [header, "-" * len(header)] + [" ".join(_cell(row[k], spec) for k, _, spec in columns) for row in rows]
    typer.echo("\n".join(lines))
    if json_out is not None:
        write_text_atomic(json_out, json.dumps({**meta, "machine": _machine(), key: rows}, indent=2) + "\n")
        typer.echo(f"wrote {json_out}", err=True)


def _machine() -> dict:
    import os

    return {
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "processor": platform.processor(),
        "python": platform.python_version(),
        "loadavg_1min": os.getloadavg()[0],
    }
