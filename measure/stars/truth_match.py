"""Cross-match measured stars to the truth list (scipy cKDTree, distance cut)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "match_to_truth",
]


def match_to_truth(
    x: np.ndarray, y: np.ndarray, x_true: np.ndarray, y_true: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-neighbour match within ``radius``.

    Pairs are accepted closest first, so each truth star is used at most once.

    Parameters
    ----------
    x, y : ndarray, shape (N,)
        Measured positions [pixel] (non-finite entries never match).
    x_true, y_true : ndarray, shape (M,)
        Truth positions [pixel].
    radius : float
        Largest match distance [pixel].

    Returns
    -------
    index : ndarray of int, shape (N,)
        Index into the truth list, -1 where unmatched.
    distance : ndarray, shape (N,)
        Match distance [pixel], NaN where unmatched.
    """
    x, y = np.atleast_1d(np.asarray(x, float)), np.atleast_1d(np.asarray(y, float))
    n = len(x)
    index = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.nan)
    good = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    if len(good) == 0 or len(x_true) == 0:
        return index, dist
    tree = cKDTree(np.column_stack([x_true, y_true]))
    k = min(4, len(x_true))
    d, j = tree.query(np.column_stack([x[good], y[good]]), k=k, distance_upper_bound=radius)
    d, j = d.reshape(len(good), k), j.reshape(len(good), k)
    cand = np.isfinite(d)
    rows = np.repeat(good[:, None], k, axis=1)[cand]
    order = np.argsort(d[cand], kind="stable")
    taken_true = np.zeros(len(x_true), bool)
    for r, t, dd in zip(rows[order], j[cand][order], d[cand][order]):
        if index[r] < 0 and not taken_true[t]:
            index[r] = t
            dist[r] = dd
            taken_true[t] = True
    return index, dist
