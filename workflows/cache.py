"""Content-addressed product cache with completion markers.

Every node's *key* is a hash of its stage, the stage's code version (package
version plus the content of the stage's source files), its settings, its
parameters, its seed and the keys of its inputs (or the content of external
input files). Keys chain from the inputs, so changing one setting changes the
key of that node and of everything downstream, and nothing else.

A node's products live in ``<store>/<stage>/<key>/``. A task writes into
``<key>.partial/`` and, when the stage returns, writes the marker
``complete.json`` there and renames the folder to ``<key>`` in one atomic
step. A folder without its marker is never trusted, so a run killed at any
moment resumes by redoing only unfinished nodes; the partial folder is reused
so stages with their own resumable state (an emcee backend) pick it up.

Committed products are made read-only and their SHA-256, size and
modification time go into the marker. A product changed afterwards (through a
hard link in a run directory, by a user allowed to write read-only files) no
longer counts as cached: its node runs again (a warning says so). The check
costs one ``stat`` per product; the content is hashed only when size or
modification time changed.
"""

from __future__ import annotations

import contextlib

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no cross-process lock
    fcntl = None
import hashlib
import json
import os
import shutil
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mavispm.workflows.graph import Node
from mavispm.workflows.registry import StageRegistry, resolve

__all__ = [
    "Store",
    "canonical_json",
    "exclusive_lock",
    "file_digest",
    "node_keys",
    "product_fingerprint",
    "without_keys",
]

MARKER = "complete.json"
LOCK_NAME = ".lock"
PARTIAL_SUFFIX = ".partial"
KEY_LENGTH = 24


def canonical_json(obj: object) -> str:
    """Deterministic JSON text of ``obj`` (sorted keys, no whitespace).

    Parameters
    ----------
    obj : object
        JSON-serialisable data; paths become strings, numpy scalars and arrays Python numbers
        and lists, anything else its ``repr``.

    Returns
    -------
    str
        The JSON text (equal objects give equal text, so it can be hashed).
    """
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(obj):
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return repr(obj)


_DIGESTS: dict[tuple, str] = {}


def file_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a file's content (memoised on path, size and modification time).

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    str
        Hexadecimal SHA-256 digest of the bytes.
    """
    path = Path(path)
    st = path.stat()
    memo = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if memo not in _DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        _DIGESTS[memo] = h.hexdigest()
    return _DIGESTS[memo]


def without_keys(settings: Mapping, dotted: tuple[str, ...]) -> dict:
    """A copy of a nested settings mapping without the ``dotted`` keys ("render.threads").

    Parameters
    ----------
    settings : mapping
        A TOML table (nested mappings).
    dotted : tuple of str
        Keys to drop, sub-tables separated by dots.

    Returns
    -------
    dict
    """
    out = dict(settings or {})
    for key in dotted:
        head, _, rest = key.partition(".")
        if head not in out:
            continue
        if rest:
            if isinstance(out[head], Mapping):
                out[head] = without_keys(out[head], (rest,))
        else:
            del out[head]
    return out


def node_keys(nodes: Mapping[str, Node], registry: StageRegistry) -> dict[str, str]:
    """Key of every node (``nodes`` in topological order).

    Parameters
    ----------
    nodes : mapping of str to Node
        Node id to node, in topological order (inputs before users).
    registry : StageRegistry
        The stages (their code fingerprints enter the keys).

    Returns
    -------
    dict of str to str
        Node id to hexadecimal key.
    """
    keys: dict[str, str] = {}
    for nid, node in nodes.items():
        inputs = {}
        for name, ref in node.inputs.items():
            inputs[name] = [keys[r] for r in ref] if isinstance(ref, list) else keys[ref]
        for name, path in node.external.items():
            inputs[name] = "file:" + file_digest(path)
        spec = registry[node.stage]
        canonical = resolve(spec.canonical)
        settings = node.settings if canonical is None else canonical(node.settings, node.stage)
        record = {
            "stage": node.stage,
            "code": spec.code_version(),
            "settings": without_keys(settings, spec.ui_keys),
            "params": node.params,
            "seed": node.seed,
            "inputs": inputs,
        }
        keys[nid] = hashlib.sha256(canonical_json(record).encode()).hexdigest()[:KEY_LENGTH]
    return keys


@contextlib.contextmanager
def exclusive_lock(path: Path):
    """Hold an exclusive OS file lock on ``path`` (created if needed) for the block.

    A killed holder releases the lock with its death. Without POSIX ``fcntl`` the
    block runs unlocked.

    Parameters
    ----------
    path : pathlib.Path
        The lock file.

    Yields
    ------
    None
        The lock is held while the block runs.
    """
    with open(path, "a+b") as fh:
        if fcntl is not None:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            if fcntl is not None:
                fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


class Store:
    """The on-disk product store of a work directory.

    Parameters
    ----------
    root : pathlib.Path
        Store folder (``<workdir>/store``); created on demand.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def final_dir(self, stage: str, key: str) -> Path:
        """Folder of a completed node.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.

        Returns
        -------
        pathlib.Path
            ``root/stage/key``.
        """
        return self.root / stage / key

    def partial_dir(self, stage: str, key: str) -> Path:
        """Working folder of an unfinished node.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.

        Returns
        -------
        pathlib.Path
            ``root/stage/key`` plus the partial suffix.
        """
        return self.root / stage / (key + PARTIAL_SUFFIX)

    def lookup(self, stage: str, key: str) -> dict | None:
        """The completion record of a node, or None if it is not complete.

        A record whose listed products are missing counts as not complete.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.

        Returns
        -------
        dict or None
            The record read from the node's marker file.
        """
        final = self.final_dir(stage, key)
        marker = final / MARKER
        try:
            record = json.loads(marker.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError):
            return None
        if not isinstance(record, dict) or not isinstance(record.get("products"), dict):
            return None
        if not all((final / rel).is_file() for rel in record["products"].values()):
            return None
        for name, rel in record["products"].items():
            if not _unchanged(final / rel, (record.get("digests") or {}).get(name)):
                warnings.warn(
                    f"cached product {final / rel} was changed after it was made; "
                    f"running node {record.get('node', key)} again",
                    stacklevel=2,
                )
                return None
        return record

    def begin(self, stage: str, key: str) -> Path:
        """Create (or reuse) the node's partial folder and return it.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.

        Returns
        -------
        pathlib.Path
            The partial folder.
        """
        part = self.partial_dir(stage, key)
        part.mkdir(parents=True, exist_ok=True)
        return part

    @contextlib.contextmanager
    def claim(self, stage: str, key: str):
        """Hold the node's partial folder exclusively (an OS file lock).

        Yields ``(partial_dir, record)``: ``record`` is the completion record when
        another process finished the node while this one waited (then nothing is
        left to do), else None. Two runs sharing a work directory therefore never
        write the same node at once; a killed holder releases the lock with its
        death.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.
        """
        part = self.begin(stage, key)
        with exclusive_lock(part / LOCK_NAME):
            record = self.lookup(stage, key)
            if record is not None and part.exists():
                shutil.rmtree(part, ignore_errors=True)  # a leftover made while waiting
            yield part, record

    def commit(self, stage: str, key: str, record: Mapping) -> Path:
        """Mark the partial folder complete and move it to its final name atomically.

        Returns the final folder. When another worker finished the same key
        first, its result is kept and this partial folder is removed.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.
        record : mapping
            The completion record (``products`` maps names to paths relative to the folder); the
            products' digests are added before it is written.

        Returns
        -------
        pathlib.Path
            The final folder.
        """
        part = self.partial_dir(stage, key)
        final = self.final_dir(stage, key)
        from mavispm.core.atomic import atomic_path

        record = {**record, "digests": _digests(part, record.get("products", {}))}
        with atomic_path(part / MARKER) as tmp:
            tmp.write_text(json.dumps(record, indent=1, sort_keys=True, default=_json_default))
        for rel in record.get("products", {}).values():  # run directories link to these
            _read_only(part / rel)
        if final.exists() and self.lookup(stage, key) is None:
            shutil.rmtree(final)  # an incomplete leftover from an older layout
        try:
            os.rename(part, final)
        except OSError:
            if self.lookup(stage, key) is None:
                raise
            shutil.rmtree(part, ignore_errors=True)
        return final

    def invalidate(self, stage: str, key: str) -> None:
        """Forget a completed node (``--force``): remove its marker and folder.

        Parameters
        ----------
        stage : str
            Stage name.
        key : str
            The node's cache key.
        """
        final = self.final_dir(stage, key)
        with contextlib.suppress(FileNotFoundError):
            (final / MARKER).unlink()
        shutil.rmtree(final, ignore_errors=True)


