"""Geometric distortion of the AO module: static map plus a per-epoch dynamic term.

Static (paper section 3.1.3): a displacement field from a file (a regular grid
of field positions and displacements) or an analytic polynomial. The
MAVIS-like default is a pure cubic radial (pincushion) term scaled to 0.44 mas
at the field corner (15", -15"); it gives 0 at the centre, 0.16 mas at
r = 15" and a 0.05 mas standard deviation of the displacement amplitude inside
the 15" science field, as the paper's ray-traced map.

Dynamic (the paper's future work): for each epoch a random draw of low-order
terms (plate scale, rotation, shears, quadratic and cubic terms), each basis
normalised to unit RMS displacement over the science field and multiplied by
``dynamic_amplitude`` and a standard normal deviate seeded by
(``dynamic_seed``, epoch). Amplitude 0 is exactly the identity.

Displacements are in arcsec (field frame) at the interface, mas in settings.
"""

from __future__ import annotations

import csv
import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from mavispm.core.config import unit_field
from mavispm.core.errors import InputError

__all__ = [
    "Distortion",
    "DistortionSettings",
    "SCIENCE_RADIUS",
    "read_distortion_map",
]

#: radius of the MAVIS science field (arcsec)
SCIENCE_RADIUS = 15.0

_BASIS = {
    "scale": lambda u, v: (u, v),
    "rotation": lambda u, v: (-v, u),
    "shear1": lambda u, v: (u, -v),
    "shear2": lambda u, v: (v, u),
    "quadratic_x": lambda u, v: (u * u, u * v),
    "quadratic_y": lambda u, v: (u * v, v * v),
    "cubic": lambda u, v: (u * (u * u + v * v), v * (u * u + v * v)),
}


@dataclass(frozen=True)
class DistortionSettings:
    """Distortion (TOML table ``[scene.optics.distortion]``).

    Parameters
    ----------
    enabled : bool
        Master switch; off gives exactly zero displacement.
    static : {"default", "polynomial", "file", "none"}
        Source of the static map.
    corner_amplitude : float
        ``default`` map: displacement at the corner (15", -15") (mas).
    coefficients_x, coefficients_y : tuple of (i, j, c)
        ``polynomial`` map: ``dx = sum c u^i v^j`` (mas) with ``u, v = x, y / 15"``.
    file : str or None
        ``file`` map: CSV with header ``x,y,dx,dy`` or whitespace text (MAVISIM
        style, ``#`` comments) with columns x y dx dy; x, y in arcsec, dx, dy in mas,
        on a complete regular grid.
    dynamic : bool
        Add the per-epoch dynamic term.
    dynamic_amplitude : float
        RMS displacement of each dynamic term over the science field (mas).
    dynamic_terms : tuple of str
        Terms drawn per epoch (of scale, rotation, shear1, shear2, quadratic_x,
        quadratic_y, cubic).
    dynamic_seed : int
        Seed of the per-epoch draws.
    calibration : str or None
        A ``calibration`` product (``mavispm simulate calibration``): its recovered
        distortion is subtracted, so the frames carry the post-calibration residual.
    """

    enabled: bool = True
    static: Literal["default", "polynomial", "file", "none"] = "default"
    corner_amplitude: float = unit_field(0.44, "mas", "default map at (15, -15) arcsec")
    coefficients_x: tuple[tuple[int, int, float], ...] = field(default=())
    coefficients_y: tuple[tuple[int, int, float], ...] = field(default=())
    file: str | None = None
    dynamic: bool = False
    dynamic_amplitude: float = unit_field(0.1, "mas", "RMS per dynamic term")
    dynamic_terms: tuple[str, ...] = ("scale", "rotation", "shear1", "shear2")
    dynamic_seed: int = 0
    calibration: str | None = None

    def __post_init__(self):
        unknown = [t for t in self.dynamic_terms if t not in _BASIS]
        if unknown:
            raise ValueError(f"unknown dynamic_terms {unknown}; known: {sorted(_BASIS)}")
        if self.static == "file" and not self.file:
            raise ValueError("distortion.static = 'file' needs distortion.file")
        if self.dynamic_amplitude < 0:
            raise ValueError("dynamic_amplitude must be >= 0 mas")
        for name in ("coefficients_x", "coefficients_y"):
            for i, j, _c in getattr(self, name):
                if i < 0 or j < 0:
                    raise ValueError(f"{name}: powers must be >= 0")


