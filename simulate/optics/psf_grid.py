"""Field grid of high-order PSFs: computation, bilinear interpolation and disk cache.

The grid holds normalised PSF stamps at an oversampled pixel scale on a
regular grid of field positions (default 11 x 11 over 30" x 30"). Modes:

``fourier``      field-variable Fourier MCAO PSFs (the default);
``static``       one Fourier PSF (at ``static_position``) used everywhere;
``diffraction``  the diffraction-limited PSF of the pupil (no AO residual);
``file``         PSFs read from a MAVISIM-format FITS database.

Computed grids are cached on disk under a key hashed from every parameter
that changes them, so a scene never recomputes an unchanged grid.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import astropy.units as u
import numpy as np

from mavispm.core.array_cache import is_immutable
from mavispm.core.config import unit_field
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import open_product, write_product
from mavispm.simulate.optics import ao_psd, cone_effect
from mavispm.simulate.optics.ao_psd import AOSettings
from mavispm.simulate.optics.atmosphere import (
    ARCSEC_PER_RAD,
    AtmosphereSettings,
    airmass,
    fried_parameter,
    layers,
    von_karman_variance_beyond,
)
from mavispm.simulate.optics.fourier_psf import (
    fourier_sampling,
    psf_from_otf,
    strehl_ratio,
    structure_function,
    telescope_otf,
)
from mavispm.simulate.optics.pupil import PupilSettings

__all__ = [
    "ALGORITHM_VERSION",
    "ConeGeometry",
    "GridResult",
    "PSFGrid",
    "PSFSettings",
    "ResidualPSDModel",
    "cached_grid",
    "compute_fourier_grid",
    "compute_grid",
    "default_cache_dir",
    "grid_key",
    "radial_average",
    "read_grid",
    "residual_psd_model",
    "write_grid",
]

#: bump when the algorithm changes so stale cache entries are not reused
ALGORITHM_VERSION = 5  # 2: LGS cone effect, weighted fitting directions, LGS position angle
# 3: servo-lag temporal frequency sign (nu = -f.v), Thomas 2 ln 2 LGS noise, P3 conventions
# 4: cone-effect residual without its pupil piston and tilt (cone_remove_tilt)
# 5: multi-LGS cone power from the extrapolation (kriging) variance (cone_model)


@dataclass(frozen=True)
class PSFSettings:
    """High-order PSF grid (TOML table ``[scene.optics.psf]``).

    Parameters
    ----------
    mode : {"fourier", "static", "diffraction", "file"}
        How PSFs are made (see module docstring).
    wavelength : float
        Monochromatic wavelength (nm).
    pixel_scale : float
        PSF pixel (mas); at most Nyquist lambda / 2D. Default 7.5 / 4.
    stamp_size : float
        Width of the PSF stamps (arcsec); holds the control radius and first halo.
    n_nodes : int
        Grid nodes per axis.
    field_size : float
        Full width of the square field covered by the nodes (arcsec).
    pupil_sampling : int
        Pupil-plane samples across D (accuracy knob: sets the PSD extent).
    psd_padding : float
        PSD grid period in units of D (accuracy knob: low-frequency sampling).
    static_position : tuple of float
        Field position (arcsec) of the PSF used in ``static`` mode.
    chunk : int
        Directions whose PSDs are computed together (memory knob).
    file : str or None
        MAVISIM PSF FITS database for ``file`` mode.
    file_pixel_scale : float or None
        Pixel scale of that file (mas) when its headers do not give it.
    file_pixel_unit : {"mas", "arcsec", "deg"}
        Unit of a header pixel scale (PIXSCALE / PIXSIZE) whose header does not
        state one (PIXUNIT, CUNIT1 or the card comment).
    """

    mode: Literal["fourier", "static", "diffraction", "file"] = "fourier"
    wavelength: float = unit_field(550.0, "nm", "monochromatic wavelength")
    pixel_scale: float = unit_field(1.875, "mas", "PSF pixel scale")
    stamp_size: float = unit_field(0.8, "arcsec", "PSF stamp width")
    n_nodes: int = 11
    field_size: float = unit_field(30.0, "arcsec", "field covered by the grid")
    pupil_sampling: int = 128
    psd_padding: float = 4.0
    static_position: tuple[float, float] = (0.0, 0.0)
    chunk: int = 8
    file: str | None = None
    file_pixel_scale: float | None = unit_field(None, "mas", "pixel scale of the PSF file")
    file_pixel_unit: Literal["mas", "arcsec", "deg"] = "mas"

    def __post_init__(self):
        if not 300 <= self.wavelength <= 3000:
            raise ValueError(f"wavelength must be in [300, 3000] nm, got {self.wavelength}")
        if not self.pixel_scale > 0:
            raise ValueError(f"pixel_scale must be > 0 mas, got {self.pixel_scale}")
        if not self.stamp_size * 1000 >= 5 * self.pixel_scale:
            raise ValueError("stamp_size must hold at least 5 pixels")
        if self.n_nodes < 1:
            raise ValueError(f"n_nodes must be >= 1, got {self.n_nodes}")
        if self.field_size < 0:
            raise ValueError("field_size must be >= 0 arcsec")
        if self.pupil_sampling < 16:
            raise ValueError(f"pupil_sampling must be >= 16, got {self.pupil_sampling}")
        if self.psd_padding < 2:
            raise ValueError(f"psd_padding must be >= 2 (OTF wrap), got {self.psd_padding}")
        if self.chunk < 1:
            raise ValueError("chunk must be >= 1")
        if self.mode == "file" and not self.file:
            raise ValueError("psf.mode = 'file' needs psf.file (a MAVISIM PSF FITS database)")

    def node_positions(self) -> np.ndarray:
        """Node coordinates along one axis (arcsec)."""
        if self.n_nodes == 1:
            return np.zeros(1)
        return np.linspace(-self.field_size / 2, self.field_size / 2, self.n_nodes)


@dataclass(frozen=True, eq=False)
class PSFGrid:
    """A grid of normalised PSF stamps with bilinear interpolation.

    Parameters
    ----------
    cube : ndarray, shape (ny, nx, n, n)
        PSFs, each summing to 1, n odd, optical axis at pixel ((n-1)/2, (n-1)/2).
    nodes_x, nodes_y : ndarray
        Node positions (arcsec, field frame), increasing.
    pixel_scale : float
        Stamp pixel (mas).
    wavelength : float
        Wavelength (nm).
    strehl : ndarray, shape (ny, nx)
        Strehl ratio of each node PSF (NaN when unknown).

    Attributes
    ----------
    cube_key : str or None
        A key of ``cube``'s content known from where it came from (the name of the
        keyed cache file it is mapped read-only from; see :meth:`with_cube_key`), so
        that caches built on the cube can be keyed without hashing its bytes. None
        unless set; not an ``__init__`` argument, so ``dataclasses.replace`` (e.g.
        with another cube) drops it.
    """

    cube: np.ndarray
    nodes_x: np.ndarray
    nodes_y: np.ndarray
    pixel_scale: float
    wavelength: float
    strehl: np.ndarray
    cube_key: str | None = field(default=None, init=False, repr=False, compare=False)

    def with_cube_key(self, key: str) -> PSFGrid:
        """This grid with ``cube_key = key``, where the cube's memory cannot be written.

        Only a cube mapped read-only from a file (whose name ``key`` is a key of its
        content) can carry a key: for any other cube (one that owns its memory, views
        writable memory, or could be made writable again) the grid is returned
        unchanged, without a key, and its users hash the bytes.

        Parameters
        ----------
        key : str
            A key of the cube's content (dtype and shape are not part of it).

        Returns
        -------
        PSFGrid
        """
        if not is_immutable(self.cube):
            return self
        keyed = replace(self)
        object.__setattr__(keyed, "cube_key", str(key))
        return keyed

    @property
    def is_static(self) -> bool:
        """True for a single PSF used everywhere."""
        return self.cube.shape[:2] == (1, 1)

    @property
    def n(self) -> int:
        """Stamp size (pixels)."""
        return self.cube.shape[-1]

    def bilinear_weights(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Node indices and bilinear weights for field positions.

        Parameters
        ----------
        x, y : array_like, shape (N,)
            Field positions (arcsec); clipped to the grid edges.

        Returns
        -------
        iy, ix : ndarray of int, shape (N, 4)
        w : ndarray, shape (N, 4)
            Non-negative, summing to 1; exact (a single weight 1) at nodes.
        """
        ix0, tx = _axis_weights(self.nodes_x, np.atleast_1d(np.asarray(x, float)))
        iy0, ty = _axis_weights(self.nodes_y, np.atleast_1d(np.asarray(y, float)))
        ix1 = np.minimum(ix0 + 1, self.nodes_x.size - 1)
        iy1 = np.minimum(iy0 + 1, self.nodes_y.size - 1)
        iy = np.stack([iy0, iy0, iy1, iy1], axis=-1)
        ix = np.stack([ix0, ix1, ix0, ix1], axis=-1)
        w = np.stack([(1 - ty) * (1 - tx), (1 - ty) * tx, ty * (1 - tx), ty * tx], axis=-1)
        return iy, ix, w

    def psf_at(self, x: float, y: float) -> np.ndarray:
        """Bilinearly interpolated PSF (n, n) at field position (x, y) arcsec; sums to 1.

        Parameters
        ----------
        x, y : float
            Field position [arcsec] (clipped to the grid edges).

        Returns
        -------
        ndarray, shape (n, n)
            The PSF stamp (pixels of ``pixel_scale`` mas).
        """
        iy, ix, w = self.bilinear_weights([x], [y])
        psf = np.tensordot(w[0], self.cube[iy[0], ix[0]], axes=1)
        return psf / psf.sum()


