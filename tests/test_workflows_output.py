"""Terminal output of ``mavispm run``: bars only on a terminal, one per stage started when
the stage starts, library warnings recorded per node instead of printed, --quiet/--verbose."""

from __future__ import annotations

import json
import threading
import warnings

from workflows_helpers import stand_in_registry, write_workflow

from mavispm.workflows import node_warnings, runner_cli
from mavispm.workflows.cli import main
from mavispm.workflows.runner import run_workflow


def _run_cli(tmp_path, monkeypatch, *extra):
    monkeypatch.setattr(
        "mavispm.workflows.stages.default_registry", stand_in_registry, raising=True
    )
    wf = write_workflow(tmp_path)
    return main(
        ["run", str(wf), "--workdir", str(tmp_path / "w"), "--scheduler", "threads", *extra]
    )


def test_warnings_are_recorded_per_node_and_not_printed(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WF_TEST_WARN", "frames")
    assert _run_cli(tmp_path, monkeypatch) == 0
    out = capsys.readouterr()
    assert "injected warning" not in out.err
    assert "2 library warning(s) recorded" in out.out
    summary = json.loads((tmp_path / "w" / "tiny" / "summary.json").read_text())
    for node in summary["nodes"]:
        expected = node["stage"] == "frames"
        assert any("UserWarning: injected warning in frames" in t for t in node["warnings"]) is (
            expected
        ), node["id"]


def test_not_a_terminal_gets_no_bars_and_quiet_prints_one_line(tmp_path, monkeypatch, capsys):
    assert _run_cli(tmp_path, monkeypatch) == 0
    out = capsys.readouterr()
    assert "\x1b[" not in out.err and "task/s" not in out.err and "s/task" not in out.err
    assert "cluster: 1 ran" in out.out
    assert _run_cli(tmp_path, monkeypatch, "--quiet") == 0
    out = capsys.readouterr()
    assert out.out.strip().splitlines() == [f"run directory: {tmp_path / 'w' / 'tiny'}"]
    assert out.err == ""


def test_verbose_logs_every_node(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WF_TEST_WARN", "stars")
    assert _run_cli(tmp_path, monkeypatch, "--verbose") == 0
    err = capsys.readouterr().err
    assert "mavispm: cluster: done in" in err
    assert "stars/main/e1: UserWarning: injected warning in stars" in err
    runner_cli.configure_logging()  # back to the default level for other tests


def test_bars_start_when_their_stage_starts(tmp_path, monkeypatch):
    """A stage's bar is created when its first task is submitted, not at launch."""
    created = []

    class Bar:
        def __init__(self, total, initial, desc, **kw):
            created.append(desc.strip())

        def update(self, n):
            pass

        def close(self):
            pass

    monkeypatch.setattr("tqdm.auto.tqdm", Bar)
    run_workflow(
        write_workflow(tmp_path),
        tmp_path / "w",
        scheduler="serial",
        registry=stand_in_registry(),
        progress=True,
    )
    assert created == ["cluster", "optics", "frames", "stars", "propermotions", "dynamics"]
    created.clear()
    run_workflow(
        write_workflow(tmp_path), tmp_path / "w", scheduler="serial", registry=stand_in_registry()
    )
    assert created == []  # all cached: no stage starts, no bar


def test_capture_is_per_thread():
    """Two threads warning at once each keep their own warnings."""
    results = {}
    barrier = threading.Barrier(2)

    def work(name):
        with node_warnings.capture() as caught:
            barrier.wait()
            warnings.warn(f"from {name}", UserWarning, stacklevel=1)
            barrier.wait()
        results[name] = list(caught)

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        threads = [threading.Thread(target=work, args=(n,)) for n in ("a", "b")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert [len(results[n]) for n in "ab"] == [1, 1]
    assert "from a" in results["a"][0] and "from b" in results["b"][0]


def test_report_lists_each_warning_once_with_its_nodes():
    from mavispm.workflows.report import warnings_section

    summary = {
        "nodes": [
            {"id": f"frames/I/e{i}", "warnings": ["UserWarning: w | x (a.py:1)"]} for i in range(5)
        ]
        + [{"id": "cluster", "warnings": []}]
    }
    text = warnings_section(summary)
    assert text.count("UserWarning") == 1 and "w \\| x" in text
    assert "frames/I/e0, frames/I/e1, frames/I/e2 and 2 more" in text
    assert "None." in warnings_section({"nodes": [{"id": "cluster"}]})
