"""``lcv-replay record synthetic -o OUT.mcap``: record the built-in synthetic street world.

The recorder (``recorders/synthetic.py``, which imports OpenCV) is imported inside the command body
so that ``--help`` stays fast.
"""

from __future__ import annotations

import contextlib
import enum
import re
from pathlib import Path
from typing import Iterator

import typer

from lcv_replay.cli.app import bench_app, check_outputs, force_option, record_app
from lcv_replay.cli.record import ImageFormatChoice, run_recording
from lcv_replay.errors import ConfigError


class OdometryChoice(str, enum.Enum):
    simulated = "simulated"
    vo = "vo"


_RESOLUTION = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_resolution(text: str) -> tuple[int, int]:
    """``"640x480" -> (640, 480)``; :class:`ConfigError` naming the value otherwise."""
    match = _RESOLUTION.match(text)
    if not match:
        raise ConfigError(f"--resolution {text!r} is not WIDTHxHEIGHT", fix="pass e.g. --resolution 640x480 or 320x240")
    return int(match.group(1)), int(match.group(2))


@contextlib.contextmanager
def _progress_bar(quiet: bool) -> Iterator:
    """A rich progress bar on stderr with the frame rate; yields ``progress(done, total)`` or ``None``."""
    if quiet:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(
        TextColumn("[bold]synthetic"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("frames"),
        TextColumn("{task.fields[rate]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        transient=True,
    ) as bar:
        task = bar.add_task("synthetic", total=None, rate="")

        def update(done: int, total: int) -> None:
            speed = bar.tasks[0].speed
            bar.update(task, completed=done, total=total, rate=f"{speed:5.1f} frames/s" if speed else "")

        yield update


@record_app.command("synthetic")
def record_synthetic_command(
    out: Path = typer.Option(..., "--out", "-o", help="Output .mcap file (written atomically)."),
    frames: int = typer.Option(1500, "--frames", min=1, help="Frames to record (~0.8 m of route each at 10 Hz)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the world, its textures, the route and the odometry noise."),
    resolution: str = typer.Option("640x480", "--resolution", help="Image size WIDTHxHEIGHT, e.g. 640x480 or 320x240."),
    odometry: OdometryChoice = typer.Option(OdometryChoice.simulated, "--odometry", case_sensitive=False, help="simulated: true motion with drift; vo: stereo VO on the rendered images."),
    drift_translation_pct: float = typer.Option(1.0, "--drift-translation-pct", help="Per-step translation noise, % of the step length (standard deviation)."),
    drift_scale_bias_pct: float = typer.Option(0.5, "--drift-scale-bias-pct", help="Systematic scale error of the odometry, %."),
    drift_yaw_deg_per_m: float = typer.Option(0.15, "--drift-yaw-deg-per-m", help="Per-step yaw noise, degrees per metre of the step (standard deviation)."),
    drift_yaw_bias_deg_per_m: float = typer.Option(0.008, "--drift-yaw-bias-deg-per-m", help="Systematic yaw drift, degrees per metre travelled."),
    image_format: ImageFormatChoice = typer.Option(ImageFormatChoice.png, "--image-format", case_sensitive=False, help="png (lossless), jpeg or raw."),
    jpeg_quality: int = typer.Option(95, "--jpeg-quality", min=1, max=100, help="JPEG quality with --image-format jpeg."),
    force: bool = force_option("OUT"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and no summary line."),
    live: bool = typer.Option(False, "--live", help="Write OUT itself chunk by chunk (one flushed chunk per frame) so that 'lcv-replay OUT --follow' can watch it; gives up the atomic rename."),
) -> None:
    """Record the built-in synthetic street world: rendered stereo, drifting odometry, ground truth.

    A procedural city (facades, street, sky) with perceptual aliasing on purpose, driven along a
    route that revisits places (once in the opposite direction). Deterministic for a seed.
    """
    from recorders.synthetic import DriftConfig, SyntheticOptions, record_synthetic

    width_px, height_px = parse_resolution(resolution)
    options = SyntheticOptions(
        frames=frames,
        seed=seed,
        width_px=width_px,
        height_px=height_px,
        drift=DriftConfig(
            translation_noise_pct=drift_translation_pct,
            scale_bias_pct=drift_scale_bias_pct,
            yaw_noise_deg_per_m=drift_yaw_deg_per_m,
            yaw_bias_deg_per_m=drift_yaw_bias_deg_per_m,
        ),
        odometry=odometry.value,  # type: ignore[arg-type]
        image_format=image_format.value,  # type: ignore[arg-type]
        jpeg_quality=jpeg_quality,
    )
    def run():
        with _progress_bar(quiet) as progress:
            return record_synthetic(out, options, force=force, progress=progress, live=live)

    run_recording(run, quiet=quiet)


@bench_app.command("synthetic", help="Recorder benchmark: frames/s, CPU per frame and MB per 1000 frames of 'record synthetic'.")
def bench_synthetic_command(
    frames: int = typer.Option(1500, "--frames", min=1, help="Frames per recording."),
    resolution: list[str] = typer.Option(["640x480"], "--resolution", help="WIDTHxHEIGHT; repeat for several."),
    image_format: list[ImageFormatChoice] = typer.Option([ImageFormatChoice.png], "--image-format", case_sensitive=False, help="png, jpeg or raw; repeat for several."),
    odometry: OdometryChoice = typer.Option(OdometryChoice.simulated, "--odometry", case_sensitive=False, help="simulated or vo."),
    workdir: Path = typer.Option(Path("bench-out"), "--workdir", help="Scratch folder for the recorded log (a scratch file, always overwritten)."),
    output: Path = typer.Option(Path("bench-out/synthetic_bench.json"), "-o", "--output", help="JSON results."),
    force: bool = force_option("the JSON results"),
) -> None:
    import json
    from dataclasses import asdict

    from lcv_replay.fileio import write_text_atomic
    from recorders.synthetic import SyntheticOptions, format_bench_results, run_synthetic_benchmark

    sizes = [parse_resolution(text) for text in resolution]
    output.parent.mkdir(parents=True, exist_ok=True)
    check_outputs(output, force=force)
    workdir.mkdir(parents=True, exist_ok=True)
    results = []
    for width_px, height_px in sizes:
        for fmt in image_format:
            options = SyntheticOptions(frames=frames, width_px=width_px, height_px=height_px, image_format=fmt.value, odometry=odometry.value)  # type: ignore[arg-type]
            results.append(run_synthetic_benchmark(workdir, options))
            typer.echo(format_bench_results(results[-1:]).splitlines()[-1] if len(results) > 1 else format_bench_results(results))
    write_text_atomic(output, json.dumps([asdict(r) for r in results], indent=2) + "\n")
    typer.echo(f"wrote {output}")
