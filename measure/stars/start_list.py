"""Observer-mode start list: earlier epochs' measured positions moved into a new frame.

An observer measuring a later epoch has the first epoch's input list (or its
detections) and what the earlier epochs measured, never the true positions at
the new epoch. This module builds the later epoch's start list from the
earlier ``measured`` products alone:

1. the bright, unflagged, isolated stars of an earlier epoch are the
   reference stars;
2. the common offset of the new frame is the peak of the histogram of
   offsets between the reference stars and the brightest peaks of the new
   frame (a cross-correlation of two point lists);
3. each reference star is centroided in the new frame at its predicted
   position, and an affine transform (earlier epoch -> new frame, pixels) is
   fitted to the centroids with sigma clipping;
4. every star of the earlier epoch is moved into the new frame with that
   transform; where several earlier epochs are given, each star takes its
   position from the latest epoch that measured it.

The fitter then refines every position (stars move by their proper motion
times the baseline, well inside its ``max_shift``). No truth is read here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import astropy.units as u
import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from mavispm.core.errors import InputError
from mavispm.core.frame import on_detector
from mavispm.core.products import TableSpec, read_product
from mavispm.measure.stars.epsf_anchor import epsf_from_product
from mavispm.measure.stars.node_centring import NodeCentring, centring_from_summary
from mavispm.measure.stars.variable_psf import VariableEPSF

__all__ = [
    "EarlierEpoch",
    "EpochTransform",
    "PREVIOUS_SPEC",
    "TransferOptions",
    "bright_peaks",
    "centroids",
    "fit_epoch_transform",
    "histogram_offset",
    "read_earlier",
    "reference_stars",
    "start_from_earlier",
]

#: Columns of an earlier ``measured`` product that the start list needs.
PREVIOUS_SPEC = TableSpec(
    required={"id": "", "x_pix": "", "y_pix": "", "flux": "electron", "flag": ""},
    allow_nan=("flux",),
)

#: Measure-stage flags that disqualify a star as a reference star (all but crowded, 8).
_BAD_REFERENCE = 1 | 2 | 4 | 16 | 32


@dataclass
class EarlierEpoch:
    """One earlier epoch's measured stars, in that epoch's pixel frame.

    Parameters
    ----------
    epoch : float
        [yr]
    ids : ndarray of int
    x, y : ndarray
        Measured positions [pixel].
    flux : ndarray
        Measured flux [electron] (NaN where the fit failed).
    flag : ndarray of int
        The measure stage's flags.
    path : Path or None
    ids_true : ndarray of int or None
        The product's ``id_true`` column (truth ids for scoring; None where absent).
    psf : VariableEPSF or None
        That epoch's ePSF (the ``epsf_basis`` array and ``epsf`` attribute of its
        product), the centre convention a later epoch's ePSF is anchored to.
    centring : NodeCentring or None
        The error of that ePSF's node centring (its ``epsf_centring`` attribute's
        covariance, :func:`~mavispm.measure.stars.node_centring.centring_from_summary`),
        which a later epoch centred on it inherits; None: not known.
    """

    epoch: float
    ids: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    flag: np.ndarray
    path: Path | None = None
    psf: VariableEPSF | None = None
    ids_true: np.ndarray | None = None
    centring: NodeCentring | None = None


def read_earlier(path) -> EarlierEpoch:
    """Read an earlier epoch's ``measured`` product.

    Parameters
    ----------
    path : str or os.PathLike
        The earlier epoch's ``measured`` product.

    Returns
    -------
    EarlierEpoch
        Its measured positions [pixel], fluxes, flags and epoch.

    Raises
    ------
    InputError
        Not a measured product, missing columns or the ``epoch`` attribute.
    """
    path = Path(path)
    prod = read_product(path, "measured", specs={"stars": PREVIOUS_SPEC})
    stars = prod.tables["stars"]
    if "epoch" not in prod.attrs:
        raise InputError("root attribute 'epoch' [yr] missing", path=path)
    epoch = float(u.Quantity(prod.attrs["epoch"], u.yr).value)
    x = np.asarray(stars["x_pix"], float)
    y = np.asarray(stars["y_pix"], float)
    keep = np.isfinite(x) & np.isfinite(y)
    flux = stars["flux"].to_value(u.electron)
    psf = None
    if "epsf_basis" in prod.arrays and "epsf" in prod.attrs:
        try:
            psf = epsf_from_product(prod.arrays["epsf_basis"], prod.attrs["epsf"])
        except (InputError, KeyError, ValueError, TypeError) as exc:
            raise InputError(f"array 'epsf_basis' / attribute 'epsf': {exc}", path=path) from None
    ids_true = np.asarray(stars["id_true"], np.int64)[keep] if "id_true" in stars.colnames else None
    try:
        centring = centring_from_summary(prod.attrs.get("epsf_centring"))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"attribute 'epsf_centring': {exc}", path=path) from None
    if centring is not None and (psf is None or centring.cov.shape[0] != psf.n_basis):
        raise InputError(
            "attribute 'epsf_centring': its covariance does not fit the product's ePSF",
            path=path,
        )
    return EarlierEpoch(
        psf=psf,
        centring=centring,
        ids_true=ids_true,
        epoch=epoch,
        ids=np.asarray(stars["id"], np.int64)[keep],
        x=x[keep],
        y=y[keep],
        flux=np.asarray(flux, float)[keep],
        flag=np.asarray(stars["flag"], np.int64)[keep],
        path=path,
    )


@dataclass(frozen=True)
class TransferOptions:
    """Knobs of the epoch-to-epoch transform.

    Parameters
    ----------
    n_reference : int
        Brightest isolated stars of the earlier epoch used as reference stars.
    isolation : float
        No brighter star within this distance [pixel] of a reference star.
    search : float
        Largest common offset between the frames [pixel].
    centroid_half : int
        Half-width of the centroid box [pixel].
    clip : float
        Sigma-clipping threshold of the affine fit (robust sigma).
    """

    n_reference: int = 300
    isolation: float = 8.0
    search: float = 20.0
    centroid_half: int = 2
    clip: float = 4.0


@dataclass
class EpochTransform:
    """Affine map from an earlier epoch's pixels to the new frame's pixels.

    ``x' = a[0] + a[1] x + a[2] y``, ``y' = b[0] + b[1] x + b[2] y``.

    Parameters
    ----------
    a, b : ndarray, shape (3,)
    n_used : int
        Reference stars kept by the clipped fit.
    rms : float
        Robust scatter of the fit residuals [pixel] (centroid noise plus the
        stars' own motions).
    offset : tuple of float
        The histogram (cross-correlation) offset [pixel] that seeded the fit.
    """

    a: np.ndarray
    b: np.ndarray
    n_used: int
    rms: float
    offset: tuple[float, float]

    def apply(self, x, y):
        """Positions [pixel] in the new frame.

        Parameters
        ----------
        x, y : array_like
            Positions in the earlier epoch's frame [pixel].

        Returns
        -------
        tuple of ndarray
            ``x', y'`` [pixel].
        """
        x, y = np.asarray(x, float), np.asarray(y, float)
        return self.a[0] + self.a[1] * x + self.a[2] * y, self.b[0] + self.b[1] * x + self.b[2] * y

    def to_dict(self) -> dict:
        """JSON-ready description."""
        return {
            "a": [float(v) for v in self.a],
            "b": [float(v) for v in self.b],
            "n_used": int(self.n_used),
            "rms_pix": float(self.rms),
            "offset_pix": [float(v) for v in self.offset],
        }


def reference_stars(earlier: EarlierEpoch, options: TransferOptions) -> np.ndarray:
    """Indices of the brightest unflagged stars with no brighter star within ``isolation``.

    Parameters
    ----------
    earlier : EarlierEpoch
        The earlier epoch's measurements.
    options : TransferOptions
        ``isolation`` [pixel] and the number wanted, ``n_reference``.

    Returns
    -------
    ndarray of int
        Indices into ``earlier``, brightest first.
    """
    flux = np.nan_to_num(earlier.flux, nan=0.0)
    ok = ((earlier.flag & _BAD_REFERENCE) == 0) & (flux > 0)
    order = np.argsort(-flux)
    order = order[ok[order]]
    if len(order) == 0:
        return order
    tree = cKDTree(np.column_stack([earlier.x, earlier.y]))
    chosen = []
    for i in order:
        near = tree.query_ball_point([earlier.x[i], earlier.y[i]], options.isolation)
        if all(flux[j] <= flux[i] or j == i for j in near):
            chosen.append(i)
            if len(chosen) >= options.n_reference:
                break
    return np.asarray(chosen, np.intp)


def bright_peaks(image: np.ndarray, sky: float, bad: np.ndarray, n: int):
    """Positions [pixel] of the ``n`` highest local maxima (3 x 3) of a frame.

    Parameters
    ----------
    image : ndarray
        The frame [electron].
    sky : float
        Sky level subtracted first [electron/pixel].
    bad : ndarray of bool
        Pixels that cannot be a peak.
    n : int
        Number of peaks.

    Returns
    -------
    x, y : ndarray
        Integer pixel positions as floats, highest first.
    """
    data = np.where(bad, -np.inf, np.asarray(image, float) - sky)
    data = np.where(np.isfinite(data), data, -np.inf)
    is_max = (data == ndimage.maximum_filter(data, size=3, mode="nearest")) & (data > 0)
    ys, xs = np.nonzero(is_max)
    values = data[ys, xs]
    top = np.argsort(-values)[:n]
    return xs[top].astype(float), ys[top].astype(float)


def histogram_offset(x_ref, y_ref, x_new, y_new, search: float) -> tuple[float, float, int]:
    """Common offset [pixel] between two point lists: the peak of the histogram of
    pairwise differences within ``search`` (1-pixel bins summed 3 x 3, refined by the
    median, then the mean, of the differences within 1 and 0.5 pixel of the peak).

    Parameters
    ----------
    x_ref, y_ref : ndarray
        Reference positions [pixel].
    x_new, y_new : ndarray
        Positions in the other list [pixel].
    search : float
        Largest offset considered [pixel].

    Returns
    -------
    dx, dy : float
    votes : int
        Pairs supporting the offset.
    """
    tree = cKDTree(np.column_stack([x_new, y_new]))
    lists = tree.query_ball_point(np.column_stack([x_ref, y_ref]), search)
    dx = np.concatenate([x_new[j] - x_ref[i] for i, j in enumerate(lists) if j] or [[]])
    dy = np.concatenate([y_new[j] - y_ref[i] for i, j in enumerate(lists) if j] or [[]])
    if dx.size == 0:
        return 0.0, 0.0, 0
    edges = np.arange(-np.ceil(search) - 0.5, np.ceil(search) + 1.0, 1.0)
    hist, ex, ey = np.histogram2d(dx, dy, bins=[edges, edges])
    # vote in 3 x 3 bins so an offset on a bin edge is not split
    hist = ndimage.uniform_filter(hist, size=3, mode="constant") * 9
    i, j = np.unravel_index(np.argmax(hist), hist.shape)
    cx, cy = 0.5 * (ex[i] + ex[i + 1]), 0.5 * (ey[j] + ey[j + 1])
    near = np.hypot(dx - cx, dy - cy) <= 2.5  # the 3 x 3 bins
    for radius in (1.0, 0.5):  # shrink onto the peak
        if not near.any():
            break
        cx, cy = float(np.median(dx[near])), float(np.median(dy[near]))
        near = np.hypot(dx - cx, dy - cy) <= radius
    if not near.any():
        return cx, cy, 0
    return float(np.mean(dx[near])), float(np.mean(dy[near])), int(np.count_nonzero(near))


def centroids(image, bad, sky: float, x, y, half: int, iterations: int = 2):
    """Background-subtracted first-moment centroids [pixel] in (2 half + 1)^2 boxes.

    Returns NaN where the box leaves the frame, holds an unusable pixel, or has
    no positive flux.

    Parameters
    ----------
    image : ndarray
        The frame [electron].
    bad : ndarray of bool
        Unusable pixels.
    sky : float
        Sky level [electron/pixel].
    x, y : array_like
        Start positions [pixel].
    half : int
        Box half-size [pixel].
    iterations : int
        Re-centred passes.

    Returns
    -------
    x, y : ndarray
        Centroids [pixel].
    """
    ny, nx = image.shape
    x, y = np.asarray(x, float).copy(), np.asarray(y, float).copy()
    off = np.arange(-half, half + 1)
    for _ in range(iterations):
        cx = np.rint(np.nan_to_num(x, nan=-1e9)).astype(int)
        cy = np.rint(np.nan_to_num(y, nan=-1e9)).astype(int)
        inside = (cx - half >= 0) & (cx + half < nx) & (cy - half >= 0) & (cy + half < ny)
        rows = np.clip(cy[:, None] + off, 0, ny - 1)[:, :, None]
        cols = np.clip(cx[:, None] + off, 0, nx - 1)[:, None, :]
        cut = np.asarray(image, float)[rows, cols] - sky
        usable = inside & ~np.any(bad[rows, cols], axis=(1, 2))
        w = np.clip(cut, 0.0, None)
        total = w.sum(axis=(1, 2))
        usable &= total > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            mx = (w * off[None, None, :]).sum(axis=(1, 2)) / total
            my = (w * off[None, :, None]).sum(axis=(1, 2)) / total
        x = np.where(usable, cx + mx, np.nan)
        y = np.where(usable, cy + my, np.nan)
    return x, y


def _affine_lsq(x, y, u_, v_):
    design = np.column_stack([np.ones_like(x), x, y])
    a, *_ = np.linalg.lstsq(design, u_, rcond=None)
    b, *_ = np.linalg.lstsq(design, v_, rcond=None)
    return a, b


def fit_epoch_transform(
    earlier: EarlierEpoch,
    image: np.ndarray,
    sky: float,
    bad: np.ndarray,
    options: TransferOptions = TransferOptions(),
) -> EpochTransform:
    """Affine transform from an earlier epoch's pixels to a new frame (no truth used).

    Parameters
    ----------
    earlier : EarlierEpoch
        The earlier epoch's measurements.
    image : ndarray
        The new frame [electron].
    sky : float
        Its sky [electron/pixel].
    bad : ndarray of bool
        Its unusable pixels.
    options : TransferOptions
        Reference-star choice, search radius and clipping.

    Returns
    -------
    EpochTransform
        The fitted affine transform.

    Raises
    ------
    InputError
        Too few reference stars, or no consistent offset (the frames do not overlap
        or the offset exceeds ``options.search``).
    """
    ref = reference_stars(earlier, options)
    if len(ref) < 6:
        raise InputError(
            f"only {len(ref)} bright unflagged isolated star(s) in the earlier epoch; "
            "the observer-mode start list needs at least 6",
            path=earlier.path,
        )
    px, py = bright_peaks(image, sky, bad, 3 * len(ref))
    dx, dy, votes = histogram_offset(earlier.x[ref], earlier.y[ref], px, py, options.search)
    if votes < max(3, len(ref) // 10):
        raise InputError(
            f"no common offset within {options.search:g} pixels between the earlier epoch "
            f"and this frame ({votes} of {len(ref)} reference stars agree); different pointing?",
            path=earlier.path,
        )
    xr, yr = earlier.x[ref], earlier.y[ref]
    cx, cy = centroids(image, bad, sky, xr + dx, yr + dy, options.centroid_half)
    ok = np.isfinite(cx) & np.isfinite(cy) & (np.hypot(cx - xr - dx, cy - yr - dy) < 1.5)
    a = np.array([dx, 1.0, 0.0])
    b = np.array([dy, 0.0, 1.0])
    rms = np.nan
    for _ in range(5):
        if np.count_nonzero(ok) < 6:
            raise InputError(
                f"only {np.count_nonzero(ok)} reference star(s) could be centroided in this frame",
                path=earlier.path,
            )
        a, b = _affine_lsq(xr[ok], yr[ok], cx[ok], cy[ok])
        rx = cx - (a[0] + a[1] * xr + a[2] * yr)
        ry = cy - (b[0] + b[1] * xr + b[2] * yr)
        r = np.hypot(rx, ry)
        rms = 1.4826 * np.median(np.abs(np.concatenate([rx[ok], ry[ok]])))
        new_ok = np.isfinite(r) & (r <= max(options.clip * rms, 0.05))
        if np.array_equal(new_ok, ok):
            break
        ok = new_ok
    return EpochTransform(
        a=a, b=b, n_used=int(np.count_nonzero(ok)), rms=float(rms), offset=(dx, dy)
    )


def start_from_earlier(
    earlier: list[EarlierEpoch],
    image: np.ndarray,
    sky: float,
    bad: np.ndarray,
    options: TransferOptions = TransferOptions(),
):
    """Start list of a new frame from earlier epochs' measured positions.

    Parameters
    ----------
    earlier : list of EarlierEpoch
        Earlier epochs (any order).
    image : ndarray
        The new frame [electron].
    sky : float
        Its sky [electron/pixel].
    bad : ndarray of bool
        Its unusable pixels.
    options : TransferOptions

    Returns
    -------
    ids : ndarray of int
    x0, y0 : ndarray
        Start positions [pixel] in the new frame (stars that land outside it are
        left out).
    transforms : list of EpochTransform
        One per earlier epoch, in time order.
    """
    if not earlier:
        raise InputError("observer mode needs at least one earlier measured epoch")
    ordered = sorted(earlier, key=lambda e: e.epoch)
    ny, nx = image.shape
    position: dict[int, tuple[float, float]] = {}
    transforms = []
    for ep in ordered:  # later epochs overwrite earlier ones
        tr = fit_epoch_transform(ep, image, sky, bad, options)
        transforms.append(tr)
        xs, ys = tr.apply(ep.x, ep.y)
        position.update(zip(ep.ids.tolist(), zip(xs.tolist(), ys.tolist())))
    ids = np.fromiter(position.keys(), np.int64, len(position))
    xy = np.array(list(position.values()), float).reshape(-1, 2)
    inside = on_detector(xy[:, 0], xy[:, 1], (ny, nx))
    order = np.argsort(ids[inside], kind="stable")
    return ids[inside][order], xy[inside, 0][order], xy[inside, 1][order], transforms