def read_distortion_map(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Read a static distortion grid file.

    Parameters
    ----------
    path : str or pathlib.Path
        Text (whitespace-separated) or ``.csv`` file with columns x, y [arcsec], dx, dy [mas].

    Returns
    -------
    xs, ys : ndarray
        Sorted unique grid coordinates (arcsec).
    dx, dy : ndarray, shape (len(ys), len(xs))
        Displacements (mas).

    Raises
    ------
    InputError
        Missing file, wrong number of columns, non-finite values or an
        incomplete / irregular grid, naming the file.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("distortion map file does not exist", path=path)
    text = path.read_text()
    rows = []
    if path.suffix.lower() == ".csv":
        reader = csv.DictReader(line for line in text.splitlines() if line.strip())
        missing = {"x", "y", "dx", "dy"} - set(reader.fieldnames or [])
        if missing:
            raise InputError(f"CSV distortion map lacks columns {sorted(missing)}", path=path)
        try:
            rows = [[float(r[k]) for k in ("x", "y", "dx", "dy")] for r in reader]
        except (TypeError, ValueError) as exc:
            raise InputError(f"non-numeric value in distortion map ({exc})", path=path) from None
    else:
        for n, line in enumerate(text.splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            if len(parts) != 4:
                raise InputError(
                    f"line {n}: expected 4 columns x y dx dy, got {len(parts)}", path=path
                )
            try:
                rows.append([float(p) for p in parts])
            except ValueError:
                raise InputError(f"line {n}: non-numeric value", path=path) from None
    data = np.asarray(rows, float).reshape(-1, 4)
    if data.shape[0] < 4:
        raise InputError("distortion map needs at least a 2 x 2 grid of points", path=path)
    if not np.all(np.isfinite(data)):
        raise InputError("distortion map contains NaN or infinite values", path=path)
    xs, ys = np.unique(data[:, 0]), np.unique(data[:, 1])
    if xs.size < 2 or ys.size < 2 or xs.size * ys.size != data.shape[0]:
        raise InputError(
            f"distortion map is not a complete regular grid ({data.shape[0]} points, "
            f"{xs.size} x values, {ys.size} y values)",
            path=path,
        )
    ix = np.searchsorted(xs, data[:, 0])
    iy = np.searchsorted(ys, data[:, 1])
    dx = np.full((ys.size, xs.size), np.nan)
    dy = np.full_like(dx, np.nan)
    dx[iy, ix] = data[:, 2]
    dy[iy, ix] = data[:, 3]
    if np.isnan(dx).any():
        raise InputError("distortion map has duplicated grid points", path=path)
    return xs, ys, dx, dy


def _basis_rms(name: str) -> float:
    g = np.linspace(-1, 1, 101)
    u, v = np.meshgrid(g, g)
    inside = u**2 + v**2 <= 1
    bx, by = _BASIS[name](u[inside], v[inside])
    return float(np.sqrt(np.mean(np.asarray(bx) ** 2 + np.asarray(by) ** 2)))


def _epoch_rng(seed: int, epoch: float) -> np.random.Generator:
    token = hashlib.sha256(f"{int(seed)}:{float(epoch):.9f}".encode()).digest()
    return np.random.default_rng(int.from_bytes(token[:8], "little"))


class Distortion:
    """Static plus dynamic displacement field.

    Parameters
    ----------
    settings : DistortionSettings

    Raises
    ------
    InputError
        For a static map file that is missing or malformed (naming the file).
    """

    def __init__(self, settings: DistortionSettings):
        self.settings = settings
        self._grid = None
        if settings.enabled and settings.static == "file":
            # imported here: scipy.interpolate (and the scipy.optimize it pulls in) costs
            # ~0.3-1 s of every process that renders or measures a frame otherwise
            from scipy.interpolate import RegularGridInterpolator

            xs, ys, dx, dy = read_distortion_map(settings.file)
            self._grid = (
                RegularGridInterpolator((ys, xs), dx, bounds_error=False, fill_value=None),
                RegularGridInterpolator((ys, xs), dy, bounds_error=False, fill_value=None),
            )
        self._rms = {t: _basis_rms(t) for t in settings.dynamic_terms}
        self._recovered = None
        if settings.enabled and settings.calibration:
            from mavispm.simulate.optics.calibration_mask import read_recovered_distortion

            self._recovered = read_recovered_distortion(settings.calibration)

    @property
    def enabled(self) -> bool:
        """Whether any displacement is applied."""
        return self.settings.enabled

    def static_displacement(self, x: ArrayLike, y: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """Static displacement (mas) at field positions (arcsec).

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec].

        Returns
        -------
        dx, dy : ndarray
            Displacements [mas]; zeros when disabled or ``static = "none"``.
        """
        x, y = np.asarray(x, float), np.asarray(y, float)
        s = self.settings
        zero = np.zeros(np.broadcast(x, y).shape)
        if not s.enabled or s.static == "none":
            return zero, zero.copy()
        u, v = x / SCIENCE_RADIUS, y / SCIENCE_RADIUS
        if s.static == "default":
            k = s.corner_amplitude / 2**1.5  # |d| = k r^3 (r in units of 15"); corner r = sqrt 2
            r2 = u * u + v * v
            return k * u * r2, k * v * r2
        if s.static == "polynomial":
            dx = zero + sum(c * u**i * v**j for i, j, c in s.coefficients_x)
            dy = zero + sum(c * u**i * v**j for i, j, c in s.coefficients_y)
            return dx, dy
        pts = np.stack(np.broadcast_arrays(y, x), -1)
        return self._grid[0](pts), self._grid[1](pts)

    def dynamic_coefficients(self, epoch: float) -> dict[str, float]:
        """The per-epoch coefficients (mas RMS units) of the dynamic terms.

        Parameters
        ----------
        epoch : float
            Epoch [yr] (seeds the draw with ``dynamic_seed``).

        Returns
        -------
        dict of str to float
            Term name to coefficient [mas RMS]; zeros when dynamic distortion is off.
        """
        s = self.settings
        if not (s.enabled and s.dynamic) or s.dynamic_amplitude == 0:
            return {t: 0.0 for t in s.dynamic_terms}
        draws = _epoch_rng(s.dynamic_seed, epoch).standard_normal(len(s.dynamic_terms))
        return {t: float(s.dynamic_amplitude * d) for t, d in zip(s.dynamic_terms, draws)}

    def displacement(
        self, x: ArrayLike, y: ArrayLike, epoch: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Total displacement (arcsec) at field positions (arcsec) for ``epoch`` (yr).

        Exactly zero when disabled.

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec], finite.
        epoch : float
            Epoch [yr].

        Returns
        -------
        dx, dy : ndarray
            Static plus dynamic displacement, less the recovered calibration when one is
            given [arcsec].

        Raises
        ------
        ValueError
            For non-finite positions.
        """
        x, y = np.asarray(x, float), np.asarray(y, float)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("field positions must be finite")
        dx, dy = self.static_displacement(x, y)
        u, v = x / SCIENCE_RADIUS, y / SCIENCE_RADIUS
        for term, c in self.dynamic_coefficients(epoch).items():
            if c == 0.0:
                continue
            bx, by = _BASIS[term](u, v)
            dx = dx + c / self._rms[term] * bx
            dy = dy + c / self._rms[term] * by
        if self._recovered is not None:
            rx, ry = self._recovered.displacement_mas(x, y)
            dx, dy = dx - rx, dy - ry
        return np.asarray(dx, float) / 1000.0, np.asarray(dy, float) / 1000.0
