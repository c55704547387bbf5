"""The optics facade: everything the renderer needs about the PSF and its blur terms.

Build once per scene with :func:`build_optics` from the ``[scene.optics]``
TOML table; every term is switchable in its sub-table:

========== ===================================== ==========================
sub-table  what                                  module
========== ===================================== ==========================
atmosphere seeing, Cn^2 layers, winds, L0         ``simulate.optics.atmosphere``
pupil      VLT pupil, obscuration, spiders        ``simulate.optics.pupil``
ao         MCAO system and PSD error terms        ``simulate.optics.ao_psd``
psf        PSF grid mode, sampling, field         ``simulate.optics.psf_grid``
halo       seeing-wing kernel                     ``simulate.optics.seeing_halo``
tiptilt    NGS asterism TT residual kernels       ``simulate.optics.tiptilt``
blur       charge diffusion and vibration         ``simulate.optics.blur``
distortion static and dynamic distortion          ``simulate.optics.distortion``
image_     per-exposure image motion and dynamic  ``simulate.optics.image_motion``
motion     distortion of stacks
refraction differential atmospheric refraction   ``simulate.optics.refraction``
telescope  plate-scale variation, field distortion ``simulate.optics.telescope``
broadband  monochromatic PSF slices of the band  ``simulate.optics.broadband``
knobs      accuracy and speed knobs (below)
========== ===================================== ==========================

The accuracy and speed knobs (:class:`OpticsKnobs`, GalSim's GSParams pattern) are one
object apart from the optical model: set them in ``[scene.optics.knobs]`` or, as before,
in ``[scene.optics.psf]`` (not both for one knob), and read them as ``settings.knobs``.
They are stored in the ``psf`` term that uses them, so the PSF-grid cache key does not
depend on where they were given.

Example
-------
>>> s = validate_settings({"knobs": {"pupil_sampling": 64}, "psf": {"n_nodes": 5}})
>>> s.knobs.pupil_sampling, s.knobs.n_nodes, s.psf.pupil_sampling
(64, 5, 64)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mavispm.core.array_cache import content_key, load_arrays, save_arrays
from mavispm.core.atomic import atomic_path
from mavispm.core.config import from_mapping
from mavispm.core.errors import ConfigError
from mavispm.core.knobs import gather_knobs, scatter_knobs
from mavispm.simulate.optics.ao_psd import AOSettings
from mavispm.simulate.optics.atmosphere import (
    MAS_PER_RAD,
    AtmosphereSettings,
    fried_parameter,
    layers,
    von_karman_psd,
)
from mavispm.simulate.optics.blur import BlurSettings, blur_sigma
from mavispm.simulate.optics.broadband import BroadbandSettings, slice_wavelengths
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings
from mavispm.simulate.optics.image_motion import (
    ImageMotion,
    ImageMotionSettings,
    build_image_motion,
)
from mavispm.simulate.optics.psf_grid import GridResult, PSFGrid, PSFSettings, cached_grid
from mavispm.simulate.optics.pupil import PupilSettings
from mavispm.simulate.optics.refraction import RefractionSettings
from mavispm.simulate.optics.seeing_halo import Halo, HaloSettings, build_halo
from mavispm.simulate.optics.telescope import TelescopeSettings
from mavispm.simulate.optics.tiptilt import TipTiltField, TipTiltSettings

__all__ = [
    "OPTICS_KNOB_HOMES",
    "OpticsKnobs",
    "HALO_CACHE_VERSION",
    "Optics",
    "OpticsSettings",
    "build_optics",
    "cached_halo",
    "check_psf_grid_memory",
    "control_radius_mas",
    "make_halo",
    "psf_grid_memory",
    "cached_taper",
    "taper_grid",
    "validate_settings",
]

#: Version of the halo computation (part of its disk-cache key).
HALO_CACHE_VERSION = 1


@dataclass(frozen=True)
class OpticsKnobs:
    """Accuracy and speed knobs of the optics (``[scene.optics.knobs]``).

    None changes the optical model, only how finely the PSF grid samples it and the memory
    it takes; the defaults are those of :class:`~mavispm.simulate.optics.psf_grid.PSFSettings`
    (docs/optics.md gives the accuracy against each).

    Parameters
    ----------
    n_nodes : int
        PSF-grid nodes per side over ``psf.field_size`` (field sampling of the PSF).
    pupil_sampling : int
        Pupil-plane samples across the diameter.
    psd_padding : float
        PSD grid period over the pupil diameter.
    chunk : int
        Directions per vectorised PSD batch (memory only; not part of the PSF-grid key).
    """

    n_nodes: int = PSFSettings.n_nodes
    pupil_sampling: int = PSFSettings.pupil_sampling
    psd_padding: float = PSFSettings.psd_padding
    chunk: int = PSFSettings.chunk


#: Knob -> its home table in ``[scene.optics]`` (where the optics model reads it).
OPTICS_KNOB_HOMES = {f.name: ("psf",) for f in dataclasses.fields(OpticsKnobs)}


@dataclass(frozen=True)
class OpticsSettings:
    """All optics settings (TOML table ``[scene.optics]``), one sub-table per term.

    Parameters
    ----------
    atmosphere : AtmosphereSettings
        Seeing, Cn^2 profile, winds, outer scale.
    pupil : PupilSettings
        Telescope pupil.
    ao : AOSettings
        MCAO system and its error terms.
    psf : PSFSettings
        PSF-grid mode, wavelength, sampling and field (holds the knobs).
    halo : HaloSettings
        Seeing-wing kernel.
    tiptilt : TipTiltSettings
        NGS asterism and tip-tilt residual.
    blur : BlurSettings
        Charge diffusion and vibration.
    distortion : DistortionSettings
        Static and dynamic distortion.
    refraction : RefractionSettings
        Differential atmospheric refraction.
    telescope : TelescopeSettings
        Plate-scale changes and telescope field distortion.
    image_motion : ImageMotionSettings
        Per-exposure image motion and dynamic distortion of stacks.
    broadband : BroadbandSettings
        Monochromatic PSF slices across the band.
    """

    atmosphere: AtmosphereSettings = field(default_factory=AtmosphereSettings)
    pupil: PupilSettings = field(default_factory=PupilSettings)
    ao: AOSettings = field(default_factory=AOSettings)
    psf: PSFSettings = field(default_factory=PSFSettings)
    halo: HaloSettings = field(default_factory=HaloSettings)
    tiptilt: TipTiltSettings = field(default_factory=TipTiltSettings)
    blur: BlurSettings = field(default_factory=BlurSettings)
    distortion: DistortionSettings = field(default_factory=DistortionSettings)
    refraction: RefractionSettings = field(default_factory=RefractionSettings)
    telescope: TelescopeSettings = field(default_factory=TelescopeSettings)
    image_motion: ImageMotionSettings = field(default_factory=ImageMotionSettings)
    broadband: BroadbandSettings = field(default_factory=BroadbandSettings)

    @property
    def knobs(self) -> OpticsKnobs:
        """The accuracy and speed knobs as one object (read from the ``psf`` term)."""
        return OpticsKnobs(**{name: getattr(self.psf, name) for name in OPTICS_KNOB_HOMES})


def validate_settings(mapping: Mapping | None, source=None) -> OpticsSettings:
    """Build :class:`OpticsSettings` from the ``[scene.optics]`` table.

    Parameters
    ----------
    mapping : mapping or None
        The ``[scene.optics]`` table (None: defaults); the knobs may be given in
        ``knobs`` or in ``psf``, not both for one knob.
    source : str, optional
        File named in error messages.

    Returns
    -------
    OpticsSettings
        The validated settings (the PSF grid's memory checked against the limit).

    Raises
    ------
    ConfigError
        Unknown keys, wrong types or units, impossible values (naming the key).
    """
    mapping = dict(mapping or {})
    gathered = gather_knobs(mapping, OPTICS_KNOB_HOMES, prefix="scene.optics", source=source)
    if mapping.get("knobs") is not None:  # names a bad knob key or value where it was given
        from_mapping(OpticsKnobs, mapping["knobs"], prefix="scene.optics.knobs", source=source)
    mapping = scatter_knobs(gathered, OPTICS_KNOB_HOMES)
    settings = from_mapping(OpticsSettings, mapping, prefix="scene.optics", source=source)
    if settings.broadband.slices > 1:
        key = "scene.optics.broadband.slices"
        if settings.refraction.band == "monochromatic":
            raise ConfigError(
                "more than 1 slice needs a band: set scene.optics.refraction.band to "
                "'V' or 'tophat'",
                key=key,
                source=source,
            )
        if settings.psf.mode == "file":
            raise ConfigError(
                "slices need PSFs computed at each wavelength; psf.mode 'file' has one",
                key=key,
                source=source,
            )
    check_psf_grid_memory(settings, source)
    return settings


def psf_grid_memory(settings: OpticsSettings) -> tuple[float, str]:
    """Estimated peak memory of building the PSF grid [bytes] and the key that drives it.

    The stamp cube (``n_nodes^2`` stamps, held twice) and, in Fourier mode, the
    complex FFT work arrays of one chunk of directions.

    Parameters
    ----------
    settings : OpticsSettings
        The optics settings.

    Returns
    -------
    nbytes : float
        Estimated peak memory [byte].
    key : str
        Dotted settings key named when the estimate is over the limit.
    """
    from mavispm.simulate.optics.fourier_psf import fourier_sampling

    psf = settings.psf
    n_stamp = int(round(psf.stamp_size * 1000 / psf.pixel_scale)) // 2 * 2 + 1
    n_fft = n_stamp
    if psf.mode != "file":
        try:
            smp = fourier_sampling(
                psf.wavelength * 1e-9,
                psf.pixel_scale,
                settings.pupil.diameter,
                psf.pupil_sampling,
                psf.psd_padding,
                psf.stamp_size * 1000,
            )
            n_stamp, n_fft = smp.n_stamp, max(smp.n_fft, smp.n_psd)
        except ValueError:  # coarser than Nyquist: refused later with its own message
            pass
    # broadband slices: the grid plus one grid per slice
    n_grids = 1 if settings.broadband.slices == 1 else 1 + settings.broadband.slices
    cube = 2.0 * psf.n_nodes**2 * n_stamp**2 * 8 * n_grids
    fft = 4.0 * min(psf.chunk, psf.n_nodes**2) * n_fft**2 * 16 if psf.mode != "file" else 0.0
    key = "scene.optics.psf.n_nodes" if cube >= fft else "scene.optics.psf.pupil_sampling"
    return cube + fft, key


def check_psf_grid_memory(settings: OpticsSettings, source=None) -> None:
    """Refuse PSF-grid settings beyond the memory limit (:mod:`mavispm.core.limits`).

    Parameters
    ----------
    settings : OpticsSettings
        The optics settings.
    source : str, optional
        File named in the error.

    Raises
    ------
    ConfigError
        Naming the key that drives the estimate and the memory it needs.
    """
    from mavispm.core.limits import check_memory

    nbytes, key = psf_grid_memory(settings)
    check_memory(nbytes, "the PSF grid", key, source)


@dataclass(frozen=True, eq=False)
class Optics:
    """The optics of one scene.

    Parameters
    ----------
    settings : OpticsSettings
    psf_grid : PSFGrid
        Core PSF stamps (tapered by the halo ramp when the halo is on), each
        summing to 1.
    halo : Halo or None
        Seeing-wing kernel; None when disabled.
    tiptilt : TipTiltField
        Atmospheric TT residual covariance (mas^2).
    blur_sigma : float
        Charge diffusion and vibration in quadrature (mas).
    distortion : Distortion
    cache_path : Path or None
        The PSF-grid cache file used.
    control_radius : float
        AO control radius lambda n_act / (2 D) (mas).
    image_motion : ImageMotion
        Per-exposure image motion and dynamic distortion of stacks (``enabled`` false
        by default).
    psf_slices : numpy.ndarray or None
        Monochromatic grids (K, n_nodes, n_nodes, n, n) at ``slice_wavelengths``, sampled
        and tapered like ``psf_grid``; None with one slice (``broadband.slices = 1``).
    slice_wavelengths : numpy.ndarray or None
        Their wavelengths [nm].
    slice_cache_paths : tuple of Path
        The PSF-grid cache files of the slices (empty with one slice).
    """

    settings: OpticsSettings
    psf_grid: PSFGrid
    halo: Halo | None
    tiptilt: TipTiltField
    blur_sigma: float
    distortion: Distortion
    cache_path: Path | None
    control_radius: float
    image_motion: ImageMotion | None = None
    psf_slices: np.ndarray | None = None
    slice_wavelengths: np.ndarray | None = None
    slice_cache_paths: tuple = ()

    def kernel_covariance(self, x, y) -> np.ndarray:
        """TT covariance plus isotropic blur, (N, 2, 2) in mas^2, at field positions (arcsec).

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec].

        Returns
        -------
        ndarray, shape (N, 2, 2)
            Covariance [mas^2].
        """
        return self.tiptilt.covariance(x, y) + self.blur_sigma**2 * np.eye(2)


def control_radius_mas(settings: OpticsSettings) -> float:
    """AO control radius lambda n_act / (2 D) in mas at the PSF wavelength.

    Parameters
    ----------
    settings : OpticsSettings
        PSF wavelength [nm], actuators across the pupil and pupil diameter [m].

    Returns
    -------
    float
        Control radius [mas].
    """
    lam = settings.psf.wavelength * 1e-9
    return lam * settings.ao.n_actuators / (2 * settings.pupil.diameter) * MAS_PER_RAD


def _fitting_profile(settings: OpticsSettings) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic fitting-only PSD (for PSF databases without a computed PSD)."""
    lam = settings.psf.wavelength * 1e-9
    fc = settings.ao.control_frequency(settings.pupil.diameter)
    f = np.linspace(0.0, 20 * fc, 4000)
    r0 = fried_parameter(settings.atmosphere, lam)
    psd = von_karman_psd(f**2, r0, settings.atmosphere.outer_scale) * (f >= fc)
    return f, psd


