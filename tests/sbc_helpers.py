"""Simulation-based calibration of the full dynamical model (issue 13, item 7).

Every parameter of a model of the validation matrix (cluster mass and Plummer scale,
free density cusp, IMBH, optional extended dark Plummer component, constant anisotropy
or the general profile beta(r) = beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2),
distance, centre and systemic motion) is drawn from the prior the fit uses, a proper-
motion sample is drawn from the model, and the fit's posterior rank of the true M_bh
is recorded (Talts et al. 2018: uniform over many draws if the posterior is calibrated).

The forward model is written here, independently of ``mavispm.dynamics``: the cusped
tracer, its enclosed mass, the Jeans integral (its integrating factor exp(int 2 beta / r dr)
itself a trapezoid sum, so that constant and radius-dependent beta take one path) and the
line-of-sight projections (beta taken at each depth) are dense trapezoid sums on fine
logarithmic grids (the package uses Gauss-Legendre panels, a closed-form integrating
factor, cubic grid interpolation and compiled kernels). The ``"df"`` draws exist for
constant beta only.

Two velocity laws:

``"projected"``
    each star's proper motion is Gaussian with the projected dispersions at its
    projected radius: exactly the law the likelihood assumes, so the SBC tests the
    computation (grids, quadrature, priors, sampler);
``"3d"``
    each star gets a line-of-sight depth from the tracer and a Gaussian 3-D velocity
    with the dispersions at its 3-D radius (a real cluster's scale mixture along the
    line of sight): the SBC then also tests the likelihood's Gaussian approximation.
``"df"``
    each star gets a line-of-sight depth from the tracer and a 3-D velocity drawn from
    the equilibrium distribution function of the tracer in the model's total potential
    (cluster mass with the tracer's profile, IMBH, dark component): the constant-beta
    Cuddeford DF ``f = L^(-2 beta) g(E)`` (Eddington's for beta = 0), ``g`` from the Abel
    inversion of ``r^(2 beta) nu(Psi)`` (``cuddeford_g``), truncated at the escape speed
    and platykurtic near a point mass as a real cluster's are. Its second moments are the
    Jeans dispersions of ``sigma_r2_3d`` (the Jeans equation is the DF's moment).
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import cumulative_trapezoid, trapezoid
from scipy.special import gamma as gamma_fn

G = 4.300917270e-3  # pc (km/s)^2 / Msun
KMS = 4.740470463533348  # km/s per mas/yr per kpc
PC_PER_ARCSEC_KPC = 1e3 * np.pi / 648000.0

#: Fine grid of r / a for the tracer, its mass and the Jeans integral (1e-4 e-fold steps
#: would be overkill: 2e-3 gives relative errors ~1e-6 for these smooth integrands).
LN_X = np.linspace(np.log(1e-7), np.log(1e5), 16_001)

#: Priors of the calibration (the fit's priors; the validation matrix's except the cluster
#: mass, here U(4.8, 5.4) in log10 solMass about NGC 3201 instead of U(3, 7)).
SBC_FULL_SETTINGS = dict(
    progress=False,
    posterior="nested",
    nlive=100,
    dlogz=0.5,
    cusp=True,
    log_mass_range=(4.8, 5.4),
    log_scale_radius_range=(1.0, 3.0),
    log_scale_radius_prior=(2.083, 0.05),
    distance_error=0.04,
    centre_error=0.5,
    systemic_error=0.05,
    anisotropy="constant",
)
SBC_DISTANCE = 4.6
SBC_FIELD_RADIUS = 15.0

#: Priors where the constant-beta DF exists around a point mass, for the draws *and* the
#: fits of the ``"df"`` SBC: gamma >= beta + 1/2 and gamma >= 2 beta at the centre (An &
#: Evans 2006), and a cusp radius of 10^1.5-10^2.5" (0.26-2.6 Plummer radii): with a
#: smaller one the tracer is flat between the cusp and the Plummer radius, inside the
#: IMBH's influence radius, and the DF is negative there (53 % of 240 draws of the full
#: U(-1, 2.5) range, 0 of 56 with r_c >= 10^1.5").
SBC_DF_PRIORS = dict(
    gamma_range=(0.75, 2.0), beta_range=(-0.5, 0.25), log_cusp_radius_range=(1.5, 2.5)
)


def sbc_space(model: str, velocity_law: str = "line_of_sight", **overrides):
    """The fit's parameter space (and settings) for ``model`` (``imbh``, ``imbh_dark`` or
    ``none``) with the likelihood's ``velocity_law``; ``overrides`` replace settings
    (e.g. ``SBC_DF_PRIORS``, ``kappa_profile``)."""
    from mavispm.dynamics.fit import parameter_space
    from mavispm.dynamics.settings import DynamicsSettings

    kw = {**SBC_FULL_SETTINGS, **overrides}
    s = DynamicsSettings(**kw, models=(model,), velocity_law=velocity_law)
    return parameter_space(s, SBC_DISTANCE, model, positions=True), s


def tracer_shape(x, gamma, xc):
    """Unnormalised cusped Plummer density: (1 + x^2)^-5/2 (1 + (xc / x)^2)^(gamma / 2)."""
    return (1.0 + x * x) ** -2.5 * (1.0 + (xc / x) ** 2) ** (0.5 * gamma)


def model_tables(p: dict):
    """Density, enclosed mass [solMass] and nu sigma_r^2 on ``LN_X`` for parameters ``p``.

    Returns
    -------
    x, nu, mass_fraction, nu_s2 : ndarray
        r / a; the tracer density normalised to unit number; the tracer's enclosed
        fraction; nu sigma_r^2 in units of G solMass / a_pc [(km/s)^2 per unit density].
    """
    x = np.exp(LN_X)
    a = 10.0 ** p["log_scale_radius"]
    shape = tracer_shape(x, p["gamma"], 10.0 ** p["log_cusp_radius"] / a)
    dm = 4.0 * np.pi * x**3 * shape  # d(mass) / d(ln x)
    inner = dm[0] / (3.0 - p["gamma"])  # the r^-gamma power law below the grid
    cum = inner + cumulative_trapezoid(dm, LN_X, initial=0.0)
    total = cum[-1] + 4.0 * np.pi * x[-1] ** -2 / 2.0  # the r^-5 tail
    nu, frac = shape / total, cum / total
    mass = total_mass(p, x, frac)
    ln_g = ln_integrating_factor(p, x)
    peak = ln_g.max()  # scaled out of g so that it stays finite on the whole grid
    f = np.exp(ln_g - peak) * nu * mass / x**2 * x  # integrand in ln x
    outer = -cumulative_trapezoid(f[::-1], LN_X[::-1], initial=0.0)[::-1]  # int_x^x_max
    # beyond the grid nu ~ x^-5 / total, the mass is constant and g ~ x^(2 beta_inf)
    b_out = float(anisotropy_at(p, x[-1]))
    tail = f[-1] / (6 - 2 * b_out)
    nu_s2 = np.exp(peak - ln_g) * (outer + tail)
    return x, nu, frac, nu_s2


def anisotropy_at(p: dict, x):
    """beta at r / a = ``x`` for parameters ``p``: constant (``beta``) or the general profile
    beta_0 + (beta_inf - beta_0) r^2 / (r^2 + r_a^2) (``beta_0``, ``beta_inf``,
    ``log_anisotropy_radius`` in log10 arcsec)."""
    x = np.asarray(x, dtype=float)
    if "beta" in p:
        return np.full_like(x, p["beta"])
    xa = 10.0 ** p["log_anisotropy_radius"] / 10.0 ** p["log_scale_radius"]
    return p["beta_0"] + (p["beta_inf"] - p["beta_0"]) * x * x / (x * x + xa * xa)


def ln_integrating_factor(p: dict, x: np.ndarray) -> np.ndarray:
    """ln g(x), g = exp(int 2 beta / x dx), of the Jeans equation for ``p``: written as the
    cumulative trapezoid sum of 2 beta over ``ln x`` (no closed form used)."""
    two_beta = 2.0 * anisotropy_at(p, x)
    lx = np.log(x)
    return two_beta[0] * lx[0] + cumulative_trapezoid(two_beta, lx, initial=0.0)


def total_mass(p: dict, x: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """The model's gravitating mass [solMass] inside r / a = ``x`` (tracer's enclosed
    fraction ``frac``): the cluster's, the point mass and the dark Plummer component."""
    mass = 10.0 ** p["log_mass"] * frac + p.get("bh_mass", 0.0)
    if p.get("dark_mass", 0.0) > 0:
        y = x * 10.0 ** p["log_scale_radius"] / 10.0 ** p["log_dark_radius"]
        mass = mass + p["dark_mass"] * y**3 / (1.0 + y * y) ** 1.5
    return mass


