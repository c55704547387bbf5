"""The workflow runner: cached, resumable execution of the stage graph.

:func:`run_workflow` loads and validates a workflow file, expands it into
stage tasks (:mod:`~mavispm.workflows.graph`), computes every task's content
key (:mod:`~mavispm.workflows.cache`), runs the tasks whose products are not
in the store yet on an executor (:mod:`~mavispm.workflows.executors`), as soon
as their inputs exist, and finally writes the run directory::

    <workdir>/store/<stage>/<key>/        the product cache (shared by all runs)
    <workdir>/<name>/products/<node id>/  the run's products (links into the store)
    <workdir>/<name>/summary.json         machine-readable summary
    <workdir>/<name>/report.md            human report with plots
    <workdir>/<name>/workflow.toml        copy of the workflow file

A second run of an unchanged workflow does no stage work; after a change only
the affected nodes run; after an interruption (exception, kill, power cut) the
next run redoes only nodes without a completion marker.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import logging
import os
import shutil
import threading
import time
import traceback
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from mavispm.core.errors import ConfigError, MavispmError
from mavispm.core.paths import check_name, contained
from mavispm.workflows import node_warnings
from mavispm.workflows.cache import Store, canonical_json, exclusive_lock, node_keys
from mavispm.workflows.config import Workflow, load_workflow
from mavispm.workflows.executors import make_executor
from mavispm.workflows.graph import Node, expand
from mavispm.workflows.registry import StageRegistry, StageSpec, resolve

if TYPE_CHECKING:
    import distributed

__all__ = [
    "RUNNING",
    "RunResult",
    "Task",
    "TaskError",
    "WorkflowError",
    "canonical_json_pretty",
    "check_workdir",
    "execute_task",
    "plan_workflow",
    "run_workflow",
]

log = logging.getLogger(__name__)

DEFAULT_WORKDIR = "mavispm-work"


class WorkflowError(MavispmError):
    """One or more tasks of a workflow failed (finished products stay cached)."""


class TaskError(MavispmError):
    """A stage raised an exception while running one node."""


@dataclass(frozen=True)
class Task:
    """Everything a worker needs to run one node (picklable).

    Parameters
    ----------
    node_id : str
    stage : StageSpec
    key : str
    settings, params : dict
    seed : int or None
    inputs : dict
        Input name to product path (str) or list of paths.
    store_root : str
    """

    node_id: str
    stage: StageSpec
    key: str
    settings: dict
    params: dict
    seed: int | None
    inputs: dict
    store_root: str


#: Serialises tasks of stages marked ``exclusive`` (not thread-safe) among the threads
#: of one process; process pools and dask worker processes each have their own.
_EXCLUSIVE_LOCK = threading.Lock()


def execute_task(task: Task) -> dict:
    """Run one node in a fresh (or resumed) partial folder and commit it.

    Parameters
    ----------
    task : Task
        The node to run.

    Returns
    -------
    dict
        The completion record: ``products`` (name to path relative to the node
        folder), ``wall_s``, ``metrics``, ``stage``, ``key``, ``node``.

    Raises
    ------
    TaskError
        Naming the node; the traceback is saved as ``error.txt`` in the partial folder.
    """
    store = Store(task.store_root)
    done = store.lookup(task.stage.name, task.key)
    if done is not None:  # finished meanwhile by another run or worker
        return done
    with store.claim(task.stage.name, task.key) as (outdir, done):
        if done is not None:
            return done
        record = _run_in(outdir, task)
        store.commit(task.stage.name, task.key, record)
    return record


def _run_in(outdir: Path, task: Task) -> dict:
    """Call the stage adapter in ``outdir``; return the completion record."""
    inputs = {
        name: [Path(p) for p in ref] if isinstance(ref, list) else Path(ref)
        for name, ref in task.inputs.items()
    }
    start = time.perf_counter()
    lock = _EXCLUSIVE_LOCK if task.stage.exclusive else contextlib.nullcontext()
    interrupted = _begin_attempt(outdir)
    try:
        run = resolve(task.stage.run)
        with lock, node_warnings.capture() as caught:
            products = run(inputs, dict(task.settings), dict(task.params), task.seed, outdir)
        rel = _relative_products(products, outdir, task)
        (outdir / RUNNING).unlink(missing_ok=True)
        summarize = resolve(task.stage.summarize)
        metrics = summarize({k: outdir / v for k, v in rel.items()}) if summarize else {}
    except Exception as exc:
        (outdir / RUNNING).unlink(missing_ok=True)  # a failure, reported below; not a loss
        (outdir / "error.txt").write_text(traceback.format_exc())
        if isinstance(exc, MavispmError):
            raise TaskError(f"{task.node_id}: {exc}") from None
        raise TaskError(
            f"{task.node_id}: {type(exc).__name__}: {exc} (traceback in {outdir / 'error.txt'})"
        ) from None
    return {
        "node": task.node_id,
        "stage": task.stage.name,
        "key": task.key,
        "products": rel,
        "metrics": metrics or {},
        "wall_s": time.perf_counter() - start,
        "seed": task.seed,
        "settings": task.settings,
        "params": task.params,
        "finished": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "interrupted_attempts": interrupted,
        "warnings": list(caught),
    }


#: Marker of a task attempt in progress in its partial folder. Found at the start
#: of an attempt, it means an earlier attempt died without finishing or failing:
#: a killed run, or a lost dask worker whose task the scheduler retried.
RUNNING = ".running"


def _begin_attempt(outdir: Path) -> int:
    """Mark an attempt as running; return how many earlier attempts died in this folder."""
    marker = outdir / RUNNING
    try:
        died = int(marker.read_text() or 0)
    except (OSError, ValueError):
        died = 0
    marker.write_text(str(died + 1))
    return died


def _relative_products(products, outdir: Path, task: Task) -> dict[str, str]:
    if not isinstance(products, Mapping) or "main" not in products:
        raise TypeError(
            f"stage '{task.stage.name}' adapter must return a dict of product paths with a "
            f"'main' entry, got {products!r}"
        )
    rel = {}
    root = outdir.resolve()
    for name, path in products.items():
        p = Path(path).resolve()
        if not p.is_file():
            raise FileNotFoundError(
                f"stage '{task.stage.name}' did not write product '{name}' at {p}"
            )
        try:
            rel[name] = str(p.relative_to(root))
        except ValueError:
            raise ValueError(
                f"stage '{task.stage.name}' wrote product '{name}' outside its folder: {p}"
            ) from None
    return rel


@dataclass
class RunResult:
    """Outcome of :func:`run_workflow`.

    Parameters
    ----------
    rundir : pathlib.Path
    summary : dict
        Contents of summary.json.
    ran : list of str
        Node ids whose stage ran in this call.
    cached : list of str
        Node ids taken from the store.
    """

    rundir: Path
    summary: dict
    ran: list[str] = field(default_factory=list)
    cached: list[str] = field(default_factory=list)

    def product(self, node_id: str, name: str = "main") -> Path:
        """Path of a node's product in the run directory.

        Parameters
        ----------
        node_id : str
            The node id (as in ``summary.json``).
        name : str
            Product name (``"main"`` feeds downstream stages).

        Returns
        -------
        pathlib.Path
            The product's path.

        Raises
        ------
        KeyError
            When no node has that id.
        """
        for node in self.summary["nodes"]:
            if node["id"] == node_id:
                return self.rundir / node["products"][name]
        raise KeyError(node_id)


def run_workflow(
    workflow: Workflow | str | os.PathLike,
    workdir: str | os.PathLike | None = None,
    scheduler: str | distributed.Client | None = None,
    force: bool = False,
    registry: StageRegistry | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> RunResult:
    """Run a workflow, reusing every product already in the work directory's store.

    Parameters
    ----------
    workflow : Workflow or path
        A loaded workflow, a TOML path, or a shipped workflow name.
    workdir : path, optional
        Work directory (default ``./mavispm-work``).
    scheduler : str or distributed.Client, optional
        ``"threads"``, ``"processes"``, ``"serial"``, a dask scheduler address or
        client; default: the workflow's ``[workflow] executor``.
    force : bool
        Recompute every node of this workflow even when cached.
    registry : StageRegistry, optional
        Stage functions (default: the real stages).
    workers : int, optional
        Local pool size (default: ``[workflow] workers``, 0 = all CPUs).
    progress : bool
        Show one progress bar per stage, each started when the stage's first task
        starts (the command line shows them only on a terminal).

    Returns
    -------
    RunResult

    Raises
    ------
    ConfigError
        For an invalid workflow file, before any work.
    WorkflowError
        When tasks fail; finished products stay cached so a rerun resumes.
    """
    if registry is None:
        from mavispm.workflows.stages import default_registry

        registry = default_registry()
    if not isinstance(workflow, Workflow):
        workflow = load_workflow(workflow, registry)
    workdir = check_workdir(workdir)
    if workers is not None and (not isinstance(workers, int) or workers < 0):
        raise ConfigError(
            f"expected an integer >= 0 (0 = all CPUs), got {workers!r}", key="--workers"
        )
    nodes = expand(workflow)
    keys = node_keys(nodes, registry)
    store = Store(workdir / "store")
    executor = make_executor(
        scheduler or workflow.meta.executor,
        workflow.meta.workers if workers is None else workers,
    )
    start = time.perf_counter()
    with executor, warnings.catch_warnings():
        warnings.simplefilter("always")  # every node records its own warnings
        node_warnings.install()
        records, ran_keys, failures = _execute(
            nodes, keys, store, registry, executor, force, progress
        )
    wall = time.perf_counter() - start
    rundir = contained(workdir, check_name(workflow.name, "workflow.name"), "run directory")
    summary = _summary(
        workflow, nodes, keys, records, ran_keys, failures, executor.name, wall, workdir
    )
    reports = {s: registry[s].report for s in summary["stages"] if registry[s].report is not None}
    summary["stage_reports"] = sorted(reports)  # names only: a run directory never names code
    _materialize(rundir, summary, nodes, keys, store, workflow)
    if failures:
        lines = "; ".join(failures.values())
        raise WorkflowError(
            f"{len(failures)} task(s) failed: {lines}. Finished products are cached in "
            f"{store.root}; fix the problem and run again to resume."
        )
    if workflow.outputs.report:
        from mavispm.workflows.report import write_report

        write_report(rundir, reports=reports)
    ran = [n["id"] for n in summary["nodes"] if n["status"] == "ran"]
    cached = [n["id"] for n in summary["nodes"] if n["status"] == "cached"]
    return RunResult(rundir=rundir, summary=summary, ran=ran, cached=cached)


def check_workdir(workdir: str | os.PathLike | None) -> Path:
    """The work directory as an absolute path; it must be a folder (or not exist yet).

    Parameters
    ----------
    workdir : str or os.PathLike or None
        The work directory (None: the default ``DEFAULT_WORKDIR``).

    Returns
    -------
    pathlib.Path
        Its absolute path.

    Raises
    ------
    ConfigError
        When it (or a folder above it) is a file, or a store inside it is a file.
    """
    path = Path(workdir or DEFAULT_WORKDIR).resolve()
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                raise ConfigError(
                    f"'{p}' is a file; expected a work directory (a folder, created if missing)",
                    key="--workdir",
                )
            break
    if (path / "store").exists() and not (path / "store").is_dir():
        raise ConfigError(f"'{path / 'store'}' is not a folder", key="--workdir")
    return path


def plan_workflow(
    workflow: Workflow | str | os.PathLike,
    workdir: str | os.PathLike | None = None,
    registry: StageRegistry | None = None,
) -> list[dict]:
    """What a run would do, without doing it.

    Parameters
    ----------
    workflow : Workflow or str or os.PathLike
        A validated workflow or a workflow file (or shipped workflow name).
    workdir : str or os.PathLike, optional
        The work directory whose store is looked up.
    registry : StageRegistry, optional
        The stages (default: the shipped ones).

    Returns
    -------
    list of dict
        Per node (execution order): ``id``, ``stage``, ``key`` and ``status``
        (``"cached"`` when its product is in the store, ``"shared"`` when an
        earlier node of this run has the same key and so computes it, else
        ``"to run"``).
    """
    if registry is None:
        from mavispm.workflows.stages import default_registry

        registry = default_registry()
    if not isinstance(workflow, Workflow):
        workflow = load_workflow(workflow, registry)
    store = Store(check_workdir(workdir) / "store")
    nodes = expand(workflow)
    keys = node_keys(nodes, registry)
    plan, seen = [], set()
    for nid, node in nodes.items():
        key = keys[nid]
        if store.lookup(node.stage, key):
            status = "cached"
        else:
            status = "shared" if key in seen else "to run"
        seen.add(key)
        plan.append({"id": nid, "stage": node.stage, "key": key, "status": status})
    return plan


def _execute(nodes, keys, store: Store, registry, executor, force: bool, progress: bool):
    """Run every incomplete task when its inputs are done; return records by key."""
    from tqdm.auto import tqdm

    by_key: dict[str, Node] = {}
    for nid, node in nodes.items():
        by_key.setdefault(keys[nid], node)
    deps = {k: {keys[u] for u in n.upstream()} for k, n in by_key.items()}
    records: dict[str, dict] = {}
    if force:
        for k, n in by_key.items():
            store.invalidate(n.stage, k)
    else:
        for k, n in by_key.items():
            rec = store.lookup(n.stage, k)
            if rec is not None:
                records[k] = rec
    bars: dict = {}

    def bar(stage: str):
        """The stage's progress bar, started when its first task starts (terminal only)."""
        if stage not in bars:
            total = sum(1 for n in by_key.values() if n.stage == stage)
            done = sum(1 for k, n in by_key.items() if n.stage == stage and k in records)
            bars[stage] = tqdm(
                total=total,
                initial=done,
                desc=f"{stage:>13}",
                unit="task",
                position=len(bars),
                leave=True,
                disable=not progress,
            )
        return bars[stage]

    todo = [k for k in by_key if k not in records]
    failures: dict[str, str] = {}
    blocked: set[str] = set()
    ran: set[str] = set()
    running: dict = {}
    try:
        while todo or running:
            for k in list(todo):
                if deps[k] & (blocked | set(failures)):
                    blocked.add(k)
                    todo.remove(k)
                elif deps[k] <= set(records):
                    node = by_key[k]
                    task = _task(node, k, nodes, keys, records, store, registry)
                    bar(node.stage)
                    running[executor.submit(execute_task, task)] = k
                    todo.remove(k)
            if not running:
                break
            done, _ = executor.wait(running)
            for fut in done:
                k = running.pop(fut)
                node = by_key[k]
                try:
                    records[k] = executor.outcome(fut)
                    ran.add(k)
                    log.info("%s: done in %.1f s", node.id, records[k]["wall_s"])
                    for text in records[k].get("warnings", []):
                        log.debug("%s: %s", node.id, text)
                except Exception as exc:  # recorded, dependants skipped, others continue
                    failures[k] = (
                        str(exc)
                        if isinstance(exc, MavispmError)
                        else f"{node.id}: {type(exc).__name__}: {exc}"
                    )
                    log.warning("failed: %s", failures[k])
                bar(node.stage).update(1)
    finally:
        for bar in bars.values():
            bar.close()
    for k in blocked:
        failures.setdefault(k, f"{by_key[k].id}: not run (an input failed)")
    return records, ran, failures