def make_halo(settings: OpticsSettings, result: GridResult) -> Halo:
    """The halo for a computed grid (uses its on-axis PSD profile).

    Parameters
    ----------
    settings : OpticsSettings
        The optics settings.
    result : GridResult
        The computed grid with its on-axis PSD profile (the fitting-error profile is used
        when the grid has none, as in ``file`` mode).

    Returns
    -------
    Halo
        The seeing-halo kernel.
    """
    lam = settings.psf.wavelength * 1e-9
    f, psd = result.psd_frequency, result.psd_profile
    if f.size == 0:
        f, psd = _fitting_profile(settings)
    grid = result.grid
    return build_halo(
        settings.halo,
        f,
        psd,
        lam,
        settings.pupil.diameter,
        settings.pupil.obscuration_ratio,
        fried_parameter(settings.atmosphere, lam),
        settings.atmosphere.outer_scale,
        control_radius_mas(settings),
        (grid.n - 1) / 2 * grid.pixel_scale,
    )


def cached_halo(settings: OpticsSettings, result: GridResult, grid_path: Path | None) -> Halo:
    """:func:`make_halo`, kept next to the PSF-grid cache file ``grid_path`` (when given).

    The halo profile is a pure function of the grid's parameters (its cache key,
    part of the file name) and the halo settings; its Hankel transforms take ~2 s,
    which every epoch of a scene would otherwise repeat.

    Parameters
    ----------
    settings : OpticsSettings
        The optics settings.
    result : GridResult
        The computed grid.
    grid_path : pathlib.Path or None
        The grid's cache file; None: no caching.

    Returns
    -------
    Halo
        The seeing-halo kernel.
    """
    if grid_path is None:
        return make_halo(settings, result)
    key = content_key(
        HALO_CACHE_VERSION,
        Path(grid_path).name,
        dataclasses.asdict(settings.halo),
        [result.grid.n, float(result.grid.pixel_scale)],
    )
    path = Path(grid_path).parent / f"halo-{key}.npz"
    stored = load_arrays(path)
    names = [f.name for f in dataclasses.fields(Halo)]
    if stored is not None and set(stored) == set(names):
        return Halo(*(stored[n] if stored[n].ndim else float(stored[n]) for n in names))
    halo = make_halo(settings, result)
    save_arrays(path, {n: np.asarray(getattr(halo, n)) for n in names})
    return halo


