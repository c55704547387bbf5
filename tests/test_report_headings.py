"""The run report is one Markdown document: one ``#`` title, and every stage report nested
below its ``## <stage> report`` / ``### <group>`` headings (issue 19: the measure stage's
page used to put its own ``#`` title inside the run report)."""

from __future__ import annotations

import re

from workflows_helpers import TINY_WORKFLOW, stand_in_registry, write_workflow

from mavispm.core.atomic import atomic_path
from mavispm.workflows.report import nest_headings, write_report
from mavispm.workflows.runner import run_workflow

#: A stage report page written as a standalone document (like the measure and
#: proper-motion stages' pages): its own H1, sub-sections, and a code block with '#'.
PAGE = "# Astrometric accuracy: e0\n\ntext\n\n## Per magnitude\n\n```\n# not a heading\n```\n"


def write_page_report(paths, outdir):
    """A stand-in stage report writing :data:`PAGE`."""
    outdir.mkdir(parents=True, exist_ok=True)
    with atomic_path(outdir / "page.md") as tmp:
        tmp.write_text(PAGE)
    return [outdir / "page.md"]


def headings(markdown: str) -> list[tuple[int, str]]:
    """(level, text) of the ATX headings outside fenced code blocks."""
    out, fenced = [], False
    for line in markdown.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"^ {0,3}(#{1,6})\s+(.*)", line)):
            out.append((len(m.group(1)), m.group(2)))
    return out


def test_stage_report_pages_are_nested_in_the_run_report(tmp_path):
    wf = write_workflow(tmp_path, TINY_WORKFLOW)
    result = run_workflow(
        wf, workdir=tmp_path / "work", registry=stand_in_registry(), progress=False
    )
    path = write_report(result.rundir, reports={"stars": f"{__name__}:write_page_report"})
    found = headings(path.read_text())
    assert [lvl for lvl, _ in found].count(1) == 1 and found[0][0] == 1
    for (before, _), (after, text) in zip(found, found[1:]):
        assert after <= before + 1, f"heading {text!r} skips a level after level {before}"
    titles = {text: lvl for lvl, text in found}
    assert titles["stars report"] == 2
    assert titles["Astrometric accuracy: e0"] == 4 and titles["Per magnitude"] == 5
    assert "# not a heading" in path.read_text()  # code is left as it is


def test_nest_headings_keeps_text_and_caps_at_six():
    assert nest_headings("#### deep\n###### deeper\nplain # text", 3) == (
        "###### deep\n###### deeper\nplain # text"
    )
    assert nest_headings("#hashtag\n# Title", 1) == "#hashtag\n## Title"