def _task(node: Node, key: str, nodes, keys, records, store: Store, registry) -> Task:
    def path_of(nid: str) -> str:
        upstream = nodes[nid]
        rec = records[keys[nid]]
        return str(store.final_dir(upstream.stage, keys[nid]) / rec["products"]["main"])

    inputs: dict = {name: str(p) for name, p in node.external.items()}
    for name, ref in node.inputs.items():
        inputs[name] = [path_of(r) for r in ref] if isinstance(ref, list) else path_of(ref)
    return Task(
        node_id=node.id,
        stage=registry[node.stage],
        key=key,
        settings=node.settings,
        params=node.params,
        seed=node.seed,
        inputs=inputs,
        store_root=str(store.root),
    )


def _summary(
    workflow: Workflow, nodes, keys, records, ran_keys, failures, executor_name, wall, workdir
):
    from mavispm import __version__

    out_nodes = []
    stages: dict[str, dict] = {}
    seen: set[str] = set()
    for nid, node in nodes.items():
        k = keys[nid]
        rec = records.get(k)
        status = "failed" if k in failures else ("ran" if k in ran_keys else "cached")
        if rec is None and status == "cached":
            status = "missing"
        entry = {
            "id": nid,
            "stage": node.stage,
            "key": k,
            "status": status,
            "wall_s": None if rec is None else rec["wall_s"],
            "products": {}
            if rec is None
            else {
                name: f"products/{nid}/{Path(rel).name}" for name, rel in rec["products"].items()
            },
            "metrics": {} if rec is None else rec.get("metrics", {}),
            "warnings": [] if rec is None else rec.get("warnings", []),
            "labels": node.labels,
            "sweep": node.sweep,
            "seed": node.seed,
        }
        if k in failures:
            entry["error"] = failures[k]
        if status == "ran" and rec is not None and rec.get("interrupted_attempts"):
            entry["interrupted_attempts"] = rec["interrupted_attempts"]
        out_nodes.append(entry)
        st = stages.setdefault(
            node.stage, {"tasks": 0, "ran": 0, "cached": 0, "failed": 0, "wall_s": 0.0}
        )
        if k in seen:
            continue  # a node shared by several variants counts once
        seen.add(k)
        st["tasks"] += 1
        st[status if status in st else "failed"] += 1
        if rec is not None and status == "ran":
            st["wall_s"] += rec["wall_s"]
    return {
        "workflow": workflow.name,
        "description": workflow.meta.description,
        "source": str(workflow.source),
        "mavispm_version": __version__,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "executor": executor_name,
        "workdir": str(workdir),
        "wall_s": wall,
        "outputs": {"tables": list(workflow.outputs.tables), "plots": workflow.outputs.plots},
        "sweep_axes": [
            {"name": a.name, "parameter": a.parameter, "values": list(a.values)}
            for a in workflow.axes
        ],
        "studies": sorted({v.study for v in workflow.variants if v.study}),
        "stages": stages,
        "nodes": out_nodes,
        # tasks redone after an attempt died (a killed run or a lost dask worker)
        "interrupted_tasks": sorted({n["id"] for n in out_nodes if n.get("interrupted_attempts")}),
    }


