"""Fleet runs on Ray: ``lcv-replay batch``, ``lcv-replay compare`` and ``bench suite --workers``.

Each log is one Ray task that calls the public :func:`lcv_replay.replay.replay` (the function behind
``lcv-replay LOG.mcap``) with ``rate = max``; the task is a thin wrapper that only chooses the
output paths, caps the threads and turns errors into data.

* :mod:`~lcv_replay.fleet.inputs`: LOGS (files, folders, globs) to a list of logs with unique names;
  the log hash.
* :mod:`~lcv_replay.fleet.engine`: the Ray cluster (embedded local one, or ``--address``) and the
  scheduling loop shared by batch and the suite (bounded in-flight tasks, Ctrl-C, worker deaths).
* :mod:`~lcv_replay.fleet.task`: one log's replay (the Ray task body) and its outcome.
* :mod:`~lcv_replay.fleet.oracle`: the oracle's ATE on the same constraints (the ATE reference).
* :mod:`~lcv_replay.fleet.batch`: planning (resume by config hash and log hash), running, ``run.json``.
* :mod:`~lcv_replay.fleet.table`: per-log figures, worst first, aggregates; ``fleet.md``,
  ``fleet.html``, ``fleet.csv``, ``fleet.parquet``.
* :mod:`~lcv_replay.fleet.compare`: two runs (or two bench JSONs) joined by log.
* :mod:`~lcv_replay.fleet.plots`: the matplotlib figures of the fleet and compare pages.
* :mod:`~lcv_replay.fleet.simulate`: the wall-time model of a corpus on N workers (docs/fleet.md).
* :mod:`~lcv_replay.fleet.bench`: ``lcv-replay bench fleet`` (scaling, Ray overheads, simulation).

Importing this package imports neither Ray nor the replay.
"""
