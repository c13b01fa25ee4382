"""Least squares for [A B] that never forms W W^T: streamed QR (TSQR) with an optional ridge.

The paper writes the EDMD solution as V W^T (W W^T)^+ (its eqs. for [A B] and C). Forming
W W^T squares the condition number of the data matrix; with radial-basis observables it easily
exceeds 1e12 and the pseudo-inverse then returns noise. Here the rows of [W | Y] are reduced by
QR chunk by chunk (memory stays O(d^2) however long the data), and the small triangular system
R11 Theta = R12 is solved by an SVD-based least squares, which gives the same minimum-norm
solution as ``np.linalg.lstsq`` on the full data.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from harness.core.checks import is_number, non_negative, require


def ridge_lstsq(chunks: Iterable[tuple[np.ndarray, np.ndarray]], ridge: float = 0.0) -> np.ndarray:
    """Theta minimizing (1/M) sum ||y_k - Theta^T w_k||^2 + ridge ||Theta||_F^2.

    Args:
        chunks: (W, Y) row blocks, W (k, d) regressors and Y (k, q) targets; M rows in all.
        ridge: Tikhonov weight, relative to the mean squared residual (so its meaning does not
            change with the amount of data).

    Returns:
        Theta (d, q), float64.
    """
    return Triangle.of(chunks).solve(ridge)


class Triangle:
    """The R of the QR of [W | Y], reduced once: every ridge is then one small solve."""

    def __init__(self, r: np.ndarray, count: int, regressors: int) -> None:
        self.r, self.count, self.regressors = r, count, regressors

    @classmethod
    def of(cls, chunks: Iterable[tuple[np.ndarray, np.ndarray]]) -> Triangle:
        """Reduce the (W, Y) row blocks, W (k, d) and Y (k, q), chunk by chunk."""
        r: np.ndarray | None = None
        count = d = 0
        for w, y in chunks:
            w = np.asarray(w, dtype=np.float64)
            y = np.asarray(y, dtype=np.float64)
            d = w.shape[1]
            block = np.hstack([w, y])
            count += len(block)
            r = np.linalg.qr(block if r is None else np.vstack([r, block]), mode="r")
        if r is None or count == 0:
            raise ValueError("least squares on zero samples")
        return cls(r, count, d)

    def column_rms(self) -> np.ndarray:
        """RMS over the samples of each regressor column (W^T W = R^T R: no pass over the data)."""
        w = self.r[:, : self.regressors]
        return np.sqrt(np.sum(w * w, axis=0) / self.count)

    def scaled(self, scale: np.ndarray) -> Triangle:
        """The triangle of [W / scale | Y]: R's regressor columns divided (still triangular)."""
        r = self.r.copy()
        r[:, : self.regressors] /= scale
        return Triangle(r, self.count, self.regressors)

    def solve(self, ridge: float = 0.0) -> np.ndarray:
        """Theta (d, q) of :func:`ridge_lstsq` for this ``ridge``."""
        r, d = self.r, self.regressors
        q = r.shape[1] - d
        if ridge > 0:
            penalty = np.hstack([np.sqrt(ridge * self.count) * np.eye(d), np.zeros((d, q))])
            r = np.linalg.qr(np.vstack([r, penalty]), mode="r")
        if r.shape[0] < d + q:  # fewer samples than unknowns: pad R with zero rows
            r = np.vstack([r, np.zeros((d + q - r.shape[0], d + q))])
        theta, *_ = np.linalg.lstsq(r[:d, :d], r[:d, d:], rcond=None)
        return theta


def row_chunks(a: np.ndarray, size: int) -> Iterable[slice]:
    """Slices cutting ``len(a)`` rows into blocks of at most ``size``."""
    return (slice(i, min(i + size, len(a))) for i in range(0, len(a), size))


def ridge_weights(ridge: Any) -> list[float]:
    """``learner.ridge`` as a list: one number or a non-empty list of numbers, each >= 0. A
    string is neither, even ``'1e-4'`` (a quoted override): iterated, it is its characters."""
    wanted = "a number >= 0 or a non-empty list of them"
    values = [ridge] if is_number(ridge) else ridge
    if isinstance(values, str | bytes) or not isinstance(values, Sequence) or not values:
        require(False, "learner.ridge", wanted, ridge)
    for value in values:
        require(is_number(value), "learner.ridge", wanted, ridge)
    return [non_negative("learner.ridge", value) for value in values]
