"""``lcv-replay info``: a :class:`LogInfo` as ``ros2 bag info``-style text or as a stable JSON object.

The JSON keys are documented in docs/log-format.md ("lcv-replay info --json") and are stable:
``frames``, ``duration_s``, ``start_ns``, ``end_ns``, ``has_ground_truth``, ``has_candidates``,
``has_labels`` and ``topics`` (a list of ``{topic, schema, count, rate_hz}``), plus the extra keys
listed in :func:`info_to_json`. New keys may be added; existing keys keep their meaning.
"""

from __future__ import annotations

import datetime as _dt
from typing import Any

from lcv_replay.log.format import describe_warnings
from lcv_replay.log.reader import LogInfo


def info_to_json(info: LogInfo) -> dict[str, Any]:
    """The stable JSON object of ``lcv-replay info --json`` (plain ``dict`` of JSON types)."""
    meta = info.metadata
    return {
        "path": str(info.path),
        "file_size_bytes": info.file_size_bytes,
        "frames": info.frames,
        "duration_s": info.duration_s,
        "start_ns": info.start_ns,
        "end_ns": info.end_ns,
        "has_images": info.has_images,
        "has_right_images": info.has_right_images,
        "has_odometry": info.has_odometry,
        "has_ground_truth": info.has_ground_truth,
        "has_candidates": info.has_candidates,
        "has_labels": info.has_labels,
        "candidate_count": info.candidate_count,
        "true_loop_count": info.true_loop_count,
        "topics": [
            {"topic": t.topic, "schema": t.schema, "count": t.count, "rate_hz": round(t.rate_hz, 6)} for t in info.topics
        ],
        "message_count": info.message_count,
        "chunk_count": info.chunk_count,
        "image_format": info.image_format,
        "nominal_rate_hz": info.nominal_rate_hz,
        "dataset": meta.get("dataset"),
        "recorder": meta.get("recorder"),
        "recorder_version": meta.get("recorder_version"),
        "format_version": meta.get("format_version"),
        "recorder_config": info.recorder_config,
        "odometry_information": None if info.odometry_information is None else info.odometry_information.tolist(),
        "dropped_unpaired_images": info.dropped_unpaired_images,
        "recovered_messages": info.recovered_messages,
        "skipped_chunks": info.skipped_chunks,
        "recorder_warnings": dict(info.recorder_warnings),
    }


def _stamp_text(stamp_ns: int) -> str:
    seconds, nanos = divmod(stamp_ns, 1_000_000_000)
    when = _dt.datetime.fromtimestamp(seconds, tz=_dt.timezone.utc)
    return f"{when:%b %d %Y %H:%M:%S}.{nanos:09d} UTC ({seconds}.{nanos:09d})"


def _size_text(size_bytes: int) -> str:
    value = float(size_bytes)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{value:.1f} {unit}" if unit != "B" else f"{size_bytes} B"
        value /= 1024
    return f"{size_bytes} B"


def format_info(info: LogInfo) -> str:
    """``ros2 bag info``-style text: file, size, times, per-topic schema/count/rate, frames and contents."""
    meta = info.metadata
    lines = [
        f"Files:             {info.path.name}",
        f"Bag size:          {_size_text(info.file_size_bytes)}",
        "Storage id:        mcap",
        f"Duration:          {info.duration_s:.3f}s",
        f"Start:             {_stamp_text(info.start_ns)}",
        f"End:               {_stamp_text(info.end_ns)}",
        f"Messages:          {info.message_count}",
    ]
    width = max((len(t.topic) for t in info.topics), default=0)
    schema_width = max((len(t.schema) for t in info.topics), default=0)
    for k, t in enumerate(info.topics):
        label = "Topic information: " if k == 0 else " " * 19
        lines.append(
            f"{label}Topic: {t.topic:<{width}} | Type: {t.schema:<{schema_width}} | Count: {t.count:>6} | Rate: {t.rate_hz:8.3f} Hz"
        )
    kinds = []
    if info.has_images:
        kinds.append(f"{'stereo' if info.has_right_images else 'mono'} images ({info.image_format})")
    kinds.append("odometry" if info.has_odometry else "no odometry")
    lines += [
        f"Frames:            {info.frames} at {info.nominal_rate_hz:g} Hz nominal: {', '.join(kinds)}",
        f"Ground truth:      {'yes' if info.has_ground_truth else 'no'}",
        f"Loop candidates:   {info.candidate_count if info.has_candidates else 'no'}",
        f"Loop labels:       {f'yes ({info.true_loop_count} true pairs)' if info.has_labels else 'no'}",
    ]
    if meta:
        lines.append(
            f"Dataset:           {meta.get('dataset', '?')} (recorder {meta.get('recorder', '?')} "
            f"{meta.get('recorder_version', '?')}, format {meta.get('format_version', '?')})"
        )
    else:
        lines.append("Dataset:           unknown (no 'lcv' metadata record)")
    if info.recorder_warnings:
        lines.append(f"Warnings:          {describe_warnings(info.recorder_warnings)} (when recorded)")
    if info.dropped_unpaired_images:
        lines.append(f"Dropped:           {info.dropped_unpaired_images} stereo images without a partner")
    if info.recovered_messages is not None:
        lines.append(
            f"Recovered:         {info.recovered_messages} messages from {info.chunk_count} complete chunks"
            + (f" ({info.skipped_chunks} damaged chunks skipped)" if info.skipped_chunks else "")
        )
    return "\n".join(lines)
