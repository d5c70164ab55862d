"""The paper's reported figures that our experiments stand beside (Lau et al., Tables 2 and 4, Section 4)."""

from __future__ import annotations

MOTIONS = ("translational", "circular")
LEVELS = ("easy", "medium", "hard")
FPS = (30, 60, 90, 120)
BACKENDS = ("gt", "noisy")

# Table 2: (backend, fps) -> {(motion, level): (position mm, orientation deg, 2D projection px)}
_TABLE2_ROWS = {
    ("gt", 30): "1.17/0.00/0.20 2.29/0.00/0.45 3.39/0.01/0.69 0.21/0.02/0.10 0.50/0.03/0.17 1.02/0.06/0.32",
    ("gt", 60): "1.05/0.00/0.18 2.07/0.00/0.41 3.13/0.01/0.64 0.19/0.02/0.08 0.49/0.03/0.15 0.90/0.05/0.25",
    ("gt", 90): "1.04/0.00/0.18 2.02/0.00/0.40 2.99/0.01/0.60 0.21/0.02/0.09 0.51/0.03/0.18 0.94/0.05/0.29",
    ("gt", 120): "1.02/0.00/0.18 1.97/0.00/0.39 2.93/0.01/0.59 0.22/0.02/0.10 0.53/0.04/0.19 0.98/0.06/0.32",
    ("noisy", 30): "4.89/0.47/1.96 5.16/0.48/2.10 5.78/0.47/2.15 4.68/0.48/2.00 4.73/0.47/2.00 4.80/0.48/2.01",
    ("noisy", 60): "5.16/0.50/2.09 5.39/0.50/2.15 5.86/0.50/2.28 5.03/0.50/2.09 5.04/0.51/2.14 5.12/0.51/2.10",
    ("noisy", 90): "5.24/0.52/2.15 5.53/0.51/2.22 5.92/0.52/2.31 5.13/0.51/2.17 5.12/0.51/2.14 5.21/0.52/2.16",
    ("noisy", 120): "5.26/0.51/2.14 5.52/0.52/2.25 5.98/0.52/2.33 5.16/0.52/2.19 5.27/0.52/2.16 5.26/0.53/2.21",
}
TABLE2: dict[tuple[str, str, int, str], tuple[float, float, float]] = {
    (motion, level, fps, backend): tuple(float(v) for v in cell.split("/"))
    for (backend, fps), row in _TABLE2_ROWS.items()
    for (motion, level), cell in zip([(m, lv) for m in MOTIONS for lv in LEVELS], row.split())
}

# Table 4 (real data, five 30 s sequences): position mm, orientation deg, 2D projection px.
TABLE4 = {"#1": (1.65, 1.54, 2.56), "#2": (2.06, 6.96, 2.93), "#3": (2.01, 8.17, 3.37), "#4": (1.25, 8.23, 2.21),
          "#5": (1.30, 3.91, 2.30)}

# Section 4.1.4: frontend timing after the 2.46 stretch, ms.
TIMING_MS = {"pim": 0.35, "prm": 0.86}

EUROC_FPS = 52.0  # the frame rate of the paper's real sequences (Table 4), which `experiment euroc` uses by default
