"""TUM files as evo and the TUM tools read them: seconds with nanoseconds kept, translation, then the
quaternion in x y z w order (checked with plain numpy parsing, not with the project's own se3)."""

import numpy as np

from flextrack.formats.tum import write_tum


def test_tum_rows_hold_time_translation_and_an_xyzw_quaternion(tmp_path):
    half = np.radians(90.0) / 2
    about_z = np.eye(4)
    about_z[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90 deg about z
    about_z[:3, 3] = [0.1, -0.2, 1.5]
    path = tmp_path / "run_estimate.tum"
    write_tum(path, np.array([1_000_000_001, 12_345_678_901_234]), np.stack([np.eye(4), about_z]))
    text = path.read_text().splitlines()
    assert text[0] == "# timestamp tx ty tz qx qy qz qw"
    assert text[1].split()[0] == "1.000000001" and text[2].split()[0] == "12345.678901234"  # ns exact
    rows = np.loadtxt(path, comments="#")
    assert rows.shape == (2, 8)
    assert np.allclose(rows[0, 1:], [0, 0, 0, 0, 0, 0, 1])
    q = rows[1, 4:]
    assert np.allclose(rows[1, 1:4], [0.1, -0.2, 1.5])
    assert np.allclose(q * np.sign(q[3]), [0, 0, np.sin(half), np.cos(half)])  # x y z w, up to sign