def _materialize(
    rundir: Path, summary: dict, nodes, keys, store: Store, workflow: Workflow
) -> None:
    """Write the run directory: product links, summary.json, a copy of the workflow.

    Runs sharing the run directory (two terminals on one workflow) take turns: the
    directory is rebuilt under an OS file lock.
    """
    rundir.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(rundir / ".materialize.lock"):
        _materialize_locked(rundir, summary, nodes, keys, store, workflow)


def _materialize_locked(
    rundir: Path, summary: dict, nodes, keys, store: Store, workflow: Workflow
) -> None:
    from mavispm.core.atomic import atomic_path

    new = rundir / "products.new"
    shutil.rmtree(new, ignore_errors=True)
    for entry in summary["nodes"]:
        node = nodes[entry["id"]]
        final = store.final_dir(node.stage, entry["key"])
        rec = store.lookup(node.stage, entry["key"])
        if rec is None:
            continue
        for name, rel in rec["products"].items():
            target = contained(rundir, entry["products"][name], "product")
            target = contained(new, target.relative_to(rundir / "products"), "product")
            target.parent.mkdir(parents=True, exist_ok=True)
            _link(final / rel, target, workflow.outputs.link)
    old = rundir / "products.old"
    shutil.rmtree(old, ignore_errors=True)
    if (rundir / "products").exists():
        os.rename(rundir / "products", old)
    new.mkdir(exist_ok=True)
    os.rename(new, rundir / "products")
    shutil.rmtree(old, ignore_errors=True)
    with atomic_path(rundir / "summary.json") as tmp:
        tmp.write_text(canonical_json_pretty(summary))
    with atomic_path(rundir / "workflow.toml") as tmp:
        shutil.copyfile(workflow.source, tmp)


def canonical_json_pretty(obj: object) -> str:
    """Indented JSON text (keys sorted) for files people read.

    Parameters
    ----------
    obj : object
        JSON-serialisable data (converted like :func:`canonical_json`).

    Returns
    -------
    str
        One-space-indented JSON ending in a newline.
    """
    import json

    return json.dumps(json.loads(canonical_json(obj)), indent=1, sort_keys=True) + "\n"


def _link(src: Path, dst: Path, mode: str) -> None:
    """Make a store product appear in a run directory.

    ``hardlink`` and ``symlink`` share the store's read-only file (an edit through
    the run directory is refused, or detected by the store's digest check);
    ``copy`` (also the fall-back across file systems) makes a private writable copy.
    """
    from mavispm.core.atomic import current_umask

    if mode == "symlink":
        os.symlink(src, dst)
        return
    if mode == "hardlink":
        try:
            os.link(src, dst)
            return
        except OSError:
            pass  # another file system: fall back to a copy
    shutil.copyfile(src, dst)
    os.chmod(dst, 0o666 & ~current_umask())
