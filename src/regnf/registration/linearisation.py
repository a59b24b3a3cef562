"""The refinement's residuals and their Jacobians at the current poses, what each
Levenberg-Marquardt iteration solves with (:mod:`regnf.registration.refinement`)."""

from __future__ import annotations

from typing import NamedTuple

import torch


class Linearisation(NamedTuple):
    """The active hypotheses' residuals at their current pose and the residuals' Jacobians in
    the local update ``(dw, dl, dtau, d delta)`` (rotation, log scale, translation, offset).

    Rows of the SDF terms are grouped by hypothesis (``group``, active index); residuals are
    in reference lengths, signed."""

    x: torch.Tensor
    """(n,) float64 SDF residuals (A rows, then B rows)."""
    J: torch.Tensor
    """(n, 8) float64 d x / d (dw, dl, dtau, d delta)."""
    a: torch.Tensor
    """(n,) float64 weight of each residual in its hypothesis's objective (the visibility over
    the weighted count of its set: each set contributes a weighted mean)."""
    group: torch.Tensor
    """(n,) long."""
    q: torch.Tensor
    """(m, 3) float64 regulariser vectors: kept mapped scene samples minus their nearest library
    sample, reference lengths."""
    Jq: torch.Tensor
    """(m, 3, 8) float64 their Jacobians."""
    aq: torch.Tensor
    """(m,) float64 regulariser weight of each vector (w over the kept count)."""
    gq: torch.Tensor
    """(m,) long hypothesis of each vector."""
    stats: torch.Tensor
    """(k, 7) as :meth:`~regnf.registration.refine_batch.HypothesisBatch.evaluate`."""

    def merge(self, other: Linearisation, take: torch.Tensor) -> Linearisation:
        """Rows of ``other`` for the hypotheses where ``take`` (k,) is true, else these rows (the
        two must share their sample sets)."""
        rows, reg = take[self.group], take[self.gq]
        return Linearisation(
            torch.where(rows, other.x, self.x), torch.where(rows[:, None], other.J, self.J),
            torch.where(rows, other.a, self.a), self.group,
            torch.where(reg[:, None], other.q, self.q), torch.where(reg[:, None, None], other.Jq, self.Jq),
            torch.where(reg, other.aq, self.aq), self.gq, torch.where(take[:, None], other.stats, self.stats))

    def select(self, keep: torch.Tensor) -> Linearisation:
        """Only the hypotheses where ``keep`` (k,) is true, renumbered in order."""
        new_id = torch.cumsum(keep.long(), 0) - 1
        rows, reg = keep[self.group], keep[self.gq]
        return Linearisation(self.x[rows], self.J[rows], self.a[rows], new_id[self.group[rows]], self.q[reg],
                       self.Jq[reg], self.aq[reg], new_id[self.gq[reg]], self.stats[keep])
