"""`flextrack bench tracker --accuracy` measures the paper's core, whose options (integrator, gains,
BSCM) it compares: with the filter (the default tracker) the integrators would read the same."""

from flextrack.benchmarks.tracker_bench import integrator_comparison


def test_the_integrator_table_is_the_paper_cores_and_tells_the_integrators_apart():
    rows = {name: (imu_only, gt) for name, imu_only, gt in integrator_comparison()}
    assert set(rows) == {"paper", "midpoint"}
    paper_px, midpoint_px = rows["paper"][0][2], rows["midpoint"][0][2]
    assert midpoint_px < 0.1 * paper_px  # second order against the paper's first-order integrator, IMU only
    assert rows["midpoint"][1][0] < rows["paper"][1][0]  # and with a GT backend
