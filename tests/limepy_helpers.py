"""NGC 3201-like LIMEPY models (Gieles & Zocchi 2015) and their DF samples as
``propermotions`` products: data from an independent model and sampler.

The ``astro-limepy`` package (PyPI name; the PyPI ``limepy`` is an unrelated
LimeSurvey tool) builds multi-mass, anisotropic lowered isothermal models and
samples positions and velocities from their distribution function
(``limepy.sample``). These models have no central point mass: they are no-IMBH
truths whose dark remnants (white dwarfs, neutron stars, a 5 Msun "black hole"
bin) are mass-segregated into the centre (``delta = 0.5``).

Version 1.3.0 does not run on scipy >= 1.17 as shipped (``ode.set_integrator``
gets ``nsteps=1e6``, a float, and scipy's dopri5 passes ``set_f_params`` on to the
``solout`` callback too); :func:`import_limepy` wraps ``scipy.integrate.ode`` inside
``limepy.limepy`` so that both work (the ODE solved is unchanged).
"""

from __future__ import annotations

import functools
import sys

import numpy as np

#: Harris (1996, 2010 edition) / Baumgardt & Vasiliev (2021) NGC 3201: core and
#: half-light radius [arcmin], distance [kpc], mass [Msun].
NGC3201 = {"rc_arcmin": 1.30, "rh_arcmin": 3.10, "distance": 4.74, "mass": 1.6e5}

#: Mass function [Msun] and mass fractions: main sequence 0.15, 0.35; 0.6 (main
#: sequence + white dwarfs, of which LUMINOUS_FRACTION_06 is luminous); 0.8 (turn-off
#: and giants, luminous); 1.0 (massive white dwarfs), 1.4 (neutron stars), 5.0 (a
#: black-hole-like dark bin: limepy's mass-function iteration did not converge with
#: 10 Msun). The last fraction is the model's ``bh_fraction``; all are normalised.
MASSES = (0.15, 0.35, 0.6, 0.8, 1.0, 1.4, 5.0)
FRACTIONS = (0.18, 0.20, 0.37, 0.11, 0.10, 0.02)
LUMINOUS_FRACTION_06 = 0.17 / 0.37
TRACER_BINS = (2, 3)
#: The models (``delta = 0.5``, ``g = 1``): W0, mass fraction of the 5 Msun bin, ``ra``
#: in model units (r0; 1e8: isotropic). Measured on the built models (0.8 Msun bin):
#: isotropic Rc/Rhp 0.51, radial 0.45 with beta 0.29 at r_h, 0.55 at 2 r_h
#: (Harris: 1.3' / 3.1' = 0.42); bh_subsystem Rc = 1.44', Rc/Rhp 0.47, 566 Msun of the
#: 5 Msun bin inside 15" (the mass-follows-light mass there: 168 Msun). limepy did not
#: converge for anisotropic models with bh_fraction 0.01 (W0 3-5, ra 3-20).
MODELS = {
    "isotropic": {"W0": 3.0, "bh_fraction": 0.005, "ra": 1.0e8},
    "radial": {"W0": 3.0, "bh_fraction": 0.005, "ra": 3.0},
    "bh_subsystem": {"W0": 5.0, "bh_fraction": 0.01, "ra": 1.0e8},
}

G = 4.300917270e-3  # pc (km/s)^2 / Msun
KMS = 4.740470463533348  # km/s per mas/yr per kpc
PC_PER_ARCSEC_KPC = 1e3 * np.pi / 648000.0


def import_limepy():
    """The ``limepy`` module of ``astro-limepy`` (a ``[test]`` dependency: a missing or
    wrong package fails the test with one line), made to run on the installed scipy."""
    try:
        import limepy
    except ImportError as exc:
        raise ImportError(
            "astro-limepy is missing: install the test extras (pip install -e '.[test]')"
        ) from exc
    if not hasattr(limepy, "sample"):
        raise ImportError(
            "the installed 'limepy' is not astro-limepy (Gieles & Zocchi): "
            "pip uninstall limepy && pip install astro-limepy"
        )
    from scipy.integrate import ode

    module = sys.modules["limepy.limepy"]
    if not getattr(module.ode, "_mavispm_wrapped", False):

        class _Ode(ode):
            _mavispm_wrapped = True

            def set_integrator(self, name, **params):
                if "nsteps" in params:
                    params["nsteps"] = int(params["nsteps"])
                return super().set_integrator(name, **params)

            def set_f_params(self, *args):
                f = self.__dict__.setdefault("_f_plain", self.f)
                self.f = lambda t, y: f(t, y, *args)
                return self

        module.ode = _Ode
    return limepy


