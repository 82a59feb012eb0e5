"""Sinks: everything a replay produces goes through one :class:`~lcv_replay.sinks.base.Sink` protocol.

* :mod:`~lcv_replay.sinks.rerun_sink`: the Rerun recording (file, spawned/connected viewer, served
  web viewer), laid out by :mod:`~lcv_replay.sinks.blueprint` from :mod:`~lcv_replay.sinks.layout`;
* :mod:`~lcv_replay.sinks.summary`: the printed summary and ``--summary-json``;
* :mod:`~lcv_replay.sinks.progress`: the progress bar;
* :mod:`~lcv_replay.sinks.null`: nothing at all.

Importing this package imports none of them (rerun and rich load only when a sink is built).
"""
