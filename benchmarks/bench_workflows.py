"""Benchmark the workflow runner.

python benchmarks/bench_workflows.py [--quick]
    Runner overhead against the number of nodes, with the small seeded stand-in
    stages of the test suite: validation + expansion + hashing, a first run
    (serial and threads), and a fully cached second run (which must do no work).

python benchmarks/bench_workflows.py --workflow quickstart [--workdir DIR] [--scheduler S]
    Wall time per stage of a real workflow (quickstart, ngc3201_imbh,
    astrometric_budget, pm_accuracy or a TOML path), read from its summary.json,
    then the time of a cached re-run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))


def runner_overhead(quick: bool) -> None:
    from workflows_helpers import TINY_WORKFLOW, stand_in_registry, write_workflow

    from mavispm.workflows.cache import node_keys
    from mavispm.workflows.config import load_workflow
    from mavispm.workflows.graph import expand
    from mavispm.workflows.runner import run_workflow

    registry = stand_in_registry()
    print("runner overhead with stand-in stages (times in s)")
    print(
        f"{'scenes':>6} {'nodes':>6} {'load+expand+hash':>17} {'run serial':>11} {'run threads':>12} {'cached rerun':>13} {'per node':>9}"
    )
    for n_scenes in (1, 4) if quick else (1, 4, 16, 32):
        scenes = "".join(
            f'\n[scenes.s{i}]\njitter = "{0.05 + 0.01 * i:.2f} mas"\n' for i in range(n_scenes)
        )
        with tempfile.TemporaryDirectory() as tmp:
            wf_path = write_workflow(Path(tmp), TINY_WORKFLOW + scenes)
            t0 = time.perf_counter()
            wf = load_workflow(wf_path, registry)
            nodes = expand(wf)
            node_keys(nodes, registry)
            t_load = time.perf_counter() - t0
            times = {}
            for sched in ("serial", "threads"):
                t0 = time.perf_counter()
                run_workflow(
                    wf,
                    workdir=Path(tmp) / sched,
                    scheduler=sched,
                    registry=registry,
                    progress=False,
                )
                times[sched] = time.perf_counter() - t0
            t0 = time.perf_counter()
            again = run_workflow(
                wf,
                workdir=Path(tmp) / "serial",
                scheduler="serial",
                registry=registry,
                progress=False,
            )
            t_cached = time.perf_counter() - t0
            assert again.ran == [], "a cached re-run did stage work"
            print(
                f"{n_scenes:>6} {len(nodes):>6} {t_load:>17.3f} {times['serial']:>11.2f} "
                f"{times['threads']:>12.2f} {t_cached:>13.3f} {t_cached / len(nodes):>9.4f}"
            )
    print("threads/serial ratio < 1 means independent nodes overlapped.")


def workflow_timing(name: str, workdir: Path, scheduler: str | None) -> None:
    from mavispm.workflows.runner import run_workflow

    t0 = time.perf_counter()
    result = run_workflow(name, workdir=workdir, scheduler=scheduler)
    total = time.perf_counter() - t0
    summary = result.summary
    print(f"workflow {summary['workflow']}: executor {summary['executor']}, wall {total:.1f} s")
    print(f"{'stage':>14} {'tasks':>5} {'ran':>4} {'compute [s]':>12} {'max node [s]':>13}")
    for stage, st in summary["stages"].items():
        walls = [
            n["wall_s"] or 0.0
            for n in summary["nodes"]
            if n["stage"] == stage and n["status"] == "ran"
        ]
        print(
            f"{stage:>14} {st['tasks']:>5} {st['ran']:>4} {st['wall_s']:>12.1f} {max(walls, default=0.0):>13.1f}"
        )
    t0 = time.perf_counter()
    again = run_workflow(name, workdir=workdir, scheduler=scheduler, progress=False)
    print(f"cached re-run: {time.perf_counter() - t0:.1f} s, {len(again.ran)} nodes ran")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="small sizes only")
    parser.add_argument("--workflow", help="time a real workflow (shipped name or TOML path)")
    parser.add_argument("--workdir", type=Path, default=Path("bench-work"))
    parser.add_argument("--scheduler", default=None)
    args = parser.parse_args(argv)
    if args.workflow:
        workflow_timing(args.workflow, args.workdir, args.scheduler)
    else:
        runner_overhead(args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
