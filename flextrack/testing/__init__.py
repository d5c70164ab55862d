"""Fixtures that the tests and the benchmarks share: small, generated worlds with known answers.

- `toy_sequence`: a tiny sequence folder (a box, the camera circling it) for oracle tests, the service
  benchmarks and the container check;
- `tracker_world`: an analytic world (a body circling a box, exact IMU and frames) that drives the
  tracker core, for its tests and the tracker benchmark.
"""