def taper_grid(grid: PSFGrid, halo: Halo, in_place: bool = False) -> PSFGrid:
    """Multiply every stamp by ``1 - ramp`` and renormalise to unit sum.

    Parameters
    ----------
    grid : PSFGrid
        The core PSF grid.
    halo : Halo
        The halo whose ramp tapers the cores.
    in_place : bool
        Taper ``grid.cube`` itself (a float64 cube nothing else uses, e.g. one just
        read from the cache): no second cube (64 MB for 11 x 11 nodes of 256 x 256
        pixels, ~0.02-0.1 s of page faults in a ``simulate frames`` process).

    Returns
    -------
    PSFGrid
        A new grid with tapered stamps (with ``in_place``: sharing ``grid.cube``).
    """
    taper = halo.core_taper(grid.n, grid.pixel_scale)
    cube = grid.cube
    writable = isinstance(cube, np.ndarray) and cube.flags.writeable
    if in_place and writable and cube.dtype == np.float64:
        cube *= taper
    else:
        cube = cube * taper
    cube /= cube.sum(axis=(-2, -1), keepdims=True)
    return dataclasses.replace(grid, cube=cube)


#: Version of the cached tapered PSF cubes (bump when :func:`taper_grid` changes).
TAPER_CACHE_VERSION = 1


