"""Entity paths of a replay recording and its default Rerun layout (stored in every .rrd).

Entity paths are named after what they hold, so that a user (or a test) finds them by name:

==============================  =====================================================================
``/camera/left``                left image, every ``image_every``-th frame (JPEG)
``/camera/right``               right image (``rerun.log_right_image``)
``/retrieval/code``             the query's binary code as a 1 × N_b image (white = 1)
``/retrieval/distances``        L2 distance of the rank-r re-ranked match (one series per rank)
``/retrieval/matches``          the top-N matches: rank, frame, L2, Hamming (markdown table)
``/retrieval/lines``            query → match lines on the map
``/constraints/segments``       every judged constraint as a segment on the rank-1 map, coloured by
                                state, with ``constraint_id``, ``query_frame``, ``match_frame``,
                                ``similarity``, ``state`` as instance data
``/constraints/pending``        constraints arrived since the last step (not judged yet; the newest 300)
``/hypotheses/trajectories``    the top-k hypotheses' trajectories, labelled by rank
``/hypotheses/ranks``           the ranking key of every kept hypothesis in rank order (bar chart, rank 1
                                first; the score for ``ilv``), with ``hypothesis_id`` and ``score``
``/hypotheses/consistency``     hypothesis × constraint consistency (tensor, rows by rank)
``/hypotheses/tree``            generation tree: nodes = hypotheses, edges parent → child
``/hypotheses/sequences``       the constraint sequence that built each top hypothesis (markdown)
``/trajectories/odometry``      odometry
``/trajectories/ground_truth``  ground truth, moved onto the odometry's first pose
``/trajectories/best``          the current best estimate (rank-1, extended by odometry)
``/trajectories/current``       the current pose on the best estimate
``/metrics/...``                time series: precision, recall, ate_rmse_m, accepted, constraints,
                                hypotheses, prefilter_size; wall clock: frame_time_s and
                                stage_time_s (one instance per verifier stage)
``/events``                     loop-closure events (text log)
``/report``                     config, log metadata and final summary (markdown, static)
``/report/timing``              wall time, × real time, set-up time (markdown, static)
``/postmortem/<table>``         the run record (static columns, see ``sinks.run_record``): what
                                ``lcv-replay report REC.rrd`` reads back; in no view
==============================  =====================================================================

Timelines: ``frame`` (sequence, replay-local index) and ``log_time`` (the MCAP timestamp, ns) on
every temporal row; ``window`` (sequence) additionally on the rows logged at a verifier step.
"""

from __future__ import annotations

CAMERA_LEFT = "/camera/left"
CAMERA_RIGHT = "/camera/right"
RETRIEVAL_CODE = "/retrieval/code"
RETRIEVAL_DISTANCES = "/retrieval/distances"
RETRIEVAL_MATCHES = "/retrieval/matches"
RETRIEVAL_LINES = "/retrieval/lines"
CONSTRAINTS_ACCEPTED = "/constraints/accepted"
CONSTRAINTS_WRONG = "/constraints/wrong"
CONSTRAINTS_MISSED = "/constraints/missed"
CONSTRAINTS_REJECTED = "/constraints/rejected"
CONSTRAINTS_AMBIGUOUS = "/constraints/ambiguous"
CONSTRAINTS_PENDING = "/constraints/pending"
HYPOTHESES_TRAJECTORIES = "/hypotheses/trajectories"
HYPOTHESES_RANKS = "/hypotheses/ranks"
HYPOTHESES_CONSISTENCY = "/hypotheses/consistency"
HYPOTHESES_TREE = "/hypotheses/tree"
HYPOTHESES_SEQUENCES = "/hypotheses/sequences"
TRAJ_ODOMETRY = "/trajectories/odometry"
TRAJ_GROUND_TRUTH = "/trajectories/ground_truth"
TRAJ_BEST = "/trajectories/best"
TRUTH_WRONG = "/trajectories/ground_truth/wrong_loops"
TRUTH_MISSED = "/trajectories/ground_truth/missed_loops"
TRAJ_CURRENT = "/trajectories/current"
METRICS = "/metrics"
EVENTS = "/events"
REPORT = "/report"
REPORT_TIMING = "/report/timing"
STAGE_TIMES = "/metrics/stage_time_s"
FRAME_TIME = "/metrics/frame_time_s"
POSTMORTEM = "/postmortem"
LEGEND = "/legend"

