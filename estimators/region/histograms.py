"""Foreground / background colour histograms (RGB, `bins`^3 cells), learned online.

A pair is filled from pixels along the correspondence lines (inside the outline: foreground,
outside: background): the first `update` replaces, later ones blend in with a learning rate (SRT3D:
0.2). The estimator keeps one pair per session, learned at its answers' poses, and builds one per
frame from that frame's pixels, mixed with the session's (`mixed`). Pixels are handled as cells
(`index`: one int a pixel). A pixel's foreground posterior is h_f / (h_f + h_b), both histograms
normalised (equal priors).
"""

from __future__ import annotations

import numpy as np


class ColourHistograms:
    def __init__(self, bins: int = 32, learning_rate_f: float = 0.2, learning_rate_b: float = 0.2):
        if 256 % bins:
            raise ValueError(f"histogram bins per channel must divide 256, got {bins}")
        self.bins = bins
        self.shift = int(np.log2(256 // bins))
        self.learning_rate_f = learning_rate_f
        self.learning_rate_b = learning_rate_b
        self.fg = np.full(bins**3, 1.0 / bins**3)
        self.bg = np.full(bins**3, 1.0 / bins**3)
        self.initialised = False

    def index(self, colours: np.ndarray) -> np.ndarray:
        """Cell of each (..., 3) uint8 RGB colour."""
        c = colours >> self.shift  # still uint8: one pass over the pixels a step, in place from here on
        cells = c[..., 0].astype(np.int32)
        cells *= self.bins
        cells += c[..., 1]
        cells *= self.bins
        cells += c[..., 2]
        return cells

    def _normalised(self, cells: np.ndarray) -> np.ndarray:
        cells = cells.ravel()
        return np.bincount(cells, minlength=self.bins**3) / max(len(cells), 1)  # the counts' sum is the cells

    def update(self, fg_cells: np.ndarray, bg_cells: np.ndarray) -> None:
        """Blend in the pixels seen inside (fg) and outside (bg), as cells (`index`); the first call replaces."""
        if len(fg_cells) == 0 or len(bg_cells) == 0:
            return
        new_fg, new_bg = self._normalised(fg_cells), self._normalised(bg_cells)
        if not self.initialised:
            self.fg, self.bg, self.initialised = new_fg, new_bg, True
            return
        self.fg = (1 - self.learning_rate_f) * self.fg + self.learning_rate_f * new_fg
        self.bg = (1 - self.learning_rate_b) * self.bg + self.learning_rate_b * new_bg

    def mixed(self, other: ColourHistograms, weight: float) -> ColourHistograms:
        """A new pair: (1 - weight) of these and `weight` of the other's (both initialised)."""
        return self._like((1 - weight) * self.fg + weight * other.fg, (1 - weight) * self.bg + weight * other.bg)

    def unmixed(self, share: float) -> ColourHistograms:
        """A new pair with `share` of each histogram's samples taken to have come from the other side (samples
        labelled by an outline that is off): observed fg = (1 - s) F + s B and bg = (1 - s) B + s F, solved for
        F and B, negatives clipped."""
        if share <= 0 or not self.initialised:
            out = self._like(self.fg.copy(), self.bg.copy())
            out.initialised = self.initialised
            return out
        det = 1.0 - 2.0 * share  # (1 - s)^2 - s^2
        fg = np.maximum(((1 - share) * self.fg - share * self.bg) / det, 0.0)
        bg = np.maximum(((1 - share) * self.bg - share * self.fg) / det, 0.0)
        return self._like(fg / max(fg.sum(), 1e-12), bg / max(bg.sum(), 1e-12))

    def _like(self, fg: np.ndarray, bg: np.ndarray) -> ColourHistograms:
        """A new, initialised pair with these settings and these histograms (no uniform ones made first)."""
        out = object.__new__(ColourHistograms)
        out.__dict__.update(self.__dict__)
        out.fg, out.bg, out.initialised = fg, bg, True
        return out

    def logits(self, clip: float) -> np.ndarray:
        """log(p / (1 - p)) of every cell's foreground posterior p kept in [clip, 1 - clip] (a histogram's empty
        cell is not certainty): one table lookup a pixel instead of a division and two logs."""
        p = np.clip(self._posteriors(), clip, 1 - clip)
        return np.log(p) - np.log1p(-p)

    def posterior(self, cells: np.ndarray) -> np.ndarray:
        """P(foreground | colour) for each cell index, in (0, 1)."""
        if np.size(cells) > self.bins**3:  # many pixels: every cell's posterior once, then one lookup a pixel
            return self._posteriors().take(cells)
        return _posterior(self.fg[cells], self.bg[cells])

    def scores(self, cells: np.ndarray) -> np.ndarray:
        """2 P(foreground | colour) - 1 for each cell index, float32 (the coarse search's evidence)."""
        return (2 * self._posteriors() - 1).astype(np.float32).take(cells)

    def _posteriors(self) -> np.ndarray:
        """Every cell's posterior, by cell index."""
        return _posterior(self.fg, self.bg)


def _posterior(fg: np.ndarray, bg: np.ndarray) -> np.ndarray:
    """P(foreground | colour) from the two histograms' values at the colour's cells, in (0, 1)."""
    return (fg + 1e-9) / (fg + bg + 2e-9)
