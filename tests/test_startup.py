"""Start-up of a ``mavispm`` process: what its imports and first compiled call cost.

``import mavispm.workflows.cli`` imports no astropy, h5py or numba; the program defers
``astropy.table``'s file-format connectors to their first use
(``core/table_preload.py``) and loads numba's cached kernels before numba's compiler
registries (``core/numba_start.py``). Each check runs in a fresh interpreter: the point
is what gets imported.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

from mavispm.core.blas_threads import BLAS_THREAD_VARIABLES


def _run(code: str, *args: str, env: dict | None = None) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout.strip().splitlines()


def test_cli_import_is_light():
    """Importing the CLI (and ``mavispm.core``'s errors) imports no astropy, h5py or numba:
    ``mavispm.core`` names its products lazily."""
    lines = _run(
        """
        import sys
        import mavispm.workflows.cli
        heavy = ("astropy", "h5py", "numba", "scipy", "mavispm.core.products")
        print(sorted(m for m in sys.modules if m.startswith(heavy)))
        import mavispm.core as core
        from mavispm.core import TableSpec, write_product
        print(core.read_product.__module__, TableSpec.__module__, "atomic_path" in dir(core))
        """
    )
    assert lines[0] == "[]"
    assert lines[1] == "mavispm.core.products mavispm.core.products True"


def test_deferred_table_connectors_load_on_first_use(tmp_path):
    """``astropy.table`` imported without ``astropy.io.ascii`` / ``fits`` / ``votable``; the
    first ``Table.write`` / ``read`` / ``get_formats`` loads them and round-trips the values."""
    lines = _run(
        """
        import sys
        from mavispm.core.table_preload import import_table_without_connectors
        print(import_table_without_connectors(), import_table_without_connectors())
        from astropy.table import QTable, Table
        io = ("astropy.io.ascii", "astropy.io.fits", "astropy.io.votable", "astropy.io.misc")
        print(sorted(m for m in sys.modules if m.startswith(io)))
        t = Table({"a": [1, 2, 3], "b": [0.5, -1.25, 1e300]})
        t.write(sys.argv[1] + "/t.ecsv")
        t.write(sys.argv[1] + "/t.fits")
        r1, r2 = Table.read(sys.argv[1] + "/t.ecsv"), QTable.read(sys.argv[1] + "/t.fits")
        print(r1["a"].tolist(), r1["b"].tolist(), r2["a"].tolist(), r2["b"].tolist())
        from astropy.io import registry
        print("ascii.ecsv" in registry.get_formats(Table)["Format"])
        """,
        str(tmp_path),
    )
    assert lines[0] == "True False"
    assert lines[1] == "[]"
    assert lines[2] == "[1, 2, 3] [0.5, -1.25, 1e+300] [1, 2, 3] [0.5, -1.25, 1e+300]"
    assert lines[3] == "True"


_KERNELS = """
import numba
import numpy as np


@numba.njit(cache=True)
def moments(x):
    out = np.empty(3)  # allocates: needs numba's runtime (NRT)
    out[0] = x.sum()
    out[1] = np.sqrt((x * x).sum())
    out[2] = np.sort(x)[x.size // 2]
    return out
"""


def test_cached_kernels_load_before_numba_registries(tmp_path):
    """A cached kernel loads and runs without numba's compiler registries (the first
    refresh, ~0.1 s; ``numba.typed.typeddict`` and ``numba.np.polynomial`` are only imported by it);
    a cache miss compiles as usual. Values against numpy's."""
    (tmp_path / "kern_mod.py").write_text(_KERNELS)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"))
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    code = """
        import sys
        import numpy as np
        from mavispm.core.numba_start import load_cached_kernels_first
        print(load_cached_kernels_first(), load_cached_kernels_first())
        import kern_mod
        x = np.random.default_rng(3).normal(size=101)
        got = kern_mod.moments(x)
        want = [x.sum(), np.sqrt((x * x).sum()), np.sort(x)[50]]
        print(np.allclose(got, want, rtol=1e-12, atol=1e-12), kern_mod.moments.stats.cache_hits)
        print("numba.np.polynomial" in sys.modules, "numba.typed.typeddict" in sys.modules)
        """
    cold = _run(code, env=env)
    warm = _run(code, env=env)
    assert cold[0] == warm[0] == "True False"
    assert cold[1].startswith("True Counter()")  # compiled (cache miss), registries loaded
    assert cold[2] == "True True"
    assert warm[1].startswith("True Counter({")  # loaded from the cache
    assert warm[2] == "False False"


def test_numba_config_imports_yaml_only_for_a_config_file(tmp_path, monkeypatch):
    """Without a ``.numba_config.yaml`` in the working directory numba's config runs
    without importing PyYAML, and still parses YAML on first use; with one, numba reads
    it as before (its setting takes effect)."""
    code = """
        import sys
        from mavispm.core.numba_start import defer_numba_yaml
        print(defer_numba_yaml(), defer_numba_yaml())
        import numba
        import numba.core.config as config
        print("yaml" in sys.modules, config._HAVE_YAML, config.DEBUG_CACHE)
        print(config.yaml.safe_load("a: [1, 2]"), "yaml" in sys.modules)
        """
    bare, with_file = tmp_path / "bare", tmp_path / "with_file"
    bare.mkdir()
    with_file.mkdir()
    (with_file / ".numba_config.yaml").write_text("debug_cache: 1\n")
    env = dict(os.environ)
    env.pop("NUMBA_DEBUG_CACHE", None)
    monkeypatch.chdir(bare)
    assert _run(code, env=env) == ["True False", "False True 0", "{'a': [1, 2]} True"]
    monkeypatch.chdir(with_file)
    assert _run(code, env=env) == ["True False", "True True 1", "{'a': [1, 2]} True"]


def _tiny_frames_inputs(tmp_path):
    from render_helpers import epoch_table
    from test_render_fast_paths import _write_psf_database

    from mavispm.core.catalogue import write_catalogue

    _write_psf_database(tmp_path / "psfs.fits")
    rng = np.random.default_rng(7)
    t = epoch_table(*rng.uniform([-0.5, -0.5, 17], [0.5, 0.5, 23], (25, 3)).T)
    write_catalogue(tmp_path / "cat.h5", {"e0": t})
    (tmp_path / "scene.toml").write_text(
        "[detector]\nnx = 160\nny = 160\n"
        f'[optics.psf]\nmode = "file"\nfile = "{tmp_path / "psfs.fits"}"\n'
        'pixel_scale = "3.75 mas"\nstamp_size = "0.12375 arcsec"\n'
    )


def _datasets(path):
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, o: out.__setitem__(n, o[()]) if isinstance(o, h5py.Dataset) else 0)
    return out


