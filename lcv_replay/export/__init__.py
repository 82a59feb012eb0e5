"""Results that leave the tool: ``--export DIR`` (evo's TUM and KITTI trajectories, ``loops.csv``,
``accepted.g2o``, ``config.toml``, ``summary.json``).

* :mod:`~lcv_replay.export.formats`: pure functions from a run's arrays and records to file text;
* :mod:`~lcv_replay.export.sink`: the export sink, which writes them atomically at the end of a
  replay from the :class:`~lcv_replay.sinks.run_record.RunRecord`.
"""
