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
CONSTRAINTS_SEGMENTS = "/constraints/segments"
CONSTRAINTS_PENDING = "/constraints/pending"
HYPOTHESES_TRAJECTORIES = "/hypotheses/trajectories"
HYPOTHESES_RANKS = "/hypotheses/ranks"
HYPOTHESES_CONSISTENCY = "/hypotheses/consistency"
HYPOTHESES_TREE = "/hypotheses/tree"
HYPOTHESES_SEQUENCES = "/hypotheses/sequences"
TRAJ_ODOMETRY = "/trajectories/odometry"
TRAJ_GROUND_TRUTH = "/trajectories/ground_truth"
TRAJ_BEST = "/trajectories/best"
TRAJ_CURRENT = "/trajectories/current"
METRICS = "/metrics"
EVENTS = "/events"
REPORT = "/report"
REPORT_TIMING = "/report/timing"
STAGE_TIMES = "/metrics/stage_time_s"
FRAME_TIME = "/metrics/frame_time_s"

#: The only entities that hold wall-clock measurements; everything else in a recording is a
#: deterministic function of the log, the config and the seed.
WALL_CLOCK_ENTITIES = (FRAME_TIME, STAGE_TIMES, REPORT_TIMING)

#: Roots of the entities drawn on the map; each gets a static y-flip so the 2-D map is y-up.
MAP_ROOTS = ("/trajectories", "/constraints", "/hypotheses", "/retrieval")

FRAME_TIMELINE = "frame"
LOG_TIME_TIMELINE = "log_time"
WINDOW_TIMELINE = "window"


def metric_path(name: str) -> str:
    """``/metrics/<name>``."""
    return f"{METRICS}/{name}"


def default_blueprint(*, has_images: bool, has_retrieval: bool):
    """The default layout: map | camera + retrieval | hypotheses, metrics and events.

    Returns a ``rerun.blueprint.Blueprint`` (rerun is imported here, not at module import).
    """
    import rerun.blueprint as rrb

    map_view = rrb.Spatial2DView(
        name="Map (rank-1 hypothesis)",
        origin="/",
        contents=[
            f"+ {TRAJ_GROUND_TRUTH}",
            f"+ {TRAJ_ODOMETRY}",
            f"+ {HYPOTHESES_TRAJECTORIES}",
            f"+ {TRAJ_BEST}",
            f"+ {TRAJ_CURRENT}",
            f"+ {CONSTRAINTS_SEGMENTS}",
            f"+ {CONSTRAINTS_PENDING}",
            f"+ {RETRIEVAL_LINES}",
        ],
    )
    middle: list = []
    if has_images:
        middle.append(rrb.Spatial2DView(name="Camera (left)", origin=CAMERA_LEFT))
    if has_retrieval:
        middle.append(
            rrb.Vertical(
                rrb.Spatial2DView(name="Query code", origin=RETRIEVAL_CODE),
                rrb.TimeSeriesView(name="Retrieval L2 distance by rank", origin=RETRIEVAL_DISTANCES),
                rrb.TextDocumentView(name="Retrieved frames", origin=RETRIEVAL_MATCHES),
                row_shares=[1, 2, 3],
            )
        )
    middle.append(
        rrb.Tabs(
            rrb.TextDocumentView(name="Top hypotheses", origin=HYPOTHESES_SEQUENCES),
            rrb.GraphView(name="Generation tree", origin=HYPOTHESES_TREE),
            rrb.TextDocumentView(name="Run report", origin=REPORT, contents=[f"+ {REPORT}"]),
            rrb.TextDocumentView(name="Timing", origin=REPORT_TIMING),
        )
    )
    right = rrb.Vertical(
        rrb.BarChartView(name="Hypotheses by rank (ranking key)", origin=HYPOTHESES_RANKS),
        rrb.TensorView(name="Consistency (hypothesis × constraint)", origin=HYPOTHESES_CONSISTENCY),
        rrb.Tabs(
            rrb.TimeSeriesView(
                name="Precision / recall",
                origin=METRICS,
                contents=[f"+ {metric_path('precision')}", f"+ {metric_path('recall')}"],
            ),
            rrb.TimeSeriesView(name="ATE [m]", origin=METRICS, contents=[f"+ {metric_path('ate_rmse_m')}"]),
            rrb.TimeSeriesView(
                name="Counts",
                origin=METRICS,
                contents=[
                    f"+ {metric_path('constraints')}",
                    f"+ {metric_path('accepted')}",
                    f"+ {metric_path('hypotheses')}",
                ],
            ),
            rrb.TimeSeriesView(name="Gate χ² (declared noise units)", origin=METRICS, contents=[f"+ {metric_path('gate_chi2')}"]),
            rrb.TimeSeriesView(
                name="Stage times [s]",
                origin=METRICS,
                contents=[f"+ {STAGE_TIMES}", f"+ {FRAME_TIME}"],
            ),
        ),
        rrb.TextLogView(name="Events", origin=EVENTS),
        row_shares=[2, 2, 2, 2],
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            map_view,
            rrb.Vertical(*middle),
            right,
            column_shares=[5, 3, 4],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=FRAME_TIMELINE),
    )
