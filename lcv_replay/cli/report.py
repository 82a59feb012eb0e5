"""`lcv-replay report REC.rrd -o FILE.html` and `lcv-replay open REC.rrd --frame N`: a recording's
post-mortem afterwards (the HTML report, or the viewer at a given moment)."""

from __future__ import annotations

import socket
import time
from pathlib import Path
from typing import Optional

import typer

from lcv_replay.cli.app import app


@app.command("report", help="Write the HTML report of a recording (REC.rrd, written by a replay) into one self-contained file.")
def report_command(
    recording: Path = typer.Argument(..., metavar="REC.rrd", help="A recording written by 'lcv-replay LOG.mcap' (--save)."),
    output: Optional[Path] = typer.Option(None, "--output", "-o", metavar="FILE.html", help="The report to write (default: REC.html next to the recording)."),
    force: bool = typer.Option(False, "--force", "-f", help="Overwrite FILE.html if it exists."),
) -> None:
    from lcv_replay.fileio import check_output_path
    from lcv_replay.report.rrd import read_run_record
    from lcv_replay.report.sink import write_report

    target = output if output is not None else recording.with_suffix(".html")
    check_output_path(target, force=force)
    record = read_run_record(recording)
    write_report(target, record)
    typer.echo(f"wrote {target}  ({record.method} on {Path(record.log).name}: {len(record.loops)} constraints, {len(record.windows)} windows)")


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.3)
        return s.connect_ex(("127.0.0.1", port)) == 0


@app.command("open", help="Open a recording in the Rerun viewer at a frame (e.g. the first wrong acceptance the summary names).")
def open_command(
    recording: Path = typer.Argument(..., metavar="REC.rrd", help="A recording written by 'lcv-replay LOG.mcap'."),
    frame: Optional[int] = typer.Option(None, "--frame", min=0, help="Put the time cursor on this frame (paused)."),
    first_wrong: bool = typer.Option(False, "--first-wrong", help="Go to the first acceptance of a false loop (needs truth in the log)."),
    connect: Optional[str] = typer.Option(None, "--connect", help="Use a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy (default: the one on --port, else a new one)."),
    port: int = typer.Option(9876, "--port", help="gRPC port of the viewer to use or start."),
) -> None:
    from lcv_replay.errors import OutputError
    from lcv_replay.report.rrd import RecordingError, read_run_record

    if not recording.is_file():
        raise RecordingError("recording not found", path=recording, fix="pass the .rrd a replay wrote (--save)")
    if first_wrong:
        record = read_run_record(recording)
        wrong = record.first_wrong_acceptance()
        if wrong is None:
            raise RecordingError("the recording has no wrong acceptance" + ("" if record.has_truth else " (its log has no truth)"),
                                 path=recording, fix="open it without --first-wrong, or with --frame N")
        frame = wrong.first_accepted_frame
    from rerun.experimental import ViewerClient

    url = connect or f"rerun+http://127.0.0.1:{port}/proxy"
    try:
        if connect is None and not _listening(port):
            viewer = ViewerClient.spawn(port=port, hide_welcome_screen=True, detach_process=True)
        else:
            viewer = ViewerClient.connect(url)
        viewer.open(str(recording.resolve()))
        deadline = time.monotonic() + 30.0
        while viewer.get_state().loading and time.monotonic() < deadline:
            time.sleep(0.2)
        if frame is not None:
            viewer.set_time("frame", sequence=int(frame), play_state="paused")
    except (RuntimeError, OSError, TimeoutError) as exc:
        raise OutputError(f"the Rerun viewer could not show the recording ({str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__})",
                          path=recording, fix=f"start a viewer ('rerun') and retry, or open it by hand: rerun {recording}") from None
    where = f" at frame {frame} (paused)" if frame is not None else ""
    typer.echo(f"opened {recording} in the Rerun viewer on {url}{where}")
