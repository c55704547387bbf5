"""Memory limits checked when settings are validated, before anything is allocated.

A setting that would need more memory than the limit (a 1e6 x 1e6 detector,
``n_nodes`` = 1e6, ``--n-stars 1e9``) is refused by the stage's
``validate_settings`` with a :class:`~mavispm.core.errors.ConfigError` naming
the key and the estimated memory, so ``mavispm run --dry-run`` refuses it too.

The limit is half of this machine's physical memory, or the explicit setting
``MAVISPM_MAX_MEMORY`` (environment variable: ``"64GB"``, ``"500 GiB"``,
``"inf"`` for none), so a large job on a large machine is one setting away.
Estimates count the dominant arrays only (order of magnitude).
"""

from __future__ import annotations

import os
import re

from mavispm.core.errors import ConfigError

__all__ = [
    "ENV_VAR",
    "check_memory",
    "human_bytes",
    "memory_limit",
    "parse_bytes",
    "physical_memory",
]

#: Environment variable overriding the memory limit.
ENV_VAR = "MAVISPM_MAX_MEMORY"

_UNITS = {
    "": 1,
    "b": 1,
    "kb": 1e3,
    "mb": 1e6,
    "gb": 1e9,
    "tb": 1e12,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
    "tib": 2**40,
}


def parse_bytes(text: str) -> float:
    """Parse a memory size: ``"64GB"``, ``"1.5 GiB"``, ``"inf"`` -> bytes.

    Parameters
    ----------
    text : str
        A number with an optional unit (B, kB, MB, GB, TB in powers of 1000; KiB, MiB, GiB,
        TiB in powers of 1024; case-insensitive), or ``inf``/``none``/``unlimited``.

    Returns
    -------
    float
        The size [byte]; ``inf`` for no limit.

    Raises
    ------
    ValueError
        When ``text`` is not such a size.
    """
    text = str(text).strip().lower()
    if text in ("inf", "none", "unlimited"):
        return float("inf")
    m = re.fullmatch(r"([0-9]*\.?[0-9]+(?:e[0-9]+)?)\s*([a-z]*)", text)
    if not m or m.group(2) not in _UNITS:
        raise ValueError(f"expected a size such as 64GB or 1.5GiB, got {text!r}")
    return float(m.group(1)) * _UNITS[m.group(2)]


def physical_memory() -> float:
    """Bytes of physical memory (inf when the OS does not say)."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return float("inf")


def memory_limit() -> float:
    """The memory limit in bytes (``$MAVISPM_MAX_MEMORY`` or half the physical memory).

    Raises
    ------
    ConfigError
        When ``MAVISPM_MAX_MEMORY`` is not a size.
    """
    raw = os.environ.get(ENV_VAR)
    if raw:
        try:
            return parse_bytes(raw)
        except ValueError as exc:
            raise ConfigError(str(exc), key=ENV_VAR) from None
    return 0.5 * physical_memory()


def human_bytes(n: float) -> str:
    """Write a byte count as a short string in powers of 1024 (``7.0 TiB``).

    Parameters
    ----------
    n : float
        Size [byte].

    Returns
    -------
    str
        The size with one decimal in the largest unit below 1024 (whole bytes below 1 KiB).
    """
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if n < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover


def check_memory(nbytes: float, what: str, key: str, source: str | None = None) -> None:
    """Refuse settings whose estimated memory exceeds :func:`memory_limit`.

    Parameters
    ----------
    nbytes : float
        Estimated memory of the request [bytes].
    what : str
        What would be allocated, for the message.
    key : str
        The setting responsible (dotted key or option).
    source : str, optional
        The configuration file.

    Raises
    ------
    ConfigError
        Naming the key, the estimate and how to raise the limit.
    """
    limit = memory_limit()
    if nbytes > limit:
        raise ConfigError(
            f"{what} needs about {human_bytes(nbytes)} of memory, more than the limit "
            f"{human_bytes(limit)} (half of this machine's memory unless {ENV_VAR} is set); "
            f'reduce it, or set {ENV_VAR} (e.g. {ENV_VAR}="{human_bytes(2 * nbytes)}") to allow it',
            key=key,
            source=source,
        )