def _model(lp, rh, W0, bh_fraction, ra, multi):
    mass = NGC3201["mass"]
    if not multi:
        return lp.limepy(W0, 1.0, M=mass, rh=rh, ra=ra, project=True)
    fr = np.array([*FRACTIONS, bh_fraction])
    return lp.limepy(
        W0,
        1.0,
        M=mass,
        rh=rh,
        ra=ra,
        mj=np.asarray(MASSES),
        Mj=fr / fr.sum() * mass,
        delta=0.5,
        project=True,
        max_mf_iter=400,
    )


@functools.lru_cache(maxsize=4)
def ngc3201_model(name="isotropic", multi=True):
    """The NGC 3201-like LIMEPY model ``name`` (:data:`MODELS`) in physical units (pc,
    km/s, Msun): the 3-D scale is set so that the 0.8 Msun bin's projected half-number
    radius (single mass: the projected half-mass radius) is Harris's half-light radius."""
    lp = import_limepy()
    p = MODELS[name]
    target = NGC3201["rh_arcmin"] * 60 * NGC3201["distance"] * PC_PER_ARCSEC_KPC
    unit = _model(lp, 1.0, p["W0"], p["bh_fraction"], p["ra"], multi)
    rh = target / (unit.rhpj[3] if multi else unit.rhp)
    return _model(lp, rh, p["W0"], p["bh_fraction"], p["ra"], multi)


#: The NGC 3201 workflow's field: 30" x 30", pointed 0.5" off the cluster's centre.
FIELD_HALF = 15.0  # arcsec
FIELD_OFFSET = (0.4, -0.3)  # arcsec, field centre relative to the cluster centre


def sample_tracers(model, seed, n_samples=4):
    """Luminous tracer stars of ``n_samples`` independent ``limepy.sample`` draws
    (each the whole cluster, ~4.3e5 stars) inside the 30" x 30" field.

    Returns a dict of field positions ``x, y`` [arcsec] (field centre at 0), true
    proper motions ``pm_x, pm_y`` [mas/yr] and ``mass`` [Msun].
    """
    lp = import_limepy()
    scale = NGC3201["distance"] * PC_PER_ARCSEC_KPC  # pc per arcsec
    conv = KMS * NGC3201["distance"]  # km/s per mas/yr
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("x", "y", "pm_x", "pm_y", "mass")}
    for i in range(n_samples):
        s = lp.sample(model, seed=int(1000 * seed + i), verbose=False)
        keep = np.zeros(s.N, bool)
        for j in TRACER_BINS:
            sl = slice(s.Nstart[j], s.Nend[j])
            luminous = rng.random(s.Nend[j] - s.Nstart[j])
            keep[sl] = luminous < (LUMINOUS_FRACTION_06 if MASSES[j] == 0.6 else 1.0)
        x = s.x / scale - FIELD_OFFSET[0]
        y = s.y / scale - FIELD_OFFSET[1]
        keep &= (np.abs(x) <= FIELD_HALF) & (np.abs(y) <= FIELD_HALF)
        out["x"].append(x[keep])
        out["y"].append(y[keep])
        out["pm_x"].append(s.vx[keep] / conv)
        out["pm_y"].append(s.vy[keep] / conv)
        out["mass"].append(s.m[keep])
    return {k: np.concatenate(v) for k, v in out.items()}


def write_propermotions(path, stars, seed, err_lo=0.010, err_hi=0.020):
    """A ``propermotions`` product of ``stars`` (:func:`sample_tracers`) with per-star
    Gaussian PM errors uniform in [err_lo, err_hi] mas/yr (the measured products'
    bright-star errors); the distance attribute is NGC 3201's literature distance."""
    import astropy.units as u
    from dynamics_helpers import write_noisy_propermotions

    n = stars["x"].size
    return write_noisy_propermotions(
        path,
        np.arange(n, dtype=np.int64),
        stars["x"],
        stars["y"],
        np.stack([stars["pm_x"], stars["pm_y"]]),
        (20.0 - 5.0 * np.log10(stars["mass"] / 0.8)) * u.mag,
        NGC3201["distance"] * u.kpc,
        seed,
        err_lo,
        err_hi,
    )


def workflow_dynamics_settings(**overrides):
    """The shipped NGC 3201 workflow's ``[dynamics]`` table (literature priors, nested
    posterior), with the completeness flat: every star of the sample is in it."""
    import tomllib
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "workflows" / "ngc3201_imbh.toml"
    settings = tomllib.loads(path.read_text())["dynamics"]
    settings["completeness_source"] = "table"
    settings.update(overrides)
    return settings