def test_warm_frames_program_defers_connectors_and_registries(tmp_path):
    """A warm ``mavispm simulate frames`` process imports neither astropy's ascii / fits /
    votable connectors nor numba's compiler registries nor PyYAML nor ``scipy.fft`` (the
    stamps' inverse FFTs load its pocketfft extension module alone) nor ``numba.np.arrayobj``
    (no cached kernel of the frames path calls ``np.empty``, whose environment names it),
    and writes the same frame, bit for bit, as ``main(argv)`` called from Python (which
    changes no import)."""
    _tiny_frames_inputs(tmp_path)
    script = """
        import atexit, json, sys, runpy
        watch = ("astropy.io.ascii", "astropy.io.votable", "astropy.io.misc", "numba.typed.",
                 "numba.np.polynomial", "cffi", "yaml", "scipy.fft", "numba.np.arrayobj")
        atexit.register(lambda: print("LOADED", json.dumps(
            sorted(m for m in sys.modules if m.startswith(watch)))))
        if sys.argv[1] == "program":
            sys.argv = ["mavispm"] + sys.argv[2:]
            runpy.run_module("mavispm.workflows.cli", run_name="__main__")
        else:
            from mavispm.workflows.cli import main
            sys.exit(main(sys.argv[2:]))
        """
    args = ["simulate", "frames", str(tmp_path / "cat.h5"), "--scene",
            str(tmp_path / "scene.toml"), "--cache-dir", str(tmp_path / "cache"), "-o"]  # fmt: skip
    _run(script, "program", *args, str(tmp_path / "cold.h5"))  # computes the caches
    warm = _run(script, "program", *args, str(tmp_path / "warm.h5"))
    library = _run(script, "library", *args, str(tmp_path / "library.h5"))
    assert json.loads(warm[-1].removeprefix("LOADED ")) == []
    assert "numba.typed.typeddict" in json.loads(library[-1].removeprefix("LOADED "))
    a, b = _datasets(tmp_path / "warm.h5"), _datasets(tmp_path / "library.h5")
    assert sorted(a) == sorted(b) and "image" in " ".join(a)
    for name in a:
        assert np.array_equal(a[name], b[name]), name


def test_program_imports_with_the_collector_off():
    """The program keeps the cyclic collector off while the command's modules are imported,
    then freezes them and turns it back on; ``main(argv)`` called from Python leaves the
    collector alone."""
    code = """
        import gc, sys
        import importlib.abc
        seen = []

        class Watch(importlib.abc.MetaPathFinder):
            def find_spec(self, fullname, path, target=None):
                if fullname == "mavispm.simulate.render.cli":
                    seen.append(gc.isenabled())
                return None

        sys.meta_path.insert(0, Watch())
        from mavispm.workflows import cli
        words = ["simulate", "frames", "--help"]
        sys.argv = ["mavispm"] + words
        try:
            cli.main({call})
        except SystemExit:
            pass
        print(seen, gc.isenabled(), gc.get_freeze_count() > 0)
        """
    assert _run(code.format(call=""))[-1] == "[False] True True"
    assert _run(code.format(call="words"))[-1] == "[True] True False"


