"""Seeded products are bitwise identical whatever the executor, dask included."""

from __future__ import annotations

import pytest
from workflows_helpers import (
    TINY_WORKFLOW,
    fingerprints,
    read_log,
    stand_in_registry,
    write_workflow,
)

from mavispm.core.errors import ConfigError
from mavispm.workflows.executors import make_executor
from mavispm.workflows.runner import run_workflow

#: Two scenes: independent branches that can run concurrently.
PARALLEL = TINY_WORKFLOW + '\n[scenes.A]\n[scenes.B]\njitter = "0.2 mas"\n'


def _run(wf, workdir, scheduler):
    return run_workflow(
        wf, workdir=workdir, scheduler=scheduler, registry=stand_in_registry(), progress=False
    )


@pytest.fixture(scope="module")
def serial_reference(tmp_path_factory):
    folder = tmp_path_factory.mktemp("serial")
    wf = write_workflow(folder, PARALLEL)
    result = _run(wf, folder / "w", "serial")
    prints = fingerprints(result.rundir)
    assert len(prints) == 1 + 2 * (1 + 4 + 2)  # every product present
    return wf, prints


def test_thread_pool_matches_serial(serial_reference, tmp_path):
    wf, prints = serial_reference
    assert fingerprints(_run(wf, tmp_path / "w", "threads").rundir) == prints


def test_dask_localcluster_on_loopback_matches_in_process(serial_reference, tmp_path, monkeypatch):
    distributed = pytest.importorskip("distributed")
    wf, prints = serial_reference
    log = tmp_path / "calls.log"
    monkeypatch.setenv("WF_TEST_LOG", str(log))
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tcp://127.0.0.1:")
        result = _run(wf, tmp_path / "w", address)  # connects by address, like --scheduler
        assert result.summary["executor"].startswith("dask(tcp://127.0.0.1")
        assert fingerprints(result.rundir) == prints
        # cached on the second run, through dask too
        n = len(read_log(log))
        assert _run(wf, tmp_path / "w", address).ran == []
        assert len(read_log(log)) == n


def test_unreachable_scheduler_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="cannot connect to the dask scheduler"):
        make_executor("tcp://127.0.0.1:9", timeout=1)  # discard port: nothing listens


def test_unknown_scheduler_name():
    with pytest.raises(ConfigError, match="unknown scheduler 'gpu'"):
        make_executor("gpu")
