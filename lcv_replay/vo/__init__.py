"""Stereo visual odometry for logs with stereo images but no odometry.

* :mod:`lcv_replay.vo.stereo_vo`: the core on OpenCV (FAST + bucketing, LK stereo along rectified
  rows, triangulation, LK temporal tracking, PnP + RANSAC, LM refinement), pure functions plus the
  stateful :class:`~lcv_replay.vo.stereo_vo.StereoVoTracker`.
* :mod:`lcv_replay.vo.config`: :class:`~lcv_replay.vo.config.VoConfig` (the ``[vo]`` config table).
* :mod:`lcv_replay.vo.drift`: the KITTI odometry drift metric on planar trajectories.
* :mod:`lcv_replay.vo.log_vo`: the log edge (``lcv-replay vo``, the recorders' ``--vo`` hook).

Submodules are imported explicitly (they load OpenCV); this package imports nothing.
"""