def cached_taper(grid: PSFGrid, halo: Halo, grid_path: Path | None) -> PSFGrid:
    """:func:`taper_grid` of the grid of the cache file ``grid_path``, itself cached.

    The tapered cube is kept next to the grid (``psftaper-<key>.npy``; key: the grid
    file's name, size and modification time and the taper) and memory-mapped read-only
    from there: a ``simulate frames`` process then neither reads the 64 MB cube (11 x 11
    nodes of 256 x 256 pixels) into fresh memory nor tapers it (~0.05 s of CPU with
    the page faults); the renderer reads it from the page cache. The same values as
    tapering the grid (saved from it, bit for bit).

    Parameters
    ----------
    grid : PSFGrid
        The grid read from ``grid_path`` (its cube may be a read-only map).
    halo : Halo
        The halo whose ramp tapers the cores.
    grid_path : pathlib.Path or None
        The grid's cache file; None: tapered in place, nothing cached.

    Returns
    -------
    PSFGrid
        The tapered grid.
    """
    if grid_path is None:
        return taper_grid(grid, halo, in_place=True)
    grid_path = Path(grid_path)
    try:
        stat = grid_path.stat()
    except OSError:
        return taper_grid(grid, halo, in_place=True)
    taper = halo.core_taper(grid.n, grid.pixel_scale)
    key = content_key(
        TAPER_CACHE_VERSION,
        [grid_path.name, stat.st_size, stat.st_mtime_ns, float(grid.pixel_scale)],
        np.asarray(taper, dtype=np.float64),
    )
    path = grid_path.parent / f"psftaper-{key}.npy"
    mapped = _mapped_taper(path, np.shape(grid.cube))
    if mapped is not None:
        return dataclasses.replace(grid, cube=mapped).with_cube_key(path.stem)
    tapered = taper_grid(grid, halo, in_place=True)  # in place only where writable
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(tapered.cube, dtype=np.float64))
    except OSError:  # a folder that cannot be written costs the taper next time
        return tapered
    # the saved cube, mapped: the same values, keyed like the next process's
    mapped = _mapped_taper(path, np.shape(grid.cube))
    if mapped is not None:
        return dataclasses.replace(grid, cube=mapped).with_cube_key(path.stem)
    return tapered


