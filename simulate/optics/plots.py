"""Paper-style optics plots (PNG, matplotlib Agg).

* ``psf_grid.png``: log-intensity thumbnails of every grid PSF (fig:psfprofile style);
* ``psf_profile.png``: radial slices at (-15", -15") and (-9", -9") over the
  central PSF, with the control radius marked (fig:psfprofile);
* ``tiptilt_map.png``: TT kernel ellipses every 3" with the NGS (fig:ttjitter);
* ``tiptilt_kernel_map.png``: the product's TT kernel map (semi-axes and angle at the
  PSF-grid nodes, with seeing, zenith angle and asterism);
* ``distortion_map.png``: static distortion amplitude with the science field
  and the x / y projections (fig:staticdistmap).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Ellipse  # noqa: E402

from mavispm.core.atomic import atomic_path  # noqa: E402
from mavispm.simulate.optics.distortion import SCIENCE_RADIUS  # noqa: E402

if TYPE_CHECKING:
    from mavispm.simulate.optics.model import Optics

__all__ = [
    "draw_all",
    "plot_distortion_map",
    "plot_psf_grid",
    "plot_psf_profile",
    "plot_tiptilt_kernel_map",
    "plot_tiptilt_map",
]


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")
    plt.close(fig)
    return path


def plot_psf_grid(optics: Optics, path: Path, crop_arcsec: float = 0.4) -> Path:
    """Mosaic of log-intensity thumbnails of the grid PSFs.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    path : pathlib.Path
        The PNG written.
    crop_arcsec : float
        Side of each thumbnail [arcsec] (limited to the stamp).

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    g = optics.psf_grid
    half = min(int(crop_arcsec * 500 / g.pixel_scale), (g.n - 1) // 2)
    c = (g.n - 1) // 2
    thumbs = g.cube[:, :, c - half : c + half + 1, c - half : c + half + 1]
    ny, nx, m, _ = thumbs.shape
    mosaic = np.log10(np.maximum(thumbs, 1e-7)).transpose(0, 2, 1, 3).reshape(ny * m, nx * m)
    fig, ax = plt.subplots(figsize=(7, 7))
    dx = (g.nodes_x[1] - g.nodes_x[0]) if nx > 1 else 1.0
    dy = (g.nodes_y[1] - g.nodes_y[0]) if ny > 1 else 1.0
    extent = [
        g.nodes_x[0] - dx / 2,
        g.nodes_x[-1] + dx / 2,
        g.nodes_y[0] - dy / 2,
        g.nodes_y[-1] + dy / 2,
    ]
    im = ax.imshow(mosaic, origin="lower", extent=extent, cmap="inferno", vmin=-6)
    fig.colorbar(im, ax=ax, label="log10 PSF (per pixel)")
    ax.set_xlabel("x [arcsec]")
    ax.set_ylabel("y [arcsec]")
    ax.set_title(f'PSF grid, {g.wavelength:.0f} nm, thumbnails {2 * crop_arcsec:.1f}" wide')
    return _save(fig, path)


def _diagonal_slice(psf: np.ndarray, pixel_scale: float):
    n = psf.shape[0]
    c = (n - 1) // 2
    k = np.arange(-c, c + 1)
    r = k * pixel_scale * np.sqrt(2)
    return r, psf[c + k, c + k]


def plot_psf_profile(
    optics: Optics,
    path: Path,
    positions: Sequence[tuple[float, float]] = ((-15.0, -15.0), (-9.0, -9.0)),
) -> Path:
    """Radial (diagonal) slices of off-axis PSFs over the central PSF.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    path : pathlib.Path
        The PNG written.
    positions : sequence of (float, float)
        Field positions of the off-axis PSFs [arcsec].

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    g = optics.psf_grid
    centre = g.psf_at(0.0, 0.0)
    fig, axes = plt.subplots(
        len(positions),
        2,
        figsize=(10, 4 * len(positions)),
        gridspec_kw={"width_ratios": [2.2, 1]},
        squeeze=False,
    )
    rc = optics.control_radius
    for row, (x, y) in enumerate(positions):
        psf = g.psf_at(x, y)
        ax = axes[row, 0]
        r0, p0 = _diagonal_slice(centre, g.pixel_scale)
        r1, p1 = _diagonal_slice(psf, g.pixel_scale)
        ax.semilogy(r0, p0 / p0.max(), "r-", label='centre (0", 0")')
        ax.semilogy(r1, p1 / p0.max(), "k--", label=f'({x:g}", {y:g}")')
        for s in (-1, 1):
            ax.axvline(s * rc, color="k", ls=":", lw=1)
        ax.set_xlabel("distance along the diagonal [mas]")
        ax.set_ylabel("PSF / central peak")
        ax.set_ylim(1e-6, 1.5)
        ax.legend(loc="upper right")
        ax2 = axes[row, 1]
        ext = (g.n - 1) / 2 * g.pixel_scale
        ax2.imshow(
            np.log10(np.maximum(psf, 1e-8)),
            origin="lower",
            cmap="inferno",
            vmin=-7,
            extent=[-ext, ext, -ext, ext],
        )
        ax2.plot([-ext, ext], [-ext, ext], "c-", lw=0.8)
        ax2.set_xlabel("[mas]")
        ax2.set_title(f'log PSF at ({x:g}", {y:g}")')
    return _save(fig, path)


def plot_tiptilt_map(
    optics: Optics, path: Path, half_width: float = 15.0, step: float = 3.0
) -> Path:
    """Tip-tilt kernel ellipses (1 sigma, magnified) on a grid, with the NGS.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    path : pathlib.Path
        The PNG written.
    half_width : float
        Half-width of the grid [arcsec].
    step : float
        Grid step [arcsec].

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    tt = optics.tiptilt
    g = np.arange(-half_width, half_width + 1e-9, step)
    gx, gy = np.meshgrid(g, g)
    cov = tt.covariance(gx.ravel(), gy.ravel())
    vals, vecs = np.linalg.eigh(cov)
    sig = np.sqrt(np.clip(vals, 0, None))
    scale = 0.45 * step / max(sig.max(), 1e-12)
    fig, ax = plt.subplots(figsize=(7, 7))
    for (x, y), s, v in zip(np.stack([gx.ravel(), gy.ravel()], -1), sig, vecs):
        ang = np.degrees(np.arctan2(v[1, 1], v[0, 1]))
        ax.add_patch(
            Ellipse(
                (x, y), 2 * s[1] * scale, 2 * s[0] * scale, angle=ang, fc="none", ec="k", lw=0.8
            )
        )
    ax.plot(tt.ngs_xy[:, 0], tt.ngs_xy[:, 1], "r*", ms=14, label="NGS")
    for (x, y), m in zip(tt.ngs_xy, tt.ngs_mag):
        ax.annotate(f"H={m:g}", (x, y), textcoords="offset points", xytext=(6, 6), color="r")
    ax.axhline(0, color="0.7", lw=0.5)
    ax.axvline(0, color="0.7", lw=0.5)
    lim = max(half_width + step, np.abs(tt.ngs_xy).max() + step if tt.ngs_xy.size else 0)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_xlabel("x [arcsec]")
    ax.set_ylabel("y [arcsec]")
    mean = float(np.mean(sig[:, 1]))
    ax.set_title(
        f"TT residual kernels ({tt.settings.asterism}); mean semi-major "
        f"sigma {mean:.2f} mas; ellipses x{scale * 1000:.0f} (mas->arcsec/1000)"
    )
    ax.legend(loc="lower right")
    return _save(fig, path)


def plot_tiptilt_kernel_map(optics: Optics, path: Path) -> Path:
    """The psfgrid product's TT kernel map: semi-major / semi-minor sigma and angle at the nodes.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    path : pathlib.Path
        The PNG written.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    from mavispm.simulate.optics.tiptilt import kernel_map

    g = optics.psf_grid
    gx, gy = np.meshgrid(g.nodes_x, g.nodes_y)
    km = kernel_map(optics.tiptilt, gx, gy)
    s = optics.settings
    half = [g.nodes_x[0], g.nodes_x[-1], g.nodes_y[0], g.nodes_y[-1]]
    dx = (g.nodes_x[1] - g.nodes_x[0]) / 2 if g.nodes_x.size > 1 else 1.0
    dy = (g.nodes_y[1] - g.nodes_y[0]) / 2 if g.nodes_y.size > 1 else 1.0
    extent = [half[0] - dx, half[1] + dx, half[2] - dy, half[3] + dy]
    vmax = max(float(km.sigma_major.max()), 1e-9)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.6), layout="constrained")
    for ax, arr, name in (
        (axes[0], km.sigma_major, "tt_sigma_major"),
        (axes[1], km.sigma_minor, "tt_sigma_minor"),
    ):
        im = ax.imshow(arr, origin="lower", extent=extent, cmap="magma", vmin=0, vmax=vmax)
        fig.colorbar(im, ax=ax, label=f"{name} [mas]")
        ax.set_xlabel("x [arcsec]")
        ax.set_ylabel("y [arcsec]")
    ang = np.radians(km.angle)
    length = 1.6 * dx * km.sigma_major / vmax
    axes[0].quiver(
        gx,
        gy,
        length * np.cos(ang),
        length * np.sin(ang),
        color="c",
        pivot="middle",
        angles="xy",
        scale_units="xy",
        scale=1,
        headwidth=0,
        headlength=0,
        headaxislength=0,
    )
    axes[0].set_title("semi-major sigma; bars: tt_angle (major axis)")
    axes[1].set_title("semi-minor sigma")
    fig.suptitle(
        f'TT kernel map on the PSF-grid nodes: seeing {s.atmosphere.seeing:g}", zenith '
        f"{s.atmosphere.zenith_angle:g} deg, asterism {s.tiptilt.asterism}, "
        f"scale x{s.tiptilt.scale_factor:g}; mean semi-major {km.sigma_major.mean():.2f} mas"
    )
    return _save(fig, path)


def plot_distortion_map(optics: Optics, path: Path, half_width: float = 15.0, n: int = 61) -> Path:
    """Static distortion amplitude map and its x / y projections.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    path : pathlib.Path
        The PNG written.
    half_width : float
        Half-width of the map [arcsec].
    n : int
        Samples per side.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    g = np.linspace(-half_width, half_width, n)
    gx, gy = np.meshgrid(g, g)
    dx, dy = optics.distortion.static_displacement(gx, gy)  # mas
    amp = np.hypot(dx, dy)
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8), layout="constrained")
    im = axes[0].imshow(amp, origin="lower", extent=[g[0], g[-1], g[0], g[-1]], cmap="viridis")
    fig.colorbar(im, ax=axes[0], label="|displacement| [mas]")
    q = slice(None, None, 6)
    axes[0].quiver(gx[q, q], gy[q, q], dx[q, q], dy[q, q], color="w")
    axes[0].add_patch(Circle((0, 0), SCIENCE_RADIUS, fc="none", ec="r"))
    axes[0].set_title("static distortion")
    for ax, comp, name in ((axes[1], dx, "x"), (axes[2], dy, "y")):
        im = ax.imshow(
            comp * 1000, origin="lower", extent=[g[0], g[-1], g[0], g[-1]], cmap="RdBu_r"
        )
        fig.colorbar(im, ax=ax, label=f"d{name} x 1000 [mas]")
        ax.set_title(f"{name} projection")
    for ax in axes:
        ax.set_xlabel("x [arcsec]")
        ax.set_ylabel("y [arcsec]")
    return _save(fig, path)


def draw_all(optics: Optics, outdir: Path) -> list[Path]:
    """Draw every optics plot into ``outdir``.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    outdir : pathlib.Path
        Folder (created if needed).

    Returns
    -------
    list of pathlib.Path
        The PNG paths.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    return [
        plot_psf_grid(optics, outdir / "psf_grid.png"),
        plot_psf_profile(optics, outdir / "psf_profile.png"),
        plot_tiptilt_map(optics, outdir / "tiptilt_map.png"),
        plot_tiptilt_kernel_map(optics, outdir / "tiptilt_kernel_map.png"),
        plot_distortion_map(optics, outdir / "distortion_map.png"),
    ]