#: The only entities that hold wall-clock measurements (and, in the run record's ``volatile`` table,
#: the recording's own path); everything else in a recording is a deterministic function of the
#: log, the config and the seed.
WALL_CLOCK_ENTITIES = (FRAME_TIME, STAGE_TIMES, REPORT_TIMING, f"{POSTMORTEM}/volatile")

#: Roots of the entities drawn on the map; each gets a static y-flip so the 2-D map is y-up.
MAP_ROOTS = ("/trajectories", "/constraints", "/hypotheses", "/retrieval")

#: The judged constraints, one entity per verdict (each row: segments with ``class_ids`` =
#: ``ConstraintState`` and ``constraint_id``, ``query_frame``, ``match_frame``, ``similarity``, ``state``).
CONSTRAINT_ENTITIES = (CONSTRAINTS_ACCEPTED, CONSTRAINTS_WRONG, CONSTRAINTS_MISSED, CONSTRAINTS_REJECTED, CONSTRAINTS_AMBIGUOUS)

#: What the map view shows; drawn bottom to top by each entity's draw order (``DRAW_ORDER``).
MAP_ENTITIES = (
    TRAJ_GROUND_TRUTH, TRAJ_ODOMETRY, HYPOTHESES_TRAJECTORIES, TRAJ_BEST, TRAJ_CURRENT,
    CONSTRAINTS_REJECTED, CONSTRAINTS_PENDING, RETRIEVAL_LINES, CONSTRAINTS_AMBIGUOUS,
    CONSTRAINTS_ACCEPTED, CONSTRAINTS_MISSED, CONSTRAINTS_WRONG, TRUTH_MISSED, TRUTH_WRONG,
)
#: Draw order on the map (higher on top): candidates and references under the estimate, the
#: verdict (accepted, missed, wrong) over it.
DRAW_ORDER = {
    CONSTRAINTS_REJECTED: 1.0, CONSTRAINTS_PENDING: 2.0, TRAJ_GROUND_TRUTH: 3.0, TRAJ_ODOMETRY: 4.0,
    HYPOTHESES_TRAJECTORIES: 5.0, RETRIEVAL_LINES: 6.0, TRAJ_BEST: 10.0, CONSTRAINTS_AMBIGUOUS: 11.0,
    CONSTRAINTS_ACCEPTED: 12.0, CONSTRAINTS_MISSED: 13.0, CONSTRAINTS_WRONG: 14.0, TRAJ_CURRENT: 15.0,
    TRUTH_MISSED: 7.0, TRUTH_WRONG: 8.0,
}

FRAME_TIMELINE = "frame"
LOG_TIME_TIMELINE = "log_time"
WINDOW_TIMELINE = "window"


def metric_path(name: str) -> str:
    """``/metrics/<name>``."""
    return f"{METRICS}/{name}"


def rank_key_name(method: str) -> str:
    """What the rank chart shows for ``method``: the key hypotheses are sorted by."""
    if method == "ilv+":
        return "TLS key = cost saved − odometry χ², higher ranks first"
    return "score = constraints consistent, higher ranks first"


def _full_range(frames: int | None):
    """An x axis over the whole log (frame 0 to the last), not a window around the cursor."""
    import rerun as rr
    import rerun.blueprint as rrb

    if not frames:
        return None
    boundary = rr.TimeRangeBoundary
    return rrb.archetypes.TimeAxis(
        view_range=rr.TimeRange(start=boundary.absolute(seq=0), end=boundary.absolute(seq=max(frames - 1, 1))),
        link="Independent",
    )


