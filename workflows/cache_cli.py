"""``mavispm cache``: disk usage of the caches, and cleaning by age or size.

Two caches grow without bound unless cleaned:

* the disk cache (``$MAVISPM_CACHE``, default ``~/.cache/mavispm``): PSF grids
  (``psfgrid-*.h5``) and their tapered cubes (``psftaper-*.npy``), seeing halos (``halo-*.npz``) and their kernels' transforms
  (``halospec-*.npz``) and stamp plans (``stampplan-*.npz``), shared by every work
  directory;
* a work directory's product store (``<workdir>/store/<stage>/<key>/``), one
  folder per node.

Cleaning removes the least recently used entries first: everything not used
for ``--older-than`` (``30d``, ``12h``, ``2w``), then, oldest first, until the
total is under ``--max-size`` (``2GB``, ``500 MiB``). Only files of the kinds
above and store node folders are ever removed, whatever the folder holds. A
removed entry is simply recomputed when a later run needs it; run directories
keep their hard-linked products.
"""

from __future__ import annotations

import argparse
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from mavispm.core.errors import ConfigError

__all__ = [
    "CACHE_PATTERNS",
    "Entry",
    "disk_cache_entries",
    "human",
    "parse_age",
    "parse_size",
    "register",
    "select_for_removal",
    "store_entries",
]

#: File patterns of the disk cache (nothing else there is ever removed).
CACHE_PATTERNS = (
    "psfgrid-*.h5",
    "psftaper-*.npy",
    "halo-*.npz",
    "halospec-*.npz",
    "stampplan-*.npz",
    ".*.tmp",
)

_SIZE_UNITS = {
    "": 1,
    "b": 1,
    "k": 1e3,
    "kb": 1e3,
    "m": 1e6,
    "mb": 1e6,
    "g": 1e9,
    "gb": 1e9,
    "t": 1e12,
    "tb": 1e12,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
    "tib": 2**40,
}
_AGE_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}


@dataclass
class Entry:
    """One removable cache entry: a file, or a store node folder.

    Parameters
    ----------
    path : pathlib.Path
        The file or folder.
    size : int
        Bytes it holds [byte] (for a folder, the sum over its files).
    last_used : float
        Latest modification or access time [s since the epoch].
    kind : str
        What it is (the cache pattern's name or ``store/<stage>``), for the listing.
    """

    path: Path
    size: int
    last_used: float  # seconds since the epoch (latest of modification and access)
    kind: str


