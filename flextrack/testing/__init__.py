"""Fixtures that the tests and the benchmarks share: small, generated worlds with known answers.

`toy_sequence`: a tiny sequence folder (a box, the camera circling it) for oracle tests, the service
benchmarks and the container check.
"""