def _digests(folder: Path, products: Mapping) -> dict:
    """SHA-256, size and modification time of each product file (for tamper checks)."""
    out = {}
    for name, rel in products.items():
        path = folder / rel
        st = path.stat()
        out[name] = {"sha256": file_digest(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    return out


def _unchanged(path: Path, digest) -> bool:
    """Whether a product still has the content recorded at commit (True when none was)."""
    if not isinstance(digest, Mapping):
        return True  # a store written before digests were recorded
    try:
        st = path.stat()
    except OSError:
        return False
    if st.st_size == digest.get("size") and st.st_mtime_ns == digest.get("mtime_ns"):
        return True
    return st.st_size == digest.get("size") and file_digest(path) == digest.get("sha256")


def _read_only(path: Path) -> None:
    """Remove every write permission of a file (best effort)."""
    with contextlib.suppress(OSError):
        os.chmod(path, path.stat().st_mode & ~0o222)


def product_fingerprint(path: str | os.PathLike, ignore: tuple[str, ...] = ()) -> str:
    """Hash of a product's *content*, ignoring its creation time stamp and timings.

    For HDF5 products every dataset (name, dtype, shape, bytes) and every
    attribute except ``created``, the wall-clock timings (attributes named
    ``time_*``, docs/formats.md) and the names in ``ignore`` (for example
    attributes recording input file paths) is hashed; for other files the bytes.
    Two products with the same fingerprint hold bitwise identical data.

    Parameters
    ----------
    path : str or os.PathLike
        The product (``.h5``/``.hdf5``) or any other file.
    ignore : tuple of str
        Further root attribute names left out of the hash.

    Returns
    -------
    str
        Hexadecimal SHA-256 digest.
    """
    path = Path(path)
    if path.suffix not in (".h5", ".hdf5"):
        return file_digest(path)
    import h5py

    h = hashlib.sha256()

    def add_attrs(obj):
        for k in sorted(obj.attrs):
            if k == "created" or k.startswith("time_") or k in ignore:
                continue
            h.update(k.encode())
            h.update(repr(np.asarray(obj.attrs[k]).tolist()).encode())

    with h5py.File(path, "r") as f:
        add_attrs(f)
        names: list[str] = []
        f.visit(names.append)
        for name in sorted(names):
            obj = f[name]
            h.update(name.encode())
            add_attrs(obj)
            if isinstance(obj, h5py.Dataset):
                data = np.ascontiguousarray(obj[()])
                h.update(f"{data.dtype.str}{data.shape}".encode())
                h.update(data.tobytes())
    return h.hexdigest()
