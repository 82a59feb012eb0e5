"""Benchmarks that print a table and write JSON.

* :mod:`~lcv_replay.bench.verify`: one log × one verification method (``bench verify``), and the
  reusable :func:`~lcv_replay.bench.verify.run_verification`.
* :mod:`~lcv_replay.bench.suites`: named suites of cases (built-in and TOML files).
* :mod:`~lcv_replay.bench.suite`: building the suite's logs and running methods side by side
  (``bench suite``).
"""
