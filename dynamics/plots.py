"""Plots of the dynamics fit: dispersion profile with model bands, corner plots."""

from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import ArrayLike  # noqa: E402

from mavispm.core.atomic import atomic_path  # noqa: E402

__all__ = [
    "corner_plot",
    "fast_star_plot",
    "model_band",
    "profile_plot",
]

_COLOURS = {
    "imbh": "tab:blue",
    "no_imbh": "tab:red",
    "none": "tab:red",
    "dark": "tab:green",
    "imbh_dark": "tab:purple",
}
_NAMES = {
    "imbh": "IMBH",
    "no_imbh": "no IMBH",
    "none": "no dark centre",
    "dark": "extended dark",
    "imbh_dark": "IMBH + extended",
}


def model_band(fit, R: ArrayLike, n_draws: int = 200, seed: int = 0):
    """16/50/84 % posterior quantiles of the model dispersions at radii ``R`` [arcsec].

    Parameters
    ----------
    fit : ModelFit
        The model's fit.
    R : array_like
        Projected radii [arcsec].
    n_draws : int
        Posterior samples drawn.
    seed : int
        Seed of the draws.

    Returns
    -------
    ndarray, shape (3, 2, len(R))
        Quantile x (radial, tangential) x radius, in mas/yr.
    """
    rng = np.random.default_rng(seed)
    samples = fit.chain.samples
    pick = rng.choice(len(samples), size=min(n_draws, len(samples)), replace=False)
    curves = np.array([fit.likelihood.dispersion_at(samples[i], R) for i in pick])
    return np.percentile(curves, [16, 50, 84], axis=0)


def profile_plot(profile, fits, truths, path: str | os.PathLike, seed: int = 0):
    """Radial and tangential dispersion profiles: data, model bands and truth.

    Parameters
    ----------
    profile : QTable
        From :func:`mavispm.dynamics.profiles.dispersion_profile`.
    fits : list of ModelFit
    truths : dict of str to QTable
        Truth profiles by model name ("imbh", "no_imbh").
    path : path
        PNG file (written atomically).
    seed : int
        Seed of the posterior draws of the model bands.
    """
    R_lo = max(float(profile["R_min"].value.min()) if len(profile) else 0.1, 0.05)
    R_hi = fits[0].likelihood.stars.field_radius
    R = np.geomspace(R_lo, R_hi, 60)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for k, (ax, comp) in enumerate(zip(axes, ("r", "t"))):
        for fit in fits:
            q = model_band(fit, R, seed=seed)
            c = _COLOURS[fit.name]
            ax.fill_between(R, q[0, k], q[2, k], color=c, alpha=0.25, lw=0)
            ax.plot(R, q[1, k], color=c, label=f"{_NAMES[fit.name]} model (68%)")
        for name, tab in truths.items():
            ax.plot(
                tab["R_mean"].value,
                tab[f"sigma_{comp}"].value,
                "s--",
                color=_COLOURS[name],
                mfc="none",
                label=f"truth {_NAMES[name]}",
            )
        if len(profile):
            ax.errorbar(
                profile["R_mean"].value,
                profile[f"sigma_{comp}"].value,
                yerr=profile[f"sigma_{comp}_err"].value,
                xerr=[
                    profile["R_mean"].value - profile["R_min"].value,
                    profile["R_max"].value - profile["R_mean"].value,
                ],
                fmt="k*",
                ms=9,
                label="measured (ML, errors deconvolved)",
            )
        ax.set_xscale("log")
        ax.set_xlabel("R [arcsec]")
        ax.set_title({"r": "radial", "t": "tangential"}[comp] + " proper motion")
    axes[0].set_ylabel(r"$\sigma_\mu$ [mas/yr]")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path