def default_blueprint(*, has_images: bool, has_retrieval: bool, frames: int | None = None, method: str = "ilv+"):
    """The default layout; it opens on the answer.

    * left: the map (final estimate with its accepted loops; wrong ones red and thick, missed ones
      orange; ground truth and odometry underneath; rejected candidates faint) over its legend (and
      the camera, for image logs);
    * middle: retrieval (image logs: the retrieved frames, their distances, the query code) over the
      top hypotheses' table and their generation tree;
    * right: the rank chart (naming its key), the consistency of the top hypotheses with the
      deciding constraints, metrics over the whole log (precision/recall on 0..1), and the events
      table (window ends, wrong acceptances, missed loops, rank-1 changes) with a readable frame column.

    The time panel is expanded and *following*: a finished recording opens at its end (the answer),
    a live one follows the newest frame; nothing plays by itself.

    Returns a ``rerun.blueprint.Blueprint`` (rerun is imported here, not at module import).
    """
    import rerun.blueprint as rrb
    from rerun.blueprint.archetypes import ScalarAxis, TextLogColumns
    from rerun.blueprint.encodings import TextLogColumn, TimelineColumn

    map_view = rrb.Spatial2DView(
        name="Map: best estimate and its loops",
        origin="/",
        contents=[f"+ {path}" for path in MAP_ENTITIES],
    )
    legend = rrb.TextDocumentView(name="Legend", origin=LEGEND)
    if has_images:  # the camera beside the legend, under the map: the middle keeps room for tables
        left = rrb.Vertical(map_view, rrb.Horizontal(legend, rrb.Spatial2DView(name="Camera (left)", origin=CAMERA_LEFT),
                                                     column_shares=[3, 2]), row_shares=[10, 4])
    else:
        left = rrb.Vertical(map_view, legend, row_shares=[10, 3])
    hypotheses = rrb.Vertical(
        rrb.TextDocumentView(name="Top hypotheses (rank, key, constraints)", origin=HYPOTHESES_SEQUENCES),
        rrb.GraphView(name="Generation tree of the top hypotheses", origin=HYPOTHESES_TREE),
        row_shares=[2, 3],
        name="Hypotheses",
    )
    report = rrb.Tabs(
        hypotheses,
        rrb.TextDocumentView(name="Run report", origin=REPORT, contents=[f"+ {REPORT}"]),
        rrb.TextDocumentView(name="Timing", origin=REPORT_TIMING),
    )
    middle: list = [report]
    if has_retrieval:
        middle.insert(0, rrb.Tabs(
            rrb.TextDocumentView(name="Retrieved frames", origin=RETRIEVAL_MATCHES),
            rrb.TimeSeriesView(name="Retrieval L2 distance by rank", origin=RETRIEVAL_DISTANCES,
                               plot_legend=rrb.PlotLegend(visible=False)),
            rrb.Spatial2DView(name="Query code", origin=RETRIEVAL_CODE),
        ))
    middle_shares = [4, 7] if has_retrieval else [1]
    axis = _full_range(frames)
    unit = ScalarAxis(range=(-0.02, 1.05), zoom_lock=True)
    metrics = rrb.Tabs(
        rrb.TimeSeriesView(name="Precision / recall", origin=METRICS, axis_x=axis, axis_y=unit,
                           contents=[f"+ {metric_path('precision')}", f"+ {metric_path('recall')}"]),
        rrb.TimeSeriesView(name="ATE [m]", origin=METRICS, axis_x=axis, contents=[f"+ {metric_path('ate_rmse_m')}"]),
        rrb.TimeSeriesView(name="Counts", origin=METRICS, axis_x=axis, contents=[
            f"+ {metric_path('constraints')}", f"+ {metric_path('accepted')}", f"+ {metric_path('hypotheses')}"]),
        rrb.TimeSeriesView(name="Gate χ² (declared noise units)", origin=METRICS, axis_x=axis,
                           contents=[f"+ {metric_path('gate_chi2')}"]),
        rrb.TimeSeriesView(name="Stage times [s]", origin=METRICS, axis_x=axis, contents=[f"+ {STAGE_TIMES}", f"+ {FRAME_TIME}"]),
    )
    events = rrb.TextLogView(
        name="Events (click a row to jump there)",
        origin=EVENTS,
        columns=TextLogColumns(
            timeline_columns=[TimelineColumn(FRAME_TIMELINE, visible=True), TimelineColumn(LOG_TIME_TIMELINE, visible=False),
                              TimelineColumn(WINDOW_TIMELINE, visible=False)],
            text_log_columns=[TextLogColumn("LogLevel", visible=True), TextLogColumn("Body", visible=True),
                              TextLogColumn("EntityPath", visible=False)],
        ),
    )
    right = rrb.Vertical(
        rrb.BarChartView(name=f"Hypotheses by rank: {rank_key_name(method)}", origin=HYPOTHESES_RANKS,
                         plot_legend=rrb.PlotLegend(visible=False)),
        rrb.Spatial2DView(name="Consistency: top hypotheses (rows) × deciding constraints (green true, red false)",
                          origin=HYPOTHESES_CONSISTENCY),
        metrics,
        events,
        row_shares=[2, 2, 2, 3],
    )
    return rrb.Blueprint(
        rrb.Horizontal(left, rrb.Vertical(*middle, row_shares=middle_shares), right, column_shares=[5, 3, 4]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline=FRAME_TIMELINE, play_state="following"),
    )
