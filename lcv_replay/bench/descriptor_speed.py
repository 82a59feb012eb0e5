"""The EfficientNet-Lite0 speed ladder: ms per image for each optimisation step, on this CPU.

Each variant runs in a fresh Python process, because the allocator tuning (``mallopt``) and the
thread count are process-wide and cannot be undone::

    python -m lcv_replay.bench.descriptor_speed fold-bn-pad-cl --batch 8 --runs 20   # one JSON line

:func:`speed_ladder` runs every variant ``repeats`` times (interleaved, so background load hits
them alike) and reports the median of the per-process medians. Every variant's descriptor
(average-pooled head, L2-normalised) is compared with the library's own model on the same input:
``cosine_min`` and ``max_abs_diff``.
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


@dataclass(frozen=True)
class Variant:
    """One rung of the ladder.

    Attributes:
        model: ``"reference"`` (the library's module tree) or ``"folded"`` (FoldedLite0).
        tune: apply the allocator tuning and set the thread count explicitly.
        channels_last: channels_last weights and input.
        fold_padding: (folded only) fold the ZeroPad2d ops into the convolutions.
        mode: ``"eager"``, ``"jit"`` (trace + freeze + optimize_for_inference), ``"compile"``
            (``torch.compile`` with inductor freezing) or ``"bf16"`` (eager under bf16 autocast).
    """

    help: str
    model: str = "folded"
    tune: bool = True
    channels_last: bool = True
    fold_padding: bool = True
    mode: str = "eager"


VARIANTS: dict[str, Variant] = {
    "eager-untuned": Variant("library model, default threads and allocator", "reference", tune=False, channels_last=False),
    "eager-tuned": Variant("library model, threads + mallopt", "reference", channels_last=False),
    "eager-tuned-cl": Variant("library model, threads + mallopt, channels_last", "reference"),
    "fold-bn-cl": Variant("BatchNorm folded (ZeroPad2d kept), channels_last", fold_padding=False),
    "fold-bn-pad-cl": Variant("BatchNorm and padding folded, channels_last (the backend's path)"),
    "fold-bn-pad-cl-jit": Variant("... + torch.jit trace/freeze/optimize_for_inference", mode="jit"),
    "fold-bn-pad-cl-compile": Variant("... + torch.compile (inductor, freezing)", mode="compile"),
    "fold-bn-pad-cl-bf16": Variant("... under bf16 autocast (changes descriptors)", mode="bf16"),
}


def run_variant(name: str, *, batch: int = 8, runs: int = 20, size_px: int = 224, threads: int = 0, seed: int = 0) -> dict:
    """Measure one variant in this process (call it in a fresh process: tuning is global)."""
    variant = VARIANTS[name]
    from lcv_replay.retrieval import efficientnet as enet

    start = time.perf_counter()
    if variant.tune:
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
                raise RuntimeError(f"variant {name} failed: {proc.stderr.strip().splitlines()[-1:]}")
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
                "cosine_min": min(r["cosine_min"] for r in rows),
                "max_abs_diff": max(r["max_abs_diff"] for r in rows),
                "loadavg_1min_median": statistics.median(r["loadavg_1min"] for r in rows),
                "processes": len(rows),
                "per_process_ms_median": [round(r["ms_per_image_median"], 3) for r in rows],
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
