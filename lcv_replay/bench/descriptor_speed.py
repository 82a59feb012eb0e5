"""The EfficientNet-Lite0 speed ladder: ms per image for each optimisation step, on this CPU.

Each variant runs in a fresh Python process, because the allocator tuning (``mallopt``) and the
thread count are process-wide and cannot be undone::

    python -m lcv_replay.bench.descriptor_speed fold-bn-pad-cl --batch 8 --runs 20   # one JSON line

:func:`speed_ladder` runs every variant ``repeats`` times (interleaved, so background load hits
them alike) and reports the median of the per-process medians. The rungs:

* the torch ladder (``eager-untuned`` ... ``fold-bn-pad-cl-bf16``): the network alone on a
  normalised float batch; its descriptor (average-pooled head, L2-normalised) is compared with the
  library's own model on the same input (``cosine_min``, ``max_abs_diff``);
* the two engines as ``lcv-replay`` runs them, uint8 images in, descriptors out
  (``EfficientNetLite0Backend.describe_prepared``): ``onnxruntime`` (the default engine, the row
  with ``"default": true``) and ``torch`` (mode "paper"'s); both are compared with the torch
  export module on the same input;
* ``matmul-bound``: this CPU's float32 matrix-multiply throughput (``torch.mm`` of 2048 x 2048
  matrices, same threads), expressed as the ms/image that Lite0's 0.77 GFLOP would take at that
  rate: a floor no engine beats.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

from lcv_replay.errors import RetrievalError


@dataclass(frozen=True)
class Variant:
    """One rung of the ladder.

    Attributes:
        model: ``"reference"`` (the library's module tree) or ``"folded"`` (FoldedLite0).
        tune: apply the allocator tuning and set the thread count explicitly.
        channels_last: channels_last weights and input.
        fold_padding: (folded only) fold the ZeroPad2d ops into the convolutions.
        mode: ``"eager"``, ``"jit"`` (trace + freeze + optimize_for_inference), ``"compile"``
            (``torch.compile`` with inductor freezing) or ``"bf16"`` (eager under bf16 autocast);
            ``"engine"``: the backend with ``retrieval.engine = engine``; ``"matmul"``: the bound.
        engine: for ``mode = "engine"``, ``"onnxruntime"`` or ``"torch"``.
    """

    help: str
    model: str = "folded"
    tune: bool = True
    channels_last: bool = True
    fold_padding: bool = True
    mode: str = "eager"
    engine: str = ""


VARIANTS: dict[str, Variant] = {
    "eager-untuned": Variant("library model, default threads and allocator", "reference", tune=False, channels_last=False),
    "eager-tuned": Variant("library model, threads + mallopt + passive OpenMP wait", "reference", channels_last=False),
    "eager-tuned-cl": Variant("library model, threads + mallopt + passive wait, channels_last", "reference"),
    "fold-bn-cl": Variant("BatchNorm folded (ZeroPad2d kept), channels_last", fold_padding=False),
    "fold-bn-pad-cl": Variant("BatchNorm and padding folded, channels_last (the backend's path)"),
    "fold-bn-pad-cl-jit": Variant("... + torch.jit trace/freeze/optimize_for_inference", mode="jit"),
    "fold-bn-pad-cl-compile": Variant("... + torch.compile (inductor, freezing)", mode="compile"),
    "fold-bn-pad-cl-bf16": Variant("... under bf16 autocast (changes descriptors)", mode="bf16"),
    "torch": Variant("engine torch as lcv-replay runs it (uint8 in, descriptor out; mode paper)", mode="engine", engine="torch"),
    "onnxruntime": Variant("engine onnxruntime as lcv-replay runs it (the default)", mode="engine", engine="onnxruntime"),
    "matmul-bound": Variant("0.77 GFLOP at this CPU's float32 matmul rate (a floor)", mode="matmul"),
}
DEFAULT_ENGINE = "onnxruntime"  # what RetrievalConfig() resolves to (mode "ranked")


def run_variant(name: str, *, batch: int = 8, runs: int = 20, size_px: int = 224, threads: int = 0, seed: int = 0) -> dict:
    """Measure one variant in this process (call it in a fresh process: tuning is global)."""
    variant = VARIANTS[name]
    if variant.mode == "engine":
        return _run_engine(name, variant, batch=batch, runs=runs, size_px=size_px, threads=threads, seed=seed)
    if variant.mode == "matmul":
        return _run_matmul(name, variant, batch=batch, runs=runs, size_px=size_px, threads=threads)
    from lcv_replay.retrieval import efficientnet as enet

    start = time.perf_counter()
    if variant.tune:
        enet.tune_omp_wait()
        enet.tune_allocator()
        enet.set_threads(threads)
    torch = enet.import_torch()
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, size=(batch, size_px, size_px, 3), dtype=np.uint8)
    reference = enet.load_reference_model(size_px)
    with torch.inference_mode():
        x = (torch.from_numpy(images).permute(0, 3, 1, 2).float() - enet.INPUT_MEAN) / enet.INPUT_STD
        x_nchw = x.contiguous()
        expected = torch.nn.functional.normalize(reference.extract_features(x_nchw).mean(dim=(2, 3)), dim=1)

    if variant.model == "reference":
        model = reference
        def forward(inp):
            return model.extract_features(inp)
    else:
        model = enet.build_folded_model(reference, taps=("head",), fold_padding=variant.fold_padding)
        def forward(inp):
            return model(inp)[0]
    if variant.channels_last:
        model = model.to(memory_format=torch.channels_last)
        x = x.contiguous(memory_format=torch.channels_last)
    else:
        x = x_nchw
    with torch.inference_mode():
        if variant.mode == "jit":
            traced = torch.jit.optimize_for_inference(torch.jit.freeze(torch.jit.trace(model, x, strict=False)))
            def forward(inp):
                return traced(inp)[0]
        elif variant.mode == "compile":
            import torch._inductor.config as inductor_config

            inductor_config.freezing = True
            compiled = torch.compile(model)
            def forward(inp):
                return compiled(inp)[0]
        elif variant.mode == "bf16":
            eager = forward
            def forward(inp):
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return eager(inp).float()
        got = torch.nn.functional.normalize(forward(x).float().mean(dim=(2, 3)), dim=1)
        warmup_s = time.perf_counter() - start
        times = []
        for _ in range(runs + 2):
            t0 = time.perf_counter()
            forward(x)
            times.append((time.perf_counter() - t0) / batch)
    times = times[2:]
    cosine = (got * expected).sum(dim=1)
    return {
        "variant": name,
        "help": variant.help,
        "batch": batch,
        "size_px": size_px,
        "threads": torch.get_num_threads(),
        "ms_per_image_median": 1000.0 * statistics.median(times),
        "ms_per_image_min": 1000.0 * min(times),
        "warmup_s": warmup_s,
        "cosine_min": float(cosine.min()),
        "max_abs_diff": float((got - expected).abs().max()),
        "loadavg_1min": os.getloadavg()[0],
    }


def _row(name: str, variant: Variant, *, batch: int, size_px: int, threads: int, times_s: list[float], warmup_s: float,
         cosine: float | None, max_abs_diff: float | None) -> dict:
    return {
        "variant": name,
        "help": variant.help,
        "batch": batch,
        "size_px": size_px,
        "threads": threads,
        "ms_per_image_median": 1000.0 * statistics.median(times_s),
        "ms_per_image_min": 1000.0 * min(times_s),
        "warmup_s": warmup_s,
        "cosine_min": cosine,
        "max_abs_diff": max_abs_diff,
        "loadavg_1min": os.getloadavg()[0],
    }


def _run_engine(name: str, variant: Variant, *, batch: int, runs: int, size_px: int, threads: int, seed: int) -> dict:
    """The backend as lcv-replay builds it, timed on ``describe_prepared`` (uint8 batch in)."""
    from lcv_replay.retrieval.config import RetrievalConfig
    from lcv_replay.retrieval.descriptors import make_backend

    start = time.perf_counter()
    backend = make_backend("efficientnet-lite0", RetrievalConfig(engine=variant.engine, input_size_px=size_px, batch_size=batch, num_threads=threads))
    if backend.engine != variant.engine:
        raise RuntimeError(f"asked for engine {variant.engine}, got {backend.engine}")
    images = np.random.default_rng(seed).integers(0, 256, size=(batch, size_px, size_px, 3), dtype=np.uint8)
    got = backend.describe_prepared(images)
    warmup_s = time.perf_counter() - start
    times = []
    for _ in range(runs + 2):
        t0 = time.perf_counter()
        backend.describe_prepared(images)
        times.append((time.perf_counter() - t0) / batch)
    expected = _torch_descriptor(images, backend)  # after timing: torch's build cost stays out of warm-up
    cosine = (got * expected).sum(axis=1)
    return _row(name, variant, batch=batch, size_px=size_px, threads=backend.num_threads, times_s=times[2:], warmup_s=warmup_s,
                cosine=float(cosine.min()), max_abs_diff=float(np.abs(got - expected).max()))


def _torch_descriptor(images: np.ndarray, backend) -> np.ndarray:
    """The descriptor of ``images`` from the torch export module (the reference both engines match)."""
    from lcv_replay.retrieval import efficientnet as enet
    from lcv_replay.retrieval.onnx_engine import DescriptorNet

    torch = enet.import_torch()
    net = DescriptorNet(enet.build_folded_model(enet.load_reference_model(backend.input_size_px), taps=backend.pooling.taps), backend.pooling).eval()
    with torch.no_grad():
        return net(torch.from_numpy(images)).numpy()


def _run_matmul(name: str, variant: Variant, *, batch: int, runs: int, size_px: int, threads: int) -> dict:
    """float32 ``torch.mm`` throughput as ms/image for Lite0's FLOPs (a floor for any engine)."""
    from lcv_replay.retrieval import efficientnet as enet

    start = time.perf_counter()
    enet.tune_omp_wait()  # as the torch engine runs
    threads = enet.set_threads(threads)
    torch = enet.import_torch()
    n = 2048
    a, b = torch.randn(n, n), torch.randn(n, n)
    torch.mm(a, b)
    warmup_s = time.perf_counter() - start
    flops = enet.lite0_flops(size_px)
    times = []
    for _ in range(max(3, runs // 2) + 1):
        t0 = time.perf_counter()
        torch.mm(a, b)
        times.append((time.perf_counter() - t0) * flops / (2.0 * n**3))  # seconds per image at this rate
    row = _row(name, variant, batch=batch, size_px=size_px, threads=threads, times_s=times[1:], warmup_s=warmup_s, cosine=None, max_abs_diff=None)
    row["gflops_median"] = flops / (row["ms_per_image_median"] / 1000.0) / 1e9
    return row


def speed_ladder(
    names: list[str] | None = None, *, batch: int = 8, runs: int = 20, size_px: int = 224, repeats: int = 3, threads: int = 0
) -> list[dict]:
    """Run each variant ``repeats`` times in fresh processes; one summary dict per variant."""
    names = names or list(VARIANTS)
    results: dict[str, list[dict]] = {n: [] for n in names}
    for _ in range(repeats):
        for name in names:
            cmd = [sys.executable, "-m", "lcv_replay.bench.descriptor_speed", name, "--batch", str(batch), "--runs", str(runs), "--size", str(size_px), "--threads", str(threads)]
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if proc.returncode != 0:
                last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
                raise RetrievalError(f"descriptor-speed variant {name} failed: {last}", fix="run it alone: python -m lcv_replay.bench.descriptor_speed " + name)
            results[name].append(json.loads(proc.stdout.strip().splitlines()[-1]))
    summary = []
    for name, rows in results.items():
        summary.append(
            {
                **{k: rows[0][k] for k in ("variant", "help", "batch", "size_px", "threads")},
                "ms_per_image_median": statistics.median(r["ms_per_image_median"] for r in rows),
                "ms_per_image_min": min(r["ms_per_image_min"] for r in rows),
                "frames_per_s_median": 1000.0 / statistics.median(r["ms_per_image_median"] for r in rows),
                "warmup_s_median": statistics.median(r["warmup_s"] for r in rows),
                "cosine_min": None if rows[0]["cosine_min"] is None else min(r["cosine_min"] for r in rows),
                "max_abs_diff": None if rows[0]["max_abs_diff"] is None else max(r["max_abs_diff"] for r in rows),
                "loadavg_1min_median": statistics.median(r["loadavg_1min"] for r in rows),
                "processes": len(rows),
                "per_process_ms_median": [round(r["ms_per_image_median"], 3) for r in rows],
                "default": name == DEFAULT_ENGINE,
                **({"gflops_median": statistics.median(r["gflops_median"] for r in rows)} if "gflops_median" in rows[0] else {}),
            }
        )
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variant", choices=sorted(VARIANTS))
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--size", type=int, default=224)
    parser.add_argument("--threads", type=int, default=0)
    args = parser.parse_args(argv)
    result = run_variant(args.variant, batch=args.batch, runs=args.runs, size_px=args.size, threads=args.threads)
    sys.stdout.write(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