def corner_plot(fit, path: str | os.PathLike, bins: int | None = None):
    """A small corner plot (histograms and smoothed 2-D 68/95% contours) of one model's chain.

    ``bins`` defaults to ``sqrt(n) / 2`` clipped to [10, 40] for ``n`` samples.

    Parameters
    ----------
    fit : ModelFit
        The model's fit.
    path : str or os.PathLike
        The PNG written.
    bins : int, optional
        Histogram bins per parameter.
    """
    from scipy.ndimage import gaussian_filter

    x = fit.chain.samples
    if bins is None:
        bins = int(np.clip(np.sqrt(len(x)) / 2, 10, 40))
    names = fit.chain.names
    labels = [p.label or p.name for p in fit.space.params]
    n = len(names)
    fig, axes = plt.subplots(n, n, figsize=(2.2 * n, 2.2 * n), squeeze=False)
    for i in range(n):
        for j in range(n):
            ax = axes[i, j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(x[:, i], bins=bins, histtype="step", color="k", density=True)
                q = np.percentile(x[:, i], [16, 50, 84])
                for v in q:
                    ax.axvline(v, color="tab:blue", ls="--", lw=0.8)
                ax.set_yticks([])
                ax.set_title(f"{q[1]:.3g} (+{q[2] - q[1]:.2g} -{q[1] - q[0]:.2g})", fontsize=8)
            else:
                h, xe, ye = np.histogram2d(x[:, j], x[:, i], bins=bins)
                h = gaussian_filter(h, 1.0)
                hs = np.sort(h.ravel())[::-1]
                cum = np.cumsum(hs) / max(hs.sum(), 1)
                levels = sorted(
                    {hs[min(np.searchsorted(cum, p), hs.size - 1)] for p in (0.95, 0.68)}
                )
                if len(levels) > 1 or (levels and levels[0] > 0):
                    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
                    ax.contour(
                        xc,
                        yc,
                        h.T,
                        levels=[lv for lv in levels if lv > 0] or [0.5],
                        colors="k",
                        linewidths=0.8,
                    )
                ax.plot(x[:, j], x[:, i], ",", color="0.6", alpha=0.3, zorder=0)
            if i == n - 1:
                ax.set_xlabel(labels[j], fontsize=9)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(labels[i], fontsize=9)
            elif j > 0:
                ax.set_yticklabels([])
    fig.suptitle(
        f"{_NAMES[fit.name]} model: {len(x)} samples, tau_max = {np.max(fit.chain.tau):.0f}"
    )
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)
    return path


def fast_star_plot(result, path: str | os.PathLike, title: str | None = None):
    """2-D speed against projected radius with the escape-velocity curves.

    Parameters
    ----------
    result : mavispm.dynamics.fast_stars.FastStarResult
        A test that was possible (``result.curves`` filled).
    path : path
        PNG file (written atomically).
    title : str, optional
    """
    from pathlib import Path

    c = result.curves
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    fast = np.asarray(c["fast_all"], bool)
    ax.errorbar(
        np.maximum(c["R_all"][~fast], 1e-2),
        c["v_all"][~fast],
        yerr=c["v_err_all"][~fast],
        fmt=".",
        ms=2,
        lw=0.5,
        color="0.6",
        label="stars",
    )
    if fast.any():
        ax.errorbar(
            np.maximum(c["R_all"][fast], 1e-2),
            c["v_all"][fast],
            yerr=c["v_err_all"][fast],
            fmt="*",
            ms=9,
            color="tab:orange",
            label=f"significant fast stars ({int(fast.sum())})",
        )
    q = result.attrs.get("fast_escape_quantile", 0.99)
    ax.plot(
        c["R"],
        c["v_esc_no_imbh"],
        color=_COLOURS["no_imbh"],
        label=f"v_esc no IMBH ({q:.0%} quantile)",
    )
    ax.plot(
        c["R"],
        c["v_esc_no_imbh_median"],
        color=_COLOURS["no_imbh"],
        ls="--",
        label="v_esc no IMBH (median)",
    )
    if np.any(np.isfinite(c["v_esc_imbh"])):
        ax.plot(c["R"], c["v_esc_imbh"], color=_COLOURS["imbh"], label="v_esc IMBH model (median)")
    ax.set_xscale("log")
    ax.set_xlabel("projected radius R [arcsec]")
    ax.set_ylabel("2-D velocity v_2D [km/s]")
    lim = result.attrs.get("bh_mass_lower_limit")
    conf = result.attrs.get("bh_mass_lower_limit_confidence", 0.95)
    sub = ""
    if lim is not None and fast.any():
        sub = f"; M_BH > {float(getattr(lim, 'value', lim)):.0f} Msun ({conf:.0%})"
    ax.set_title(title or f"Fast-star test: 2-D velocity vs radius{sub}", fontsize=10)
    top = np.nanmax(
        np.concatenate(
            [
                c["v_all"] + c["v_err_all"],
                c["v_esc_imbh"][np.isfinite(c["v_esc_imbh"])],
                c["v_esc_no_imbh"],
            ]
        )
    )
    ax.set_ylim(0, 1.1 * top)
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path