def test_wrap_on_import_runs_its_wrapper_once_around_the_module():
    """The one import hook of the start-up loaders (``core/import_hook.py``): the wrapper
    runs around the module's own code on its first import, the hook then leaves
    ``sys.meta_path``, and a second hook for the same module is refused."""
    code = """
        import sys
        from mavispm.core.import_hook import WrapOnImport, wrap_on_import
        calls = []
        def wrap(exec_module, module):
            calls.append(hasattr(module, "rgb_to_hsv"))
            exec_module(module)
            calls.append(hasattr(module, "rgb_to_hsv"))
        assert "colorsys" not in sys.modules
        print(wrap_on_import("colorsys", wrap), wrap_on_import("colorsys", wrap))
        import colorsys
        import colorsys as again
        print(calls, colorsys.rgb_to_hsv(1.0, 0.0, 0.0))
        print(any(isinstance(f, WrapOnImport) for f in sys.meta_path))
    """
    lines = _run(code)
    assert lines[0] == "True False"
    assert lines[1] == "[False, True] (0.0, 1.0, 1.0)"
    assert lines[2] == "False"


def test_program_keeps_freed_memory_for_its_next_arrays():
    """The ``simulate frames`` program (``main()`` reading ``sys.argv``) sets glibc's
    allocator to keep what it frees (``core/malloc_policy.py``): a 24 MB array freed by the
    main thread is reused by the next one and by a worker thread's, with no fresh page
    faults (the kernel's count); ``main(argv)`` called from Python, and the program of a
    command it was not measured on, leave the allocator as it is (each array faulted in
    afresh: one fault per 4 KB page)."""
    code = """
        import resource, sys, threading
        import numpy as np
        from mavispm.workflows import cli
        words = {words}
        sys.argv = ["mavispm"] + words
        try:
            cli.main({call})
        except SystemExit:
            pass

        def faults_of_a_fresh_array():
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            a = np.empty(3 << 20)  # 24 MB
            a.fill(1.0)
            del a
            return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

        counts = [faults_of_a_fresh_array(), faults_of_a_fresh_array()]
        thread = threading.Thread(target=lambda: counts.append(faults_of_a_fresh_array()))
        thread.start()
        thread.join()
        print(counts)
        """
    env = {**os.environ, "NUMPY_MADVISE_HUGEPAGE": "0"}  # 4 KB pages: one fault per page
    for k in ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"):
        env.pop(k, None)
    frames = '["simulate", "frames", "--help"]'
    program = json.loads(_run(code.format(words=frames, call=""), env=env)[-1])
    library = json.loads(_run(code.format(words=frames, call="words"), env=env)[-1])
    measure = '["measure", "stars", "--help"]'
    other = json.loads(_run(code.format(words=measure, call=""), env=env)[-1])
    pages = (3 << 20) * 8 // 4096
    assert program[0] >= 0.9 * pages  # the first array is new memory either way
    assert max(program[1:]) < 0.02 * pages  # then reused, in the main thread and a worker
    for counts in (library, other):  # glibc's defaults: unmapped, faulted in again
        assert min(counts[1:]) >= 0.9 * pages


@pytest.mark.skipif(
    (os.cpu_count() or 1) < 2 or not os.path.isdir("/proc/self/task"),
    reason="OpenBLAS starts worker threads only on several cores; counted in /proc",
)
def test_frames_program_loads_openblas_without_worker_threads():
    """The ``simulate frames`` program (``main()`` reading ``sys.argv``) loads numpy's and
    scipy's OpenBLAS (numba's BLAS module) with one thread, so no idle worker busy-waits on
    the other cores (``core/blas_threads.py``): the process then has one thread (the
    kernel's count, ``/proc/self/task``). A count set in the environment, ``main(argv)``
    called from Python, and other commands keep OpenBLAS's own workers (more threads)."""
    code = """
        import os, sys
        from mavispm.workflows import cli
        words = {words}
        sys.argv = ["mavispm"] + words
        try:
            cli.main({call})
        except SystemExit:
            pass
        import numpy as np
        import numba.np.arraymath  # scipy's OpenBLAS (scipy.linalg.cython_blas)
        np.ones((300, 300)) @ np.ones((300, 300))  # a product numpy's OpenBLAS may split
        print(len(os.listdir("/proc/self/task")))
        """
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    frames = '["simulate", "frames", "--help"]'
    measure = '["measure", "stars", "--help"]'
    program = int(_run(code.format(words=frames, call=""), env=env)[-1])
    library = int(_run(code.format(words=frames, call="words"), env=env)[-1])
    other = int(_run(code.format(words=measure, call=""), env=env)[-1])
    chosen = int(
        _run(code.format(words=frames, call=""), env={**env, "OPENBLAS_NUM_THREADS": "2"})[-1]
    )
    assert program == 1
    assert min(library, other, chosen) > 1