def tracer_log_slope(x, gamma, xc):
    """d ln(tracer_shape) / d ln x, analytic (no cancellation in the core)."""
    return -5.0 * x * x / (1.0 + x * x) - gamma * xc * xc / (x * x + xc * xc)


def relative_potential(x: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Psi(x) = int_x^inf M(x') / x'^2 dx' [G solMass / a] (0 at infinity; M constant
    beyond the grid), a trapezoid sum in ln x."""
    lx = np.log(x)
    inner = -cumulative_trapezoid((mass / x)[::-1], lx[::-1], initial=0.0)[::-1]
    return inner + mass[-1] / x[-1]


def cuddeford_g(x, rho_b, slope_b, mass, beta: float, n_energy: int = 2000):
    """g(E) of the constant-beta DF ``f = L^(-2 beta) g(E)`` of the density ``nu`` with
    ``rho_b = x^(2 beta) nu`` (and its analytic log slope ``slope_b``) in the potential of
    ``mass`` (G = 1, lengths in units of the grid ``x``).

    ``r^(2 beta) nu = C_beta int_0^Psi (Psi - E)^(1/2 - beta) g(E) dE`` (Cuddeford 1991) is
    inverted in its second form,
    ``g(E) = int_0^E (d^2 rho_b / d Psi^2) (E - Psi)^(beta - 1/2) dPsi / (C_beta
    Gamma(3/2 - beta) Gamma(1/2 + beta))`` (``rho_b`` and its slope vanish at Psi = 0):
    ``d rho_b / d Psi = -rho_b slope_b x / M`` on the grid, its derivative by central
    differences in ln x, and the Abel integral by product integration (midpoint value of
    the second derivative on each segment, the kernel integrated exactly), with the
    part below the grid's last Psi from ``rho_b`` linear in Psi there (``rho_b'(Psi_min)
    (E - Psi_min)^(k - 1) + c (E^(k - 1) - (E - Psi_min)^(k - 1))`` with ``c`` that slope;
    negligible for a cluster, whose ``rho_b`` falls as ``Psi^5`` there).

    Returns
    -------
    psi : ndarray
        Psi on the grid ``x`` (descending).
    energy, g : ndarray
        Energies (Psi at ``n_energy`` grid radii, ascending) and g there (may be negative
        where no DF of this family exists).
    """
    k = beta + 0.5
    psi = relative_potential(x, mass)
    lx = np.log(x)
    d1 = -rho_b * slope_b * x / mass  # d rho_b / d Psi
    d2 = np.gradient(d1, lx) / (-mass / x)  # d^2 rho_b / d Psi^2
    ps, d2s = psi[::-1], d2[::-1]  # ascending Psi
    slope0 = rho_b[-1] / ps[0]  # rho_b linear in Psi below the grid
    lo, hi, mid = ps[:-1], ps[1:], 0.5 * (d2s[:-1] + d2s[1:])
    pick = np.unique(np.linspace(0, x.size - 1, n_energy).astype(int))[::-1]
    energy = psi[pick]
    c_beta = 2.0 ** (1.5 - beta) * np.pi**1.5 * gamma_fn(1.0 - beta) / gamma_fn(1.5 - beta)
    norm = c_beta * gamma_fn(1.5 - beta) * gamma_fn(0.5 + beta)
    g = np.empty(energy.size)
    for i0 in range(0, energy.size, 64):
        e = energy[i0 : i0 + 64, None]
        w = (np.clip(e - lo, 0, None) ** k - np.clip(e - hi, 0, None) ** k) / k
        de = np.maximum(e[:, 0] - ps[0], 1e-300)
        g[i0 : i0 + 64] = (
            w @ mid
            + np.where(e[:, 0] > ps[0], (d1[-1] - slope0) * de ** (k - 1.0), 0.0)
            + slope0 * e[:, 0] ** (k - 1.0)
        )
    return psi, energy, g / norm


def df_tables(p: dict, n_energy: int = 2000):
    """The tracer's constant-beta DF in the model's total potential, for parameters ``p``.

    Returns
    -------
    dict
        ``x`` (grid r / a, from 1e-6), ``psi`` [G solMass / a_pc], ``energy``, ``g`` (the
        inversion, normalised to the tracer's unit number), ``nu``, ``beta``,
        ``min_g`` (most negative g over max g; < 0: no DF of this family for ``p``).
    """
    if "beta" not in p:
        raise ValueError("the DF draws are written for constant beta only (parameter 'beta')")
    x, nu, frac, _ = model_tables(p)
    keep = x >= 1e-6
    x, nu, frac = x[keep], nu[keep], frac[keep]
    a = 10.0 ** p["log_scale_radius"]
    xc = 10.0 ** p["log_cusp_radius"] / a
    beta = p["beta"]
    mass = total_mass(p, x, frac)
    slope = tracer_log_slope(x, p["gamma"], xc) + 2.0 * beta
    psi, energy, g = cuddeford_g(x, x ** (2 * beta) * nu, slope, mass, beta, n_energy)
    return dict(
        x=x, psi=psi, energy=energy, g=g, nu=nu, beta=beta, min_g=min(g.min(), 0.0) / g.max()
    )


def df_velocities(energy, g, beta: float, psi_star, rng, n_u: int = 2048):
    """3-D velocities from ``f = L^(-2 beta) g(E)`` at relative potentials ``psi_star``.

    In speed ``v`` and the angle ``eta`` from the radial direction the density is
    ``v^(2 - 2 beta) g(Psi - v^2/2) sin^(1 - 2 beta)(eta)``: separable. The speed is drawn
    per star by inverting the cumulative sum on ``n_u`` nodes of ``u = v / v_esc``
    (``v_esc = sqrt(2 Psi)``: no star exceeds it), ``eta`` from its tabulated CDF, the
    tangential direction uniform. ``g <= 0`` counts as 0.

    Returns
    -------
    v_r, v_1, v_2 : ndarray
        Radial and the two tangential components, in units of sqrt(Psi's unit).
    """
    psi_star = np.asarray(psi_star, float)
    ln_e = np.log(energy)
    ln_g = np.log(np.maximum(g, 1e-300))
    u = np.linspace(0.0, 1.0, n_u)
    out = np.empty(psi_star.size)
    for i0 in range(0, psi_star.size, 256):
        ps = psi_star[i0 : i0 + 256, None]
        e = ps * (1.0 - u * u)
        weight = np.broadcast_to((u * u) ** (1.0 - beta), e.shape)
        dens = np.zeros(e.shape)
        ok = (e >= energy[0]) & (e <= energy[-1])
        dens[ok] = np.exp(np.interp(np.log(e[ok]), ln_e, ln_g)) * weight[ok]
        cdf = np.concatenate(
            [np.zeros((dens.shape[0], 1)), np.cumsum(0.5 * (dens[:, 1:] + dens[:, :-1]), 1)], 1
        )
        cdf /= cdf[:, -1:]
        q = rng.uniform(0.0, 1.0, dens.shape[0])
        j = np.sum(cdf < q[:, None], axis=1).clip(1, n_u - 1)
        rows = np.arange(dens.shape[0])
        t = (q - cdf[rows, j - 1]) / np.maximum(cdf[rows, j] - cdf[rows, j - 1], 1e-300)
        out[i0 : i0 + 256] = (u[j - 1] + t * (u[j] - u[j - 1])) * np.sqrt(2.0 * ps[:, 0])
    eta_grid = np.linspace(0.0, np.pi, 4097)
    w = np.sin(eta_grid) ** (1.0 - 2.0 * beta)
    ceta = cumulative_trapezoid(w, eta_grid, initial=0.0)
    eta = np.interp(rng.uniform(0.0, ceta[-1], psi_star.size), ceta, eta_grid)
    phi = rng.uniform(0.0, 2.0 * np.pi, psi_star.size)
    vt = out * np.sin(eta)
    return out * np.cos(eta), vt * np.cos(phi), vt * np.sin(phi)


def df_moments(energy, g, beta: float, psi_star, n_u: int = 20001):
    """Density and radial / one-tangential velocity second moments of the DF at
    potentials ``psi_star`` by quadrature over the speed (no sampling).

    ``nu_b = r^(2 beta) nu = 2 pi int sin^(1-2 beta) deta int v^(2-2 beta) g dv`` and
    ``<v_r^2> = <v^2> / (3 - 2 beta)``, ``<v_t1^2> = (1 - beta) <v^2> / (3 - 2 beta)``.
    """
    ln_e, ln_g = np.log(energy), np.log(np.maximum(g, 1e-300))
    u = np.linspace(0.0, 1.0, n_u)
    res = []
    for ps in np.atleast_1d(psi_star):
        e = ps * (1.0 - u * u)
        gv = np.where(
            (e >= energy[0]) & (e <= energy[-1]),
            np.exp(np.interp(np.log(np.maximum(e, 1e-300)), ln_e, ln_g)),
            0.0,
        )
        v = u * np.sqrt(2.0 * ps)
        m0 = trapezoid(v ** (2 - 2 * beta) * gv, v)
        m2 = trapezoid(v ** (4 - 2 * beta) * gv, v)
        ang = np.sqrt(np.pi) * gamma_fn(1.0 - beta) / gamma_fn(1.5 - beta)
        v2 = m2 / m0
        res.append((2 * np.pi * ang * m0, v2 / (3 - 2 * beta), (1 - beta) * v2 / (3 - 2 * beta)))
    return np.array(res).T


def _dispersion_unit(p: dict) -> float:
    """G solMass / a_pc in (mas/yr)^2 (the unit of ``nu_s2 / nu``) at the distance of ``p``."""
    a_pc = 10.0 ** p["log_scale_radius"] * p["distance"] * PC_PER_ARCSEC_KPC
    return G / a_pc / (KMS * p["distance"]) ** 2


def _line_of_sight(X: np.ndarray, x_max: float, n_t: int):
    """Nodes t of x = X cosh t from the sky plane to ``x_max`` (x dx / sqrt(x^2 - X^2) = x dt)
    and the radii x there, one row per X."""
    t = np.linspace(0.0, 1.0, n_t)[None, :] * np.arccosh(x_max / X)[:, None]
    return t, X[:, None] * np.cosh(t)


def projected_dispersions(p: dict, X: np.ndarray, n_t: int = 3000):
    """Projected radial and tangential dispersions squared [(mas/yr)^2] at X = R / a."""
    x, nu, _, nu_s2 = model_tables(p)
    lx = np.log(x)
    t, r = _line_of_sight(X, x[-1], n_t)
    lr = np.log(r)
    sig = trapezoid(np.exp(np.interp(lr, lx, np.log(nu))) * r, t, axis=1)
    s2 = np.exp(np.interp(lr, lx, np.log(nu_s2))) * r
    beta = anisotropy_at(p, r)
    t_part = trapezoid((1.0 - beta) * s2, t, axis=1)
    r_part = t_part + trapezoid(beta * s2 / np.cosh(t) ** 2, t, axis=1)
    scale = _dispersion_unit(p)
    return scale * r_part / sig, scale * t_part / sig


def sigma_r2_3d(p: dict, x3: np.ndarray):
    """3-D radial dispersion squared [(mas/yr)^2] at r / a = ``x3``."""
    x, nu, _, nu_s2 = model_tables(p)
    ln_s2 = np.interp(np.log(x3), np.log(x), np.log(nu_s2) - np.log(nu))
    return _dispersion_unit(p) * np.exp(ln_s2)


def draw_sample(
    p: dict,
    n_stars: int,
    rng,
    velocities: str = "projected",
    field_radius: float = SBC_FIELD_RADIUS,
    df: dict | None = None,
):
    """Stars inside the field (radius ``field_radius`` [arcsec] about the origin, the
    cluster centre at ``(x0, y0)``) with noisy proper motions; a ``StarSample``.
    ``velocities``: "projected", "3d" or "df" (``df``: ``df_tables(p)`` if computed)."""
    if velocities not in ("projected", "3d", "df"):
        raise ValueError(f"velocities must be 'projected', '3d' or 'df', got {velocities!r}")
    from mavispm.dynamics.likelihood import StarSample

    x, _, frac, _ = model_tables(p)
    a = 10.0 ** p["log_scale_radius"]
    xs, ys, zs = [], [], []
    need = n_stars
    while need > 0:
        q = rng.uniform(frac[0], frac[-1], 400_000)
        r = np.exp(np.interp(q, frac, np.log(x))) * a  # arcsec
        cth, phi = rng.uniform(-1, 1, q.size), rng.uniform(0, 2 * np.pi, q.size)
        sth = np.sqrt(1 - cth**2)
        px = r * sth * np.cos(phi) + p["x0"]
        py = r * sth * np.sin(phi) + p["y0"]
        keep = np.hypot(px, py) < field_radius
        xs.append(px[keep])
        ys.append(py[keep])
        zs.append((r * cth)[keep])
        need -= int(keep.sum())
    px, py, pz = (np.concatenate(v)[:n_stars] for v in (xs, ys, zs))
    dx, dy = px - p["x0"], py - p["y0"]
    Rc = np.hypot(dx, dy)
    c, s = dx / Rc, dy / Rc
    if velocities == "projected":
        s2r, s2t = projected_dispersions(p, Rc / a)
        v_R = np.sqrt(s2r) * rng.standard_normal(n_stars)
        v_T = np.sqrt(s2t) * rng.standard_normal(n_stars)
    else:
        r3 = np.sqrt(Rc**2 + pz**2)
        if velocities == "3d":
            sr = np.sqrt(sigma_r2_3d(p, r3 / a))
            st = sr * np.sqrt(1.0 - anisotropy_at(p, r3 / a))
            v_r, v_1, v_2 = (sg * rng.standard_normal(n_stars) for sg in (sr, st, st))
        else:
            df = df_tables(p) if df is None else df
            psi_star = np.exp(np.interp(np.log(r3 / a), np.log(df["x"]), np.log(df["psi"])))
            v = df_velocities(df["energy"], df["g"], p["beta"], psi_star, rng)
            v_r, v_1, v_2 = (np.sqrt(_dispersion_unit(p)) * vi for vi in v)
        # sky-radial = r-hat and theta-hat mixed by the angle between R and r
        sin_i, cos_i = Rc / r3, pz / r3
        v_R = v_r * sin_i + v_1 * cos_i
        v_T = v_2
    pm_x = v_R * c - v_T * s + p["pm_x0"]
    pm_y = v_R * s + v_T * c + p["pm_y0"]
    err = rng.uniform(0.015, 0.050, n_stars)
    pm_x = pm_x + err * rng.standard_normal(n_stars)
    pm_y = pm_y + err * rng.standard_normal(n_stars)
    R = np.hypot(px, py)
    cx, sy = px / R, py / R
    return StarSample(
        R,
        pm_x * cx + pm_y * sy,
        -pm_x * sy + pm_y * cx,
        err,
        err.copy(),
        field_radius,
        x=px,
        y=py,
    )


def draw_prior(space, rng) -> dict:
    """One parameter vector from the fit's prior (its own unit-cube transform is not used:
    uniform and Gaussian draws are made here)."""
    out = {}
    for par in space.params:
        if par.prior == "uniform":
            out[par.name] = rng.uniform(par.lo, par.hi)
        elif par.prior == "gaussian":
            out[par.name] = rng.normal(par.mean, par.sd)
        else:
            raise ValueError(f"prior {par.prior!r} of {par.name} not drawn here")
    return out


#: g / max(g) below this counts as a negative DF (the inversion's noise is ~1e-9).
DF_NEGATIVE_TOLERANCE = 1e-6


#: The truth of the nuisances a fit may hold fixed (``distance_error``, ``centre_error``,
#: ``systemic_error`` zero): the fit's own values.
FIXED_NUISANCES = dict(distance=SBC_DISTANCE, x0=0.0, y0=0.0, pm_x0=0.0, pm_y0=0.0)


def draw_truth(space, rng, velocities: str, max_redraws: int = 100, bh_mass=None):
    """A prior draw for ``velocities`` (with M_bh set to ``bh_mass`` if given; nuisances
    the space holds fixed at ``FIXED_NUISANCES``); for "df"
    redrawn (at most ``max_redraws`` times) while the DF of the draw is negative
    somewhere. Returns (truth, df tables or None, number of redraws): any redraw truncates
    the prior the fit does not know of."""
    for n in range(max_redraws + 1):
        truth = {**FIXED_NUISANCES, **draw_prior(space, rng)}
        if bh_mass is not None:
            truth["bh_mass"] = float(bh_mass)
        if velocities != "df":
            return truth, None, 0
        df = df_tables(truth)
        if df["min_g"] >= -DF_NEGATIVE_TOLERANCE:
            return truth, df, n
    raise RuntimeError(f"no prior draw with a positive DF in {max_redraws + 1} tries")


def sbc_full_trial(
    seed,
    model="imbh",
    n_stars=800,
    n_ranks=99,
    velocities="3d",
    velocity_law="line_of_sight",
    field_radius=SBC_FIELD_RADIUS,
    priors=None,
    **law_settings,
):
    """One SBC draw of the full model: the prior draw, a sample, a nested fit, the ranks.

    ``velocities`` is the law the stars are drawn from, ``velocity_law`` the one the fit
    assumes (the SBC tests the fit where they agree: "3d" with "line_of_sight",
    "projected" with "gaussian"; "df" is the equilibrium a real cluster has).
    ``priors`` (e.g. ``SBC_DF_PRIORS``) replace settings of the prior for the draw *and*
    the fit; ``law_settings`` (e.g. ``kappa_profile``) only the fit's. The truth is drawn
    from the space of the line-of-sight law (no kappa), so every law sees the same data.

    Returns
    -------
    dict
        ``seed, model, velocities, truth`` (every parameter), ``rank`` of the true M_bh
        among ``n_ranks`` posterior draws, ``ranks`` of every parameter, M_bh quantiles,
        ``df_redraws`` (prior draws rejected for a negative DF), kappa medians if fitted.
    """
    from mavispm.dynamics.evidence import run_dynesty
    from mavispm.dynamics.fit import make_likelihood, nested_chain

    priors = priors or {}
    rng = np.random.default_rng([seed, 17])
    truth_space, _ = sbc_space(model, "line_of_sight", **priors)
    space, s = sbc_space(model, velocity_law, **priors, **law_settings)
    truth, df, redraws = draw_truth(truth_space, rng, velocities)
    stars = draw_sample(truth, n_stars, rng, velocities, field_radius, df)
    like = make_likelihood(stars, space, s, SBC_DISTANCE)
    evid = run_dynesty(like, space, seed, nlive=s.nlive, dlogz=s.dlogz, walks=s.walks)
    chain = nested_chain(evid, space)
    pick = np.linspace(0, chain.samples.shape[0] - 1, n_ranks).astype(int)
    ranks = {
        n: int(np.sum(chain.samples[pick, space.index(n)] < truth[n]))
        for n in space.names
        if n in truth
    }
    bh = chain.samples[:, space.index("bh_mass")]
    q = np.percentile(bh, [2.5, 16, 50, 84, 97.5])
    kappas = {
        f"{n}_median": float(np.median(chain.samples[:, space.index(n)]))
        for n in space.names
        if n.startswith("kappa")
    }
    return {
        "seed": seed,
        "model": model,
        "velocities": velocities,
        "velocity_law": velocity_law,
        "n_stars": n_stars,
        "field_radius": field_radius,
        "df_redraws": redraws,
        "truth": {k: float(v) for k, v in truth.items()},
        "bh_true": float(truth["bh_mass"]),
        "log_z": float(evid.log_z),
        "rank": ranks["bh_mass"],
        "ranks": ranks,
        "n_ranks": n_ranks,
        **kappas,
        **{f"q{p:g}": float(v) for p, v in zip((2.5, 16, 50, 84, 97.5), q)},
    }


def null_df_trial(
    seed,
    n_stars=800,
    velocity_law="line_of_sight",
    field_radius=SBC_FIELD_RADIUS,
    priors=None,
    models=("none", "imbh"),
    **law_settings,
):
    """A null draw (M_bh = 0, every other parameter from the prior, no dark component)
    with DF velocities, fitted with ``models`` (default ``none`` and ``imbh``; the stage's
    four add ``dark`` and ``imbh_dark``) by the stage's own ``fit_models`` and ``compare``
    (nested evidences, no separate kinematic evidence): ln B and verdict."""
    from mavispm.dynamics.fit import compare, fit_models
    from mavispm.dynamics.settings import DynamicsSettings

    priors = priors or {}
    rng = np.random.default_rng([seed, 17])
    truth_space, _ = sbc_space("imbh", "line_of_sight", **priors)
    truth, df, redraws = draw_truth(truth_space, rng, "df", bh_mass=0.0)
    stars = draw_sample(truth, n_stars, rng, "df", field_radius, df)
    kw = {**SBC_FULL_SETTINGS, **priors, **law_settings}
    s = DynamicsSettings(
        **kw,
        models=tuple(models),
        velocity_law=velocity_law,
        evidence=True,
        kinematic_evidence=False,
    )
    fits = fit_models(stars, s, SBC_DISTANCE, seed)
    c = compare(fits, s.bh_mass_max)
    return {
        "seed": seed,
        "velocity_law": velocity_law,
        "n_stars": n_stars,
        "field_radius": field_radius,
        "df_redraws": redraws,
        "truth": {k: float(v) for k, v in truth.items()},
        "models": list(models),
        "ln_b": float(c.ln_bayes_factor),
        "ln_b_err": float(c.ln_bayes_factor_err),
        "verdict": c.verdict,
        "log_z": {f.name: float(f.evidence.log_z) for f in fits},
    }


def surface_density(p: dict, X: np.ndarray, n_t: int = 4000):
    """Projected tracer density [per unit (R / a)^2, unit total number] at X = R / a."""
    x, nu, _, _ = model_tables(p)
    t, r = _line_of_sight(X, x[-1], n_t)
    return 2.0 * trapezoid(np.exp(np.interp(np.log(r), np.log(x), np.log(nu))) * r, t, axis=1)


def _about_centre(p: dict, stars):
    """Projected radius [arcsec], radial / tangential motions [mas/yr] and squared errors of
    ``stars`` about the model centre and systemic motion of ``p`` (the errors, given about
    the field centre, rotated to the model centre's directions)."""
    dx, dy = stars.x - p["x0"], stars.y - p["y0"]
    R = np.hypot(dx, dy)
    c, s = dx / R, dy / R
    cx, sy = stars.x / stars.R, stars.y / stars.R
    pm_x = stars.v_r * cx - stars.v_t * sy - p["pm_x0"]
    pm_y = stars.v_r * sy + stars.v_t * cx - p["pm_y0"]
    cos2 = (cx * c + sy * s) ** 2
    e2_R = stars.e_r**2 * cos2 + stars.e_t**2 * (1.0 - cos2)
    e2_T = stars.e_r**2 * (1.0 - cos2) + stars.e_t**2 * cos2
    return R, pm_x * c + pm_y * s, -pm_x * s + pm_y * c, e2_R, e2_T


def independent_ln_likelihood(p: dict, stars, n_r: int = 3000, n_phi: int = 1440):
    """ln L of ``stars`` under parameters ``p``: the Gaussian proper-motion terms with the
    projected dispersions above and the star counts ln[Sigma(R_i) / N_field], N_field a
    midpoint sum over the field disc (``n_r`` x ``n_phi`` cells). Returns (kinematic,
    star-count) parts."""
    a = 10.0 ** p["log_scale_radius"]
    R, v_R, v_T, e2_R, e2_T = _about_centre(p, stars)
    kin = 0.0
    for vi, s2, e2 in zip((v_R, v_T), projected_dispersions(p, R / a), (e2_R, e2_T)):
        var = s2 + e2
        kin -= 0.5 * np.sum(vi * vi / var + np.log(2.0 * np.pi * var))
    rr = (np.arange(n_r) + 0.5) * stars.field_radius / n_r
    ph = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    RR, PP = np.meshgrid(rr, ph, indexing="ij")
    Rc = np.hypot(RR * np.cos(PP) - p["x0"], RR * np.sin(PP) - p["y0"]) / a
    Xs = np.geomspace(Rc.min(), Rc.max(), 400)
    sig = np.exp(np.interp(np.log(Rc), np.log(Xs), np.log(surface_density(p, Xs))))
    n_field = np.sum(sig * RR) * (stars.field_radius / n_r) * (2.0 * np.pi / n_phi) / a**2
    counts = np.sum(np.log(surface_density(p, R / a) / a**2 / n_field))
    return kin, counts


def independent_line_of_sight_ln_likelihood(p: dict, stars, n_t: int = 4000):
    """Kinematic ln L of ``stars`` under parameters ``p`` with the line-of-sight mixture:
    each star's density is the trapezoid sum over ``n_t`` depths (``x = X cosh t`` out to
    the end of ``LN_X``) of the tracer-weighted product of Gaussians with the sky-radial and
    sky-tangential dispersions at that depth, convolved with the errors."""
    from scipy.special import logsumexp

    x, nu, _, nu_s2 = model_tables(p)
    a = 10.0 ** p["log_scale_radius"]
    R, v_R, v_T, e2_R, e2_T = _about_centre(p, stars)
    t, r = _line_of_sight(R / a, x[-1], n_t)
    lx, lr = np.log(x), np.log(r)
    ln_w = np.interp(lr, lx, np.log(nu)) + np.log(r)  # nu dz / dt = nu x
    ln_w[:, [0, -1]] += np.log(0.5)  # trapezoid ends (uniform t per star)
    s2 = _dispersion_unit(p) * np.exp(np.interp(lr, lx, np.log(nu_s2) - np.log(nu)))
    beta = anisotropy_at(p, r)
    var_R = s2 * ((1.0 - beta) + beta / np.cosh(t) ** 2) + e2_R[:, None]
    var_T = (1.0 - beta) * s2 + e2_T[:, None]
    ln_g = -0.5 * (v_R[:, None] ** 2 / var_R + v_T[:, None] ** 2 / var_T + np.log(var_R * var_T))
    ln_p = logsumexp(ln_w + ln_g, axis=1) - logsumexp(ln_w, axis=1) - np.log(2.0 * np.pi)
    return float(np.sum(ln_p))