def parse_size(text: str, option: str = "--max-size") -> int:
    """``"2GB"``, ``"500 MiB"``, ``"0"`` -> bytes.

    Parameters
    ----------
    text : str
        A number with an optional unit (B, kB/k, MB/M, GB/G, TB/T in powers of 1000;
        KiB, MiB, GiB, TiB in powers of 1024).
    option : str
        The option named in the error message.

    Returns
    -------
    int
        The size [byte].

    Raises
    ------
    ConfigError
        Naming ``option`` for anything else.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([A-Za-z]*)\s*", str(text))
    if not m or m.group(2).lower() not in _SIZE_UNITS:
        raise ConfigError(f"expected a size such as 500MB, 2GB or 1.5GiB, got {text!r}", key=option)
    return int(float(m.group(1)) * _SIZE_UNITS[m.group(2).lower()])


def parse_age(text: str, option: str = "--older-than") -> float:
    """``"30d"``, ``"12h"``, ``"2w"``, ``"90m"``, ``"45s"`` -> seconds.

    Parameters
    ----------
    text : str
        A number followed by s, m, h, d or w.
    option : str
        The option named in the error message.

    Returns
    -------
    float
        The age [s].

    Raises
    ------
    ConfigError
        Naming ``option`` for anything else.
    """
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([smhdw])\s*", str(text))
    if not m:
        raise ConfigError(
            f"expected an age such as 30d, 12h, 2w, 90m or 45s, got {text!r}", key=option
        )
    return float(m.group(1)) * _AGE_UNITS[m.group(2)]


def _stat_entry(path: Path, kind: str) -> Entry | None:
    try:
        if path.is_dir():
            files = [p for p in path.rglob("*") if p.is_file() and not p.is_symlink()]
            stats = [p.stat() for p in files] or [path.stat()]
            size = sum(s.st_size for s in stats) if files else 0
            used = max(max(s.st_mtime, s.st_atime) for s in stats)
        else:
            st = path.stat()
            size, used = st.st_size, max(st.st_mtime, st.st_atime)
    except OSError:
        return None
    return Entry(path, size, used, kind)


def disk_cache_entries(folder: Path) -> list[Entry]:
    """The removable files of a disk cache folder.

    Parameters
    ----------
    folder : pathlib.Path
        The disk cache folder (``$MAVISPM_CACHE``).

    Returns
    -------
    list of Entry
        Files matching the cache's patterns (symbolic links skipped); empty when the folder
        does not exist.
    """
    if not folder.is_dir():
        return []
    seen: dict[Path, Entry] = {}
    for pattern in CACHE_PATTERNS:
        for path in folder.rglob(pattern):
            if path.is_file() and not path.is_symlink() and path not in seen:
                entry = _stat_entry(path, pattern.split("-")[0].strip(".*") or "temporary")
                if entry is not None:
                    seen[path] = entry
    return list(seen.values())


def store_entries(workdir: Path) -> list[Entry]:
    """The node folders (complete and partial) of a work directory's store.

    Parameters
    ----------
    workdir : pathlib.Path
        The work directory (its ``store/`` sub-folder is listed).

    Returns
    -------
    list of Entry
        One per node folder; empty without a store.
    """
    store = workdir / "store"
    if not store.is_dir():
        return []
    out = []
    for stage in sorted(p for p in store.iterdir() if p.is_dir()):
        for node in stage.iterdir():
            if node.is_dir() and not node.is_symlink():
                entry = _stat_entry(node, f"store/{stage.name}")
                if entry is not None:
                    out.append(entry)
    return out


def select_for_removal(
    entries: list[Entry], older_than: float | None, max_size: int | None, now: float
) -> list[Entry]:
    """Entries to remove: unused for ``older_than`` s, then oldest first down to ``max_size``.

    Parameters
    ----------
    entries : list of Entry
        Candidates.
    older_than : float or None
        Remove entries unused for longer than this [s]; None: no age limit.
    max_size : int or None
        Then remove the least recently used entries until the rest hold at most this [byte];
        None: no size limit.
    now : float
        Current time [s since the epoch].

    Returns
    -------
    list of Entry
        The entries to remove.
    """
    doomed = []
    keep = sorted(entries, key=lambda e: e.last_used)
    if older_than is not None:
        doomed = [e for e in keep if now - e.last_used > older_than]
        keep = [e for e in keep if now - e.last_used <= older_than]
    if max_size is not None:
        total = sum(e.size for e in keep)
        while keep and total > max_size:
            e = keep.pop(0)
            doomed.append(e)
            total -= e.size
    return doomed


def human(n: float) -> str:
    """Bytes as a short human-readable string (powers of 1000).

    Parameters
    ----------
    n : float
        Size [byte].

    Returns
    -------
    str
        For example ``"1.5 GB"``.
    """
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``cache`` command to the top-level sub-parsers.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``mavispm`` parser's sub-parsers.
    """
    p = subparsers.add_parser(
        "cache",
        help="show disk usage of the caches; clean them by age or size",
        description="Show how much the disk cache ($MAVISPM_CACHE, default ~/.cache/mavispm) "
        "and, with --workdir, a work directory's product store hold; with --older-than "
        "and/or --max-size, remove the least recently used entries (they are recomputed "
        "when needed).",
    )
    p.add_argument(
        "--dir", type=Path, default=None, help="disk cache folder (default $MAVISPM_CACHE)"
    )
    p.add_argument(
        "--workdir", type=Path, default=None, help="also the product store of this work directory"
    )
    p.add_argument(
        "--older-than",
        default=None,
        metavar="AGE",
        help="remove entries unused for AGE (30d, 12h, 2w)",
    )
    p.add_argument(
        "--max-size",
        default=None,
        metavar="SIZE",
        help="then remove the oldest entries until each cache is under SIZE (2GB, 500MiB)",
    )
    p.add_argument(
        "--dry-run", action="store_true", help="list what would be removed, remove nothing"
    )
    p.set_defaults(func=_cache)


def _cache(args: argparse.Namespace) -> int:
    from mavispm.simulate.optics.psf_grid import default_cache_dir

    older = None if args.older_than is None else parse_age(args.older_than)
    limit = None if args.max_size is None else parse_size(args.max_size)
    folder = args.dir if args.dir is not None else default_cache_dir()
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"'{folder}' is not a folder", key="--dir")
    places = [("disk cache", folder, disk_cache_entries(folder))]
    if args.workdir is not None:
        if not (args.workdir / "store").is_dir():
            raise ConfigError(
                f"'{args.workdir}' is not a mavispm work directory (no store/ folder)",
                key="--workdir",
            )
        places.append(("product store", args.workdir / "store", store_entries(args.workdir)))
    now = time.time()
    for label, where, entries in places:
        total = sum(e.size for e in entries)
        print(f"{label} {where}: {human(total)} in {len(entries)} entries")
        kinds: dict[str, list[Entry]] = {}
        for e in entries:
            kinds.setdefault(e.kind, []).append(e)
        for kind, es in sorted(kinds.items()):
            oldest = (now - min(e.last_used for e in es)) / 86400
            print(
                f"  {kind:>20}: {human(sum(e.size for e in es)):>9} in {len(es)}, oldest unused {oldest:.1f} d"
            )
        if older is None and limit is None:
            continue
        doomed = select_for_removal(entries, older, limit, now)
        freed = 0
        for e in doomed:
            if args.dry_run:
                print(f"  would remove {e.path} ({human(e.size)})")
            elif e.path.is_dir():
                shutil.rmtree(e.path, ignore_errors=True)
            else:
                e.path.unlink(missing_ok=True)
            freed += e.size
        verb = "would free" if args.dry_run else "freed"
        print(f"  {verb} {human(freed)} ({len(doomed)} entries); {human(total - freed)} left")
    return 0
