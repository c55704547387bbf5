"""Cross-match the star lists of several epochs.

Stars are matched by their ID when the catalogues share IDs (forced
photometry on a common input list), otherwise by position with a
:class:`scipy.spatial.cKDTree`, using the largest expected motion over the
baseline (plus a tolerance for the not-yet-fitted frame transformation) as the
search radius. Positional matches are refined once: a linear transformation is
fitted to the unambiguous first-pass matches, applied, and the match repeated.
Ambiguous matches (a second candidate within the radius, or two reference
stars claiming the same star) and unmatched stars are reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from mavispm.core.errors import InputError
from mavispm.measure.propermotions.alignment import TransformModel, normalisation_length

__all__ = [
    "EpochMatch",
    "ID_SHARE_FRACTION",
    "ids_are_shared",
    "match_by_id",
    "match_by_position",
    "match_epochs",
]

#: Fraction of the smaller catalogue's IDs that must be shared for ``auto`` to match by ID.
ID_SHARE_FRACTION = 0.5


@dataclass
class EpochMatch:
    """Cross-identification of stars over epochs.

    Parameters
    ----------
    index : ndarray of int, shape (n_stars, n_epochs)
        Row of each star in each epoch's table, -1 where it was not matched.
    ids : ndarray of int
        Star ID (from the first epoch where the star appears).
    ambiguous : ndarray of bool, shape (n_stars,)
        Matched by position with a competing candidate within the radius.
    n_unmatched : list of int
        Per epoch: rows of that epoch's table that were not matched to any star.
    method : str
        ``"id"`` or ``"position"``.
    notes : list of str
    """

    index: np.ndarray
    ids: np.ndarray
    ambiguous: np.ndarray
    n_unmatched: list[int]
    method: str
    notes: list[str] = field(default_factory=list)

    @property
    def n_epochs_present(self) -> np.ndarray:
        """Number of epochs in which each star was matched."""
        return np.count_nonzero(self.index >= 0, axis=1)


def ids_are_shared(ids_list: Sequence[np.ndarray]) -> bool:
    """Whether every epoch shares most IDs with the first (so matching by ID is sound).

    Parameters
    ----------
    ids_list : sequence of ndarray
        Star IDs of each epoch.

    Returns
    -------
    bool
    """
    first = np.asarray(ids_list[0])
    for ids in ids_list[1:]:
        common = np.intersect1d(first, np.asarray(ids)).size
        if common < ID_SHARE_FRACTION * min(first.size, np.size(ids)) or common == 0:
            return False
    return True


def match_by_id(ids_list: Sequence[np.ndarray]) -> EpochMatch:
    """Match stars by ID: one row per ID present in any epoch.

    Parameters
    ----------
    ids_list : list of ndarray of int
        IDs of each epoch's table (unique within an epoch).
    """
    all_ids = np.unique(np.concatenate([np.asarray(i) for i in ids_list]))
    index = np.full((all_ids.size, len(ids_list)), -1, dtype=np.int64)
    for k, ids in enumerate(ids_list):
        ids = np.asarray(ids)
        pos = np.searchsorted(all_ids, ids)
        index[pos, k] = np.arange(ids.size)
    present = np.count_nonzero(index >= 0, axis=1)
    n_unmatched = [
        int(np.count_nonzero(present[np.searchsorted(all_ids, i)] < 2)) for i in ids_list
    ]
    return EpochMatch(
        index=index,
        ids=all_ids,
        ambiguous=np.zeros(all_ids.size, bool),
        n_unmatched=n_unmatched,
        method="id",
    )


def _nearest_unique(tree: cKDTree, x, y, radius):
    """Nearest neighbour within ``radius`` for each query point; ambiguity flags."""
    n_tree = tree.n
    k = min(2, n_tree)
    dist, idx = tree.query(np.column_stack([x, y]), k=k, distance_upper_bound=radius)
    if k == 1:
        dist = dist[:, None]
        idx = idx[:, None]
    found = np.isfinite(dist[:, 0])
    nearest = np.where(found, idx[:, 0], -1)
    ambiguous = found & (np.isfinite(dist[:, 1]) if k == 2 else False)
    # two queries claiming the same target: keep neither as unique
    claimed = nearest[found]
    uniq, counts = np.unique(claimed, return_counts=True)
    dup = np.isin(nearest, uniq[counts > 1]) & found
    ambiguous = ambiguous | dup
    return nearest, ambiguous, dup


def match_by_position(
    xy_list: Sequence[tuple[np.ndarray, np.ndarray]], reference: int, radius: float
) -> EpochMatch:
    """Match each epoch to the reference epoch by position.

    Parameters
    ----------
    xy_list : list of (ndarray, ndarray)
        Positions [arcsec] of each epoch.
    reference : int
        Index of the reference epoch; only its stars can be matched.
    radius : float
        Search radius [arcsec]: largest expected motion over the baseline plus a
        tolerance for the frame transformation.

    Returns
    -------
    EpochMatch
        Stars in ``ids`` are the reference epoch's row numbers (the caller maps
        them to IDs).
    """
    xr, yr = (np.asarray(v, float) for v in xy_list[reference])
    n_ref = xr.size
    n_ep = len(xy_list)
    index = np.full((n_ref, n_ep), -1, dtype=np.int64)
    index[:, reference] = np.arange(n_ref)
    ambiguous = np.zeros(n_ref, bool)
    n_unmatched = [0] * n_ep
    model = TransformModel(order=1, length=normalisation_length(xr, yr))
    for k, (xk, yk) in enumerate(xy_list):
        if k == reference:
            continue
        xk = np.asarray(xk, float)
        yk = np.asarray(yk, float)
        if xk.size == 0 or n_ref == 0:
            n_unmatched[k] = xk.size
            continue
        tree = cKDTree(np.column_stack([xk, yk]))
        near, amb, dup = _nearest_unique(tree, xr, yr, radius)
        good = (near >= 0) & ~amb
        if np.count_nonzero(good) >= 6:
            # refine: fit a linear map reference -> epoch k, re-match in the mapped frame
            a = model.design(xr[good], yr[good])
            b = np.concatenate([xk[near[good]], yk[near[good]]])
            params, *_ = np.linalg.lstsq(a, b, rcond=None)
            mx, my = model.apply(params, xr, yr)
            near, amb, dup = _nearest_unique(tree, mx, my, radius)
        index[:, k] = np.where(dup, -1, near)
        ambiguous |= amb
        n_unmatched[k] = int(xk.size - np.count_nonzero(index[:, k] >= 0))
    n_unmatched[reference] = int(np.count_nonzero(np.count_nonzero(index >= 0, axis=1) < 2))
    return EpochMatch(
        index=index,
        ids=np.arange(n_ref),
        ambiguous=ambiguous,
        n_unmatched=n_unmatched,
        method="position",
    )


def match_epochs(
    ids_list: Sequence[np.ndarray],
    xy_list: Sequence[tuple[np.ndarray, np.ndarray]],
    reference: int,
    radius: float,
    method: str = "auto",
):
    """Match stars over epochs by ID or by position.

    Parameters
    ----------
    ids_list : list of ndarray of int
    xy_list : list of (ndarray, ndarray)
        Positions [arcsec].
    reference : int
        Index of the reference epoch.
    radius : float
        Positional search radius [arcsec].
    method : {"auto", "id", "position"}
        ``auto`` matches by ID when the epochs share most IDs, else by position.

    Returns
    -------
    EpochMatch

    Raises
    ------
    InputError
        When no star is common to the reference epoch and another epoch.
    """
    if method not in ("auto", "id", "position"):
        raise InputError(f"unknown match method {method!r}; expected auto, id or position")
    if method == "auto":
        method = "id" if ids_are_shared(ids_list) else "position"
    if method == "id":
        result = match_by_id(ids_list)
    else:
        result = match_by_position(xy_list, reference, radius)
        ref_ids = np.asarray(ids_list[reference])
        result.ids = ref_ids[result.ids] if ref_ids.size else result.ids
    present = result.index >= 0
    for k in range(len(ids_list)):
        if k == reference:
            continue
        common = np.count_nonzero(present[:, k] & present[:, reference])
        if common == 0:
            how = "ID" if method == "id" else f"position within {radius * 1e3:.1f} mas"
            raise InputError(
                f"no star of epoch #{k} matches the reference epoch #{reference} by {how}; "
                "are the catalogues from the same field?"
            )
    return result