def _axis_weights(nodes: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if not np.all(np.isfinite(x)):
        raise ValueError("field positions must be finite")
    if nodes.size == 1:
        return np.zeros(x.shape, int), np.zeros(x.shape)
    i0 = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
    t = np.clip((x - nodes[i0]) / (nodes[i0 + 1] - nodes[i0]), 0.0, 1.0)
    return i0, t


@dataclass(frozen=True)
class GridResult:
    """A computed grid plus what the halo needs.

    Parameters
    ----------
    grid : PSFGrid
    psd_frequency : ndarray
        Radial frequencies (m^-1) of the on-axis azimuthally averaged PSD.
    psd_profile : ndarray
        That PSD (rad^2 m^2); empty for ``file`` mode.
    """

    grid: PSFGrid
    psd_frequency: np.ndarray
    psd_profile: np.ndarray


def grid_key(psf: PSFSettings, pupil, atmosphere, ao) -> str:
    """Hash of every parameter that changes the grid (cache key).

    Parameters
    ----------
    psf : PSFSettings
        PSF settings (``chunk``, which only sets memory use, is left out).
    pupil : PupilSettings
        Pupil settings.
    atmosphere : AtmosphereSettings
        Atmosphere settings.
    ao : AOSettings
        AO settings.

    Returns
    -------
    str
        Hexadecimal key (includes the algorithm version and, in ``file`` mode, the file's
        size and modification time).
    """
    payload = {
        "version": ALGORITHM_VERSION,
        "psf": {k: v for k, v in asdict(psf).items() if k != "chunk"},
        "pupil": asdict(pupil),
        "atmosphere": asdict(atmosphere),
        "ao": asdict(ao),
    }
    if psf.mode == "file" and psf.file:
        st = Path(psf.file).stat() if Path(psf.file).exists() else None
        payload["file_stat"] = [st.st_size, st.st_mtime_ns] if st else None
    text = json.dumps(payload, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def default_cache_dir() -> Path:
    """$MAVISPM_CACHE or ~/.cache/mavispm."""
    env = os.environ.get("MAVISPM_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "mavispm"


def radial_average(fx, fy, psd, df) -> tuple[np.ndarray, np.ndarray]:
    """Azimuthal average of a centred 2-D PSD in rings of width df.

    Parameters
    ----------
    fx, fy : ndarray
        Spatial frequencies [1/m].
    psd : ndarray
        The PSD on the same grid (any unit; the profile shares it).
    df : float
        Ring width [1/m].

    Returns
    -------
    f : ndarray
        Ring radii [1/m] (non-empty rings only).
    profile : ndarray
        Mean PSD per ring.
    """
    r = np.hypot(fx, fy).ravel()
    idx = np.floor(r / df + 0.5).astype(int)
    n = idx.max() + 1
    s = np.bincount(idx, weights=psd.ravel(), minlength=n)
    c = np.bincount(idx, minlength=n)
    ok = c > 0
    return np.arange(n)[ok] * df, s[ok] / c[ok]


@dataclass(frozen=True)
class ConeGeometry:
    """What the cone effect needs.

    Parameters
    ----------
    lgs_directions : ndarray, shape (G, 2)
        LGS directions [rad].
    lgs_range : float
        LGS range along the line of sight [m].
    diameter : float
        Pupil diameter [m].
    obscuration : float
        Central obstruction ratio (dimensionless).
    remove_tilt : bool
        Leave the residual's pupil piston and tilt out (``AOSettings.cone_remove_tilt``).
    model : {"kriging", "gap"}
        ``AOSettings.cone_model``.
    r0, outer_scale : float
        Fried parameter of the whole atmosphere at the science wavelength and outer
        scale [m] (for the kriging variance).
    weights : ndarray, shape (L,)
        Cn^2 fractions of the layers.
    """

    lgs_directions: np.ndarray
    lgs_range: float
    diameter: float
    obscuration: float
    remove_tilt: bool = True
    model: str = "kriging"
    r0: float = 0.1
    outer_scale: float = 25.0
    weights: np.ndarray | None = None

    def __post_init__(self):
        if self.model not in ("kriging", "gap"):
            raise ValueError(f"ConeGeometry.model: expected 'kriging' or 'gap', got {self.model!r}")
        if self.model == "kriging" and self.weights is None:
            raise ValueError(
                "ConeGeometry.weights: the kriging model needs the layers' Cn^2 weights"
            )


@dataclass
class ResidualPSDModel:
    """The residual PSD of one configuration on the PSD grid.

    The direction-independent parts (fitting, aliasing) are stored once; the
    servo-lag, tomography and noise parts come per direction from the
    tomographic operator on the control-region frequencies ``sel``.

    Parameters
    ----------
    sampling : FourierSampling
    fx, fy : ndarray
        Centred frequency grid (m^-1).
    fitting, aliasing : ndarray
        Direction-independent PSDs (rad^2 m^2).
    sel : ndarray of bool
        Control-region frequencies except zero.
    operator : TomographicOperator or None
        None for a zero residual.
    hf_variance : float
        Fitting variance beyond the PSD grid (rad^2).
    wavelength : float
        (m)
    cone : ConeGeometry or None
        LGS geometry for the cone effect; None when it is off.
    """

    sampling: object
    fx: np.ndarray
    fy: np.ndarray
    fitting: np.ndarray
    aliasing: np.ndarray
    sel: np.ndarray
    operator: object
    hf_variance: float
    wavelength: float
    cone: ConeGeometry | None = None
    _cone_cache: dict = field(default_factory=dict, repr=False)

    def cone_psd(self, direction: np.ndarray) -> np.ndarray:
        """Cone-effect PSD on the control-region frequencies ``sel`` for one direction (rad).

        Parameters
        ----------
        direction : ndarray, shape (2,)
            Science direction [rad].

        Returns
        -------
        ndarray
            PSD [rad^2 m^2] on the control-region frequencies; zeros without cone geometry.
        """
        if self.cone is None or self.operator is None:
            return np.zeros(int(self.sel.sum()))
        c = self.cone
        f = np.hypot(self.operator.fx, self.operator.fy)
        if c.model == "gap":
            gaps, area = cone_effect.footprint_coverage(
                direction, c.lgs_directions, self.operator.layer_heights, c.lgs_range, c.diameter
            )
            return cone_effect.cone_psd(
                f, self.operator.turbulence, gaps, area, c.diameter, c.obscuration, c.remove_tilt
            )
        # the error spectrum is the same for every direction of a symmetry orbit of the
        # asterism: computed once per orbit on a radial grid, interpolated to |f|
        cache = self._cone_cache
        if "symmetries" not in cache:
            cache["symmetries"] = cone_effect.asterism_symmetries(c.lgs_directions)
            radii, inverse = np.unique(f, return_inverse=True)
            cache["radii"] = (radii, inverse.ravel(), np.linspace(0.0, radii.max(), 256))
        radii, inverse, fq = cache["radii"]
        key = cone_effect.canonical_direction(direction, cache["symmetries"])
        if key not in cache:
            heights = self.operator.layer_heights
            gaps, _ = cone_effect.footprint_coverage(
                np.asarray(key), c.lgs_directions, heights, c.lgs_range, c.diameter
            )
            seen = gaps > 0
            spectrum = np.zeros(fq.size)
            if seen.any():
                variance, spec = cone_effect.extrapolation_spectrum(
                    np.asarray(key),
                    c.lgs_directions,
                    heights[seen],
                    c.lgs_range,
                    c.diameter,
                    c.obscuration,
                    c.r0,
                    c.outer_scale,
                    fq,
                    c.remove_tilt,
                )
                spectrum = c.weights[seen] @ spec  # rad^2 m^2 of the whole atmosphere
            cache[key] = spectrum
        return np.interp(radii, fq, cache[key])[inverse]

    def psds(self, directions: np.ndarray, chunk: int):
        """Yield the full PSD for each direction (rad), computing ``chunk`` at a time.

        Parameters
        ----------
        directions : ndarray, shape (K, 2)
            Science directions [rad].
        chunk : int
            Directions whose correction residual is computed at once.

        Yields
        ------
        ndarray
            Residual phase PSD [rad^2 m^2] of one direction: fitting, aliasing, and on the
            control region the correction residual and the cone effect.
        """
        base = self.fitting + self.aliasing
        for start in range(0, directions.shape[0], chunk):
            part = directions[start : start + chunk]
            res = (
                ao_psd.correction_residual_psd(self.operator, part)
                if self.operator is not None
                else None
            )
            for j in range(part.shape[0]):
                psd = base.copy()
                if res is not None:
                    psd[self.sel] += res[j] + self.cone_psd(part[j])
                yield psd

    def budget(self, position_arcsec=(0.0, 0.0)) -> dict[str, float]:
        """RMS wavefront error (nm) of each term in one direction.

        Parameters
        ----------
        position_arcsec : tuple of float
            Field position [arcsec].

        Returns
        -------
        dict of str to float
            ``fitting``, ``aliasing``, ``servo_tomography``, ``noise``, ``cone`` and their
            quadrature sum ``total`` [nm].
        """
        df2 = self.sampling.df**2
        to_nm = self.wavelength * 1e9 / (2 * np.pi)
        out = {
            "fitting": np.sqrt(self.fitting.sum() * df2 + self.hf_variance) * to_nm,
            "aliasing": np.sqrt(self.aliasing.sum() * df2) * to_nm,
            "servo_tomography": 0.0,
            "noise": 0.0,
            "cone": 0.0,
        }
        if self.operator is not None:
            d = np.asarray([position_arcsec], float) / ARCSEC_PER_RAD
            corr, noise = ao_psd.correction_residual_psd(self.operator, d, split=True)
            out["servo_tomography"] = np.sqrt(corr.sum() * df2) * to_nm
            out["noise"] = np.sqrt(noise.sum() * df2) * to_nm
            out["cone"] = np.sqrt(self.cone_psd(d[0]).sum() * df2) * to_nm
        out["total"] = float(np.sqrt(sum(v**2 for v in out.values())))
        return {k: float(v) for k, v in out.items()}


def residual_psd_model(
    psf: PSFSettings,
    pupil: PupilSettings,
    atmosphere: AtmosphereSettings,
    ao: AOSettings,
    residual: bool = True,
) -> ResidualPSDModel:
    """Set up the PSD grid and the direction-independent terms.

    Parameters
    ----------
    psf : PSFSettings
        Wavelength [nm], pixel scale [mas], stamp size and pupil sampling.
    pupil : PupilSettings
        Pupil geometry.
    atmosphere : AtmosphereSettings
        Turbulence profile and seeing.
    ao : AOSettings
        AO system.
    residual : bool
        Include the AO residual terms the settings switch on (fitting, aliasing,
        tomography, servo, noise, cone); False: none (the diffraction-limited PSF).

    Returns
    -------
    ResidualPSDModel
        The PSD model.

    Raises
    ------
    ConfigError
        If the PSF pixel is coarser than Nyquist.
    """
    lam = psf.wavelength * 1e-9
    try:
        smp = fourier_sampling(
            lam,
            psf.pixel_scale,
            pupil.diameter,
            psf.pupil_sampling,
            psf.psd_padding,
            psf.stamp_size * 1000,
        )
    except ValueError as exc:
        raise ConfigError(str(exc), key="scene.optics.psf.pixel_scale") from None
    fx, fy = smp.frequencies()
    r0 = fried_parameter(atmosphere, lam)
    l0 = atmosphere.outer_scale
    d = ao.pitch(pupil.diameter)
    fc = ao.control_frequency(pupil.diameter)
    fitting = np.zeros_like(fx)
    aliasing = np.zeros_like(fx)
    hf_var = 0.0
    inside = ao_psd.control_mask(fx, fy, fc, ao.control_region)
    sel = inside & ((fx != 0) | (fy != 0))
    op = None
    cone = None
    if residual:
        if ao.fitting:
            fitting = ao_psd.fitting_psd(fx, fy, fc, r0, l0, ao.control_region)
            f_eq = smp.f_max * 2 / np.sqrt(np.pi)  # circle with the PSD grid's area
            hf_var = von_karman_variance_beyond(f_eq, r0, l0)
        if ao.aliasing:
            # aliased high frequencies reach the DMs through the loop at their own
            # temporal frequencies (frozen flow of each layer)
            gain = ao_psd.aliasing_temporal_gain(ao, layers(atmosphere))
            aliasing[inside] = ao_psd.aliasing_psd(fx[inside], fy[inside], d, r0, l0, temporal=gain)
        fxs, fys = fx[sel], fy[sel]
        r0_wfs = fried_parameter(atmosphere, ao.lgs_wavelength * 1e-9)
        sigma_nm = ao_psd.shack_hartmann_noise(ao, d, r0_wfs)
        sigma_rad = 2 * np.pi * sigma_nm * 1e-9 / lam
        noise = ao_psd.noise_psd(fxs, fys, d, sigma_rad) if ao.noise else np.zeros_like(fxs)
        op = ao_psd.tomographic_operator(
            fxs, fys, ao, layers(atmosphere), r0, l0, noise, ao.lgs_height * airmass(atmosphere)
        )
        if ao.cone_effect:
            cone = ConeGeometry(
                lgs_directions=ao_psd.lgs_directions(ao),
                lgs_range=ao.lgs_height * airmass(atmosphere),
                diameter=pupil.diameter,
                obscuration=pupil.obscuration_ratio,
                remove_tilt=ao.cone_remove_tilt,
                model=ao.cone_model,
                r0=r0,
                outer_scale=l0,
                weights=layers(atmosphere).weights,
            )
    return ResidualPSDModel(smp, fx, fy, fitting, aliasing, sel, op, hf_var, lam, cone)


def compute_fourier_grid(
    psf: PSFSettings,
    pupil: PupilSettings,
    atmosphere: AtmosphereSettings,
    ao: AOSettings,
    positions: np.ndarray,
    progress: bool = True,
    residual: bool = True,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray], float]:
    """Fourier MCAO PSFs at field positions.

    Parameters
    ----------
    psf : PSFSettings
        Wavelength, pixel scale, stamp size and the sampling knobs.
    pupil : PupilSettings
        Pupil geometry.
    atmosphere : AtmosphereSettings
        Turbulence profile and seeing.
    ao : AOSettings
        AO system.
    positions : ndarray, shape (K, 2)
        Field positions (arcsec).
    progress : bool
        Progress bar (on a terminal only).
    residual : bool
        False gives the diffraction-limited PSF (zero residual PSD).

    Returns
    -------
    psfs : ndarray, shape (K, n, n)
    strehl : ndarray, shape (K,)
        Strehl ratio including the variance beyond the PSD grid.
    profile : (f, psd)
        Azimuthal average of the first direction's PSD.
    hf_variance : float
        Fitting variance beyond the PSD grid (rad^2).
    """
    model = residual_psd_model(psf, pupil, atmosphere, ao, residual)
    smp = model.sampling
    otf_tel = telescope_otf(pupil, smp)
    k_dirs = positions.shape[0]
    psfs = np.empty((k_dirs, smp.n_stamp, smp.n_stamp))
    strehl = np.empty(k_dirs)
    profile = (np.zeros(0), np.zeros(0))
    dirs = np.asarray(positions, float) / ARCSEC_PER_RAD
    from tqdm.auto import tqdm  # only when a grid is computed (~0.15 s of every import)

    bar = tqdm(total=k_dirs, desc="PSF grid", unit="psf", disable=not progress, leave=False)
    for k, psd in enumerate(model.psds(dirs, psf.chunk)):
        if k == 0:
            profile = radial_average(model.fx, model.fy, psd, smp.df)
        otf_ao = np.exp(-0.5 * structure_function(psd, smp.df))
        psfs[k] = psf_from_otf(otf_tel * otf_ao, smp)
        strehl[k] = strehl_ratio(otf_tel, otf_ao) * np.exp(-model.hf_variance)
        bar.update(1)
    bar.close()
    return psfs, strehl, profile, model.hf_variance


def compute_grid(
    psf: PSFSettings,
    pupil: PupilSettings,
    atmosphere: AtmosphereSettings,
    ao: AOSettings,
    progress: bool = True,
) -> GridResult:
    """Compute the PSF grid for ``psf.mode`` (no cache).

    Parameters
    ----------
    psf : PSFSettings
        PSF settings (``mode``: Fourier model or a file of PSFs).
    pupil : PupilSettings
        Pupil geometry.
    atmosphere : AtmosphereSettings
        Turbulence profile and seeing.
    ao : AOSettings
        AO system.
    progress : bool
        Show a progress bar (on a terminal only).

    Returns
    -------
    GridResult
        The grid and the on-axis PSD profile.
    """
    if psf.mode == "file":
        from mavispm.simulate.optics.psf_fits import read_mavisim_psfs

        cube, nx, ny, lam = read_mavisim_psfs(
            psf.file,
            psf.pixel_scale,
            psf.stamp_size * 1000,
            psf.file_pixel_scale,
            psf.file_pixel_unit,
            pupil.diameter,
        )
        grid = PSFGrid(cube, nx, ny, psf.pixel_scale, lam, np.full(cube.shape[:2], np.nan))
        return GridResult(grid, np.zeros(0), np.zeros(0))
    if psf.mode == "fourier":
        nodes = psf.node_positions()
        gx, gy = np.meshgrid(nodes, nodes)
        # the on-axis direction first, so the halo profile is on-axis
        pos = np.concatenate([[[0.0, 0.0]], np.stack([gx.ravel(), gy.ravel()], -1)])
        psfs, strehl, prof, _ = compute_fourier_grid(psf, pupil, atmosphere, ao, pos, progress)
        n = nodes.size
        cube = psfs[1:].reshape(n, n, *psfs.shape[1:])
        grid = PSFGrid(
            cube, nodes, nodes.copy(), psf.pixel_scale, psf.wavelength, strehl[1:].reshape(n, n)
        )
        return GridResult(grid, *prof)
    pos = np.asarray([psf.static_position], float)
    residual = psf.mode == "static"
    psfs, strehl, prof, _ = compute_fourier_grid(
        psf, pupil, atmosphere, ao, pos, progress, residual=residual
    )
    grid = PSFGrid(
        psfs.reshape(1, 1, *psfs.shape[1:]),
        np.array([psf.static_position[0]], float),
        np.array([psf.static_position[1]], float),
        psf.pixel_scale,
        psf.wavelength,
        strehl.reshape(1, 1),
    )
    return GridResult(grid, *prof)


def write_grid(
    path: Path,
    result: GridResult,
    key: str,
    config: dict | None = None,
    extra_arrays: dict | None = None,
    extra_attrs: dict | None = None,
) -> Path:
    """Write a grid as a ``psfgrid`` HDF5 product (see docs/optics.md).

    ``extra_arrays`` / ``extra_attrs`` add datasets and root attributes (quantities
    allowed), e.g. the TT kernel map of :func:`mavispm.simulate.optics.cli.run_stage`.

    Parameters
    ----------
    path : pathlib.Path
        The product written.
    result : GridResult
        The grid.
    key : str
        Its cache key (stored).
    config : dict, optional
        Settings recorded as provenance.
    extra_arrays, extra_attrs : dict, optional
        More datasets and root attributes.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    g = result.grid
    return write_product(
        path,
        "psfgrid",
        arrays={
            "cube": g.cube,
            "nodes_x": g.nodes_x * u.arcsec,
            "nodes_y": g.nodes_y * u.arcsec,
            "strehl": g.strehl,
            "psd_frequency": result.psd_frequency / u.m,
            "psd_profile": result.psd_profile * u.m**2,
            **(extra_arrays or {}),
        },
        attrs={
            "pixel_scale": g.pixel_scale * u.mas,
            "wavelength": g.wavelength * u.nm,
            "grid_key": key,
            "static": bool(g.is_static),
            **(extra_attrs or {}),
        },
        config=config,
    )


def read_grid(path: Path, mapped: bool = False) -> GridResult:
    """Read a ``psfgrid`` product written by :func:`write_grid`.

    Parameters
    ----------
    path : pathlib.Path
        The product.
    mapped : bool
        Map the cube read-only from the file (a float64 dataset stored contiguous and
        unfiltered, as :func:`write_grid` writes it) instead of reading it: nothing is
        read until it is used (a caller that replaces it, such as ``build_optics`` with a
        cached tapered cube, never pays for it). Otherwise, or for another layout, read.

    Returns
    -------
    GridResult
        The grid and its PSD profile.
    """
    with open_product(path, "psfgrid") as f:
        try:
            cube = _mapped_cube(path, f["cube"]) if mapped else None
            if cube is None:
                cube = np.asarray(f["cube"], float)
            nx = np.asarray(f["nodes_x"], float)
            ny = np.asarray(f["nodes_y"], float)
            strehl = np.asarray(f["strehl"], float)
            pf = np.asarray(f["psd_frequency"], float)
            pp = np.asarray(f["psd_profile"], float)
            scale = float(f.attrs["pixel_scale"])
            lam = float(f.attrs["wavelength"])
        except KeyError as exc:
            raise InputError(f"psfgrid product lacks {exc}", path=path) from None
    if cube.ndim != 4 or cube.shape[:2] != (ny.size, nx.size) or cube.shape[2] % 2 == 0:
        raise InputError(f"psfgrid cube has inconsistent shape {cube.shape}", path=path)
    return GridResult(PSFGrid(cube, nx, ny, scale, lam, strehl), pf, pp)


def _mapped_cube(path: Path, ds) -> np.ndarray | None:
    """A read-only memory map of the HDF5 dataset ``ds`` of ``path``, or None.

    Only for a native float64 dataset stored contiguous without filters (its bytes are
    the array's, at ``ds.id.get_offset()``).
    """
    try:
        offset = ds.id.get_offset()
    except Exception:  # no storage allocated, or an h5py without it
        return None
    if offset is None or ds.chunks is not None or ds.dtype != np.dtype("<f8") or ds.size == 0:
        return None
    if ds.compression is not None or ds.external:
        return None
    return np.memmap(path, dtype=ds.dtype, mode="r", offset=offset, shape=ds.shape)


def cached_grid(
    psf: PSFSettings,
    pupil: PupilSettings,
    atmosphere: AtmosphereSettings,
    ao: AOSettings,
    cache_dir: Path | None = None,
    progress: bool = True,
    mapped: bool = False,
) -> tuple[GridResult, Path]:
    """The grid for these settings, from the disk cache or computed and cached.

    Parameters
    ----------
    psf : PSFSettings
        PSF settings.
    pupil : PupilSettings
        Pupil geometry.
    atmosphere : AtmosphereSettings
        Turbulence profile and seeing.
    ao : AOSettings
        AO system.
    cache_dir : pathlib.Path, optional
        Cache folder (default: :func:`default_cache_dir`).
    progress : bool
        Show a progress bar (on a terminal only).
    mapped : bool
        A cached grid's cube mapped read-only from the file (see :func:`read_grid`).

    Returns
    -------
    (GridResult, path of the cache file)
    """
    key = grid_key(psf, pupil, atmosphere, ao)
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path = cache / f"psfgrid-{key}.h5"
    if path.exists():
        try:
            return read_grid(path, mapped), path
        except Exception:  # a corrupt cache entry is recomputed, never trusted
            path.unlink(missing_ok=True)
    result = compute_grid(psf, pupil, atmosphere, ao, progress)
    config = {
        "psf": asdict(psf),
        "pupil": asdict(pupil),
        "atmosphere": asdict(atmosphere),
        "ao": asdict(ao),
    }
    write_grid(path, result, key, config)
    return result, path