def _mapped_taper(path: Path, shape) -> np.ndarray | None:
    """The tapered cube of the cache file ``path``, mapped read-only, or None (a miss).

    The caller attaches the file's key (``path.stem``) to the grid
    (:meth:`~mavispm.simulate.optics.psf_grid.PSFGrid.with_cube_key`): the renderer keys
    its stamp plans by it instead of hashing the 64 MB.
    """
    try:
        cube = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError):
        return None
    if cube.shape != tuple(shape) or cube.dtype != np.float64:
        return None
    return cube


def build_optics(
    settings: OpticsSettings, cache_dir: Path | None = None, progress: bool = True
) -> Optics:
    """Build (or load from the cache) everything about the optics of a scene.

    Parameters
    ----------
    settings : OpticsSettings
    cache_dir : Path, optional
        Where PSF grids are cached (default ``$MAVISPM_CACHE`` or ``~/.cache/mavispm``).
    progress : bool
        Show a progress bar while computing a grid.
    """
    s = settings
    # with a halo the cube is mapped, not read: the tapered one is usually cached
    result, path = cached_grid(
        s.psf, s.pupil, s.atmosphere, s.ao, cache_dir, progress, mapped=s.halo.enabled
    )
    grid = result.grid
    halo = None
    if s.halo.enabled:
        halo = cached_halo(s, result, path)
        grid = cached_taper(grid, halo, path)
    tiptilt = TipTiltField(
        s.tiptilt, s.atmosphere, s.pupil, cache_dir=None if path is None else Path(path).parent
    )
    slices = lam_k = None
    slice_paths = []
    if s.broadband.slices > 1:
        lam_k = slice_wavelengths(s.refraction, s.broadband.slices)
        cubes = []
        for lam in lam_k:
            psf_k = dataclasses.replace(s.psf, wavelength=float(lam))
            res_k, path_k = cached_grid(psf_k, s.pupil, s.atmosphere, s.ao, cache_dir, progress)
            slice_paths.append(path_k)
            grid_k = res_k.grid
            cubes.append((taper_grid(grid_k, halo, True) if halo is not None else grid_k).cube)
        slices = np.stack(cubes)
    return Optics(
        settings=s,
        psf_grid=grid,
        halo=halo,
        tiptilt=tiptilt,
        blur_sigma=blur_sigma(s.blur),
        distortion=Distortion(s.distortion),
        cache_path=path,
        control_radius=control_radius_mas(s),
        image_motion=build_image_motion(
            s.image_motion, tiptilt, layers(s.atmosphere), s.pupil.diameter
        ),
        psf_slices=slices,
        slice_wavelengths=lam_k,
        slice_cache_paths=tuple(slice_paths),
    )
