"""The frame's background on a mesh of block medians: the PSF stars' isolation test's sky.

An unresolved crowd of faint stars lays a background on the frame that the global sky
misses (at 1e5 stars over 30" it is several times a V 25 star's flux per 5 x 5 box
above the frame's sky); a mesh of block medians, each smoothed over its 3 x 3 block
neighbourhood, follows it while one bright star raises a block's median by little.
The algorithm is photutils' ``Background2D`` (``MedianBackground``, ``filter_size =
3``), kept as our own for its cost and checked against the library in
``tests/test_measure_mesh_sky.py`` (:func:`sky_mesh`).
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
from photutils.utils import ShepardIDWInterpolator
from scipy import ndimage

from mavispm.core.frame import Frame

__all__ = ["SkyMesh", "mesh_sky", "sky_mesh"]


class SkyMesh(NamedTuple):
    """The frame's background on a mesh of blocks (:func:`sky_mesh`).

    Attributes
    ----------
    medians : ndarray (nby, nbx)
        Median of each block's usable pixels [electron / pixel]; NaN where a block has none.
    background : ndarray (nby, nbx)
        The medians, a block without usable pixels given the inverse-distance mean of the
        10 nearest blocks' (photutils' ``ShepardIDWInterpolator``, as ``Background2D``),
        smoothed by the median of each 3 x 3 block neighbourhood [electron / pixel].
    yc, xc : ndarray
        Centres of the blocks' rows and columns [pixel] (an edge block narrower than
        ``mesh``: the centre of its pixels).
    """

    medians: np.ndarray
    background: np.ndarray
    yc: np.ndarray
    xc: np.ndarray


def sky_mesh(frame: Frame, mesh: int) -> SkyMesh:
    """The frame's background on a mesh of ``mesh x mesh`` pixel blocks.

    The algorithm of photutils' ``Background2D`` (``MedianBackground`` without sigma
    clipping, ``exclude_percentile = 100``, the frame's bad pixels as ``mask``); its raw
    block medians are the library's to float32 rounding and its smoothed mesh is the
    library's ``background_mesh`` (``filter_size = 3``) away from the frame's edges
    (``tests/test_measure_mesh_sky.py``). Kept as our own for its cost: on the 4000 x
    4000 float64 frames of the scale benchmark ``Background2D`` took 0.9-1.7 s CPU and a
    256 MB traced peak (its float32 copy of the frame included; 304 MB with its default
    sigma clipping) against 0.4-0.65 s and < 5 MB here (one block row at a time), for the
    same PSF-star pool (4,332 of 4,332 at 1e4 stars, 5,752 of 5,753 at 1e5; loaded host;
    docs/measure-scale.md, mesh sky). A block without usable pixels is filled as the
    library fills it. Where the two differ, by choice:

    * edges: the mesh is padded by odd reflection (``2 edge - inner``) before the 3 x 3
      median, so a plane passes unchanged up to the corners; the library's NaN padding
      (a median over the 4-6 blocks inside) sets an edge block half a block's step of
      a perpendicular gradient towards the inside;
    * :func:`mesh_sky` interpolates bilinearly between the blocks' pixel centres and
      extrapolates linearly beyond the outer ones to the frame's edge (the library's
      ``background`` image places a narrower edge block's value at a full block's
      centre).

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    mesh : int
        Block side [pixel].

    Returns
    -------
    SkyMesh
    """
    ny, nx = frame.shape
    nby, nbx = -(-ny // mesh), -(-nx // mesh)
    medians = np.empty((nby, nbx))
    for j in range(nby):  # a row of blocks at a time: no full-frame copy
        rows = frame.image[j * mesh : (j + 1) * mesh].astype(np.float32)
        rows[frame.bad[j * mesh : (j + 1) * mesh]] = np.nan
        pad = nbx * mesh - nx
        if pad:
            rows = np.pad(rows, ((0, 0), (0, pad)), constant_values=np.nan)
        cells = rows.reshape(len(rows), nbx, mesh).transpose(1, 0, 2).reshape(nbx, -1)
        with warnings.catch_warnings():  # a block without usable pixels: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            medians[j] = np.nanmedian(cells, axis=1)
    empty = ~np.isfinite(medians)
    if empty.all():
        filled = np.full(medians.shape, float(frame.sky))
    elif empty.any():  # as the library: inverse-distance weights of the 10 nearest
        good = np.argwhere(~empty)
        idw = ShepardIDWInterpolator(good, medians[~empty])
        filled = medians.copy()
        filled[empty] = idw(np.argwhere(empty), n_neighbors=min(10, len(good)), power=1.0)
    else:
        filled = medians
    padded = np.pad(filled, 1, mode="reflect", reflect_type="odd")
    background = ndimage.median_filter(padded, size=3)[1:-1, 1:-1]

    def centres(n, nb):
        lo = np.arange(nb) * mesh
        return (lo + np.minimum(lo + mesh, n) - 1) / 2.0

    return SkyMesh(medians, background, centres(ny, nby), centres(nx, nbx))


def mesh_sky(frame: Frame, x: np.ndarray, y: np.ndarray, mesh: int) -> np.ndarray:
    """The frame's background [electron / pixel] at the stars, from a mesh of block medians.

    The frame is cut into ``mesh x mesh`` pixel blocks; each block's median (usable
    pixels only) is smoothed by the median of its 3 x 3 block neighbourhood (a block
    dominated by one bright star does not count) and interpolated bilinearly between
    block centres at ``x, y`` (extrapolated linearly to the frame's edge; positions
    beyond it are taken at it) (:func:`sky_mesh`: photutils' ``Background2D`` mesh, kept
    as our own for its cost). The background an unresolved crowd of faint stars lays on
    the frame is in it (at 1e5 stars over 30" it is several times a V 25 star's flux per
    5 x 5 box above the frame's sky), while one bright star raises a block's median by
    little.

    Parameters
    ----------
    frame : Frame
        The frame [electron].
    x, y : ndarray
        Positions [pixel].
    mesh : int
        Block side [pixel].

    Returns
    -------
    ndarray
        Background per pixel [electron], one per position.
    """
    sky = sky_mesh(frame, mesh)
    ny, nx = frame.shape
    iy, ty = _mesh_cell(np.clip(np.nan_to_num(np.asarray(y, float)), -0.5, ny - 0.5), sky.yc)
    ix, tx = _mesh_cell(np.clip(np.nan_to_num(np.asarray(x, float)), -0.5, nx - 0.5), sky.xc)
    b = sky.background
    jy, jx = np.minimum(iy + 1, len(sky.yc) - 1), np.minimum(ix + 1, len(sky.xc) - 1)
    return (1 - ty) * ((1 - tx) * b[iy, ix] + tx * b[iy, jx]) + ty * (
        (1 - tx) * b[jy, ix] + tx * b[jy, jx]
    )


def _mesh_cell(p: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh interval of each position and its fraction along it, extrapolated
    linearly beyond the outer block centres (a constant there sets a gradient's edge
    value half a block off)."""
    if len(centres) == 1:
        return np.zeros(len(p), int), np.zeros(len(p))
    i = np.clip(np.searchsorted(centres, p) - 1, 0, len(centres) - 2)
    return i, (p - centres[i]) / (centres[i + 1] - centres[i])
