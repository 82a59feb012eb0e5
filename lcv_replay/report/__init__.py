"""A report to share: one self-contained HTML page per replay (``--report FILE.html``, or
``lcv-replay report REC.rrd -o FILE.html`` from any recording afterwards).

* :mod:`~lcv_replay.report.figures`: matplotlib figures from a run record;
* :mod:`~lcv_replay.report.html`: the page;
* :mod:`~lcv_replay.report.rrd`: a run record read back from a recording (``rerun.chunk.RrdReader``);
* :mod:`~lcv_replay.report.sink`: the sink that writes the page when a replay ends.
"""
