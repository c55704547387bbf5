"""Accuracy/speed knobs apart from the model settings (issue 19, item 6): the cluster, optics
and proper-motion stages each have one frozen knobs object, set from ``[<stage>.knobs]`` or,
as before, from the knobs' earlier places; the spelling never changes a cache key, a knob's
value changes the key of exactly its node and the nodes downstream (docs/workflows.md)."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import pytest

from mavispm.core.config import to_mapping
from mavispm.core.errors import ConfigError
from mavispm.core.knobs import gather_knobs, scatter_knobs
from mavispm.dynamics.cli import validate_settings as validate_dynamics
from mavispm.dynamics.settings import DynamicsKnobs
from mavispm.measure.propermotions.settings import ProperMotionKnobs
from mavispm.measure.propermotions.settings import validate_settings as validate_pm
from mavispm.simulate.cluster.cli import validate_settings as validate_cluster
from mavispm.simulate.cluster.settings import ClusterKnobs, ClusterSettings
from mavispm.simulate.optics.model import OpticsKnobs
from mavispm.simulate.optics.model import validate_settings as validate_optics
from mavispm.workflows.cache import node_keys
from mavispm.workflows.config import load_workflow
from mavispm.workflows.graph import expand
from mavispm.workflows.stages import default_registry

ROOT = Path(__file__).resolve().parents[1]
QUICKSTART = (ROOT / "workflows" / "quickstart.toml").read_text()

STAGES = {
    # stage: (validator, knobs class, TOML of the knobs table, same values at their homes)
    "cluster": (
        validate_cluster,
        ClusterKnobs,
        "[knobs]\nn_rows = 64\nn_energy = 300\n",
        "[resolution]\nn_rows = 64\nn_energy = 300\n",
    ),
    "optics": (
        validate_optics,
        OpticsKnobs,
        "[knobs]\npupil_sampling = 64\nchunk = 4\n",
        "[psf]\npupil_sampling = 64\nchunk = 4\n",
    ),
    "dynamics": (
        validate_dynamics,
        DynamicsKnobs,
        '[knobs]\nnlive = 80\nposterior = "nested"\n',
        'nlive = 80\nposterior = "nested"\n',
    ),
    "propermotions": (
        validate_pm,
        ProperMotionKnobs,
        '[knobs]\nclip_iterations = 5\nmatch_tolerance = "30 mas"\n',
        'clip_iterations = 5\nmatch_tolerance = "30 mas"\n',
    ),
}


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_knobs_round_trip_from_toml(stage):
    """A ``[knobs]`` table read from TOML gives the knobs object; the same values at their
    earlier places give equal settings; the settings written back as a mapping (product
    provenance) read back equal."""
    validate, knobs_cls, nested, home = STAGES[stage]
    s = validate(tomllib.loads(nested))
    expected = {
        "cluster": {"n_rows": 64, "n_energy": 300},
        "dynamics": {"nlive": 80, "posterior": "nested"},
    }.get(
        stage,
        {"pupil_sampling": 64, "chunk": 4}
        if stage == "optics"
        else {"clip_iterations": 5, "match_tolerance": 0.03},
    )
    assert isinstance(s.knobs, knobs_cls)
    assert s.knobs == dataclasses.replace(knobs_cls(), **expected)
    assert validate(tomllib.loads(home)) == s
    assert validate(to_mapping(s)) == s
    defaults = validate({})
    assert defaults.knobs == knobs_cls()  # the knobs' defaults are the stage's defaults
    assert s != defaults


def test_knobs_read_as_before():
    """Code written against the earlier names keeps working."""
    c = validate_cluster({"knobs": {"n_rows": 64}})
    assert c.resolution is c.knobs and c.resolution.n_rows == 64
    assert ClusterSettings().replace(resolution=ClusterKnobs(n_rows=32)).knobs.n_rows == 32
    p = validate_pm({"clip_iterations": 5})
    assert p.clip_iterations == 5 and p.replace(clip_iterations=7).knobs.clip_iterations == 7
    o = validate_optics({"knobs": {"n_nodes": 5}})
    assert o.psf.n_nodes == 5 and o.knobs.n_nodes == 5


@pytest.mark.parametrize(
    ("validate", "mapping", "key"),
    [
        (validate_cluster, {"knobs": {"n_row": 64}}, "knobs.n_row"),
        (validate_cluster, {"resolution": {"n_rowz": 64}}, "resolution.n_rowz"),
        (validate_cluster, {"knobs": {"n_rows": 4}}, "knobs"),
        (
            validate_cluster,
            {"knobs": {"n_rows": 64}, "resolution": {"n_rows": 64}},
            "resolution.n_rows",
        ),
        (validate_optics, {"knobs": {"pupil_samplng": 64}}, "scene.optics.knobs.pupil_samplng"),
        (validate_optics, {"knobs": {"chunk": "many"}}, "scene.optics.knobs.chunk"),
        (validate_optics, {"knobs": {"chunk": 2}, "psf": {"chunk": 4}}, "scene.optics.psf.chunk"),
        (validate_optics, {"knobs": 3}, "scene.optics.knobs"),
        (validate_pm, {"knobs": {"clip_iteration": 5}}, "propermotions.knobs.clip_iteration"),
        (validate_pm, {"clip_iterationz": 5}, "propermotions.clip_iterationz"),
        (validate_pm, {"knobs": {"clip_iterations": 0}}, "propermotions.knobs"),
        (validate_dynamics, {"knobs": {"nlivee": 80}}, "dynamics.knobs.nlivee"),
        (validate_dynamics, {"knobs": {"nlive": 80}, "nlive": 80}, "dynamics.nlive"),
        (validate_dynamics, {"knobs": 3}, "dynamics.knobs"),
        (validate_dynamics, {"knobs": {"walks": -1}}, "dynamics"),
        (validate_dynamics, {"knobs": {"walks": 2.5}}, "dynamics.knobs.walks"),
    ],
)
def test_a_bad_knob_is_a_one_line_error_naming_the_key(validate, mapping, key):
    with pytest.raises(ConfigError) as info:
        validate(mapping)
    message = str(info.value)
    assert f"key '{key}'" in message and "\n" not in message


def test_a_workflow_with_a_bad_knob_is_refused_in_one_line(tmp_path):
    """Loading a workflow (what ``mavispm run`` and ``--dry-run`` do first; the command
    line prints a ConfigError as its one line, exit 2) refuses a misspelt knob by name."""
    path = tmp_path / "wf.toml"
    path.write_text(QUICKSTART + "\n[propermotions.knobs]\nclip_iteratons = 3\n")
    with pytest.raises(ConfigError) as info:
        load_workflow(path, default_registry())
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    assert "propermotions.knobs.clip_iteratons" in message and "clip_iterations" in message


def _keys(text: str, tmp_path: Path, name: str) -> dict[str, str]:
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    registry = default_registry()
    return node_keys(expand(load_workflow(path, registry)), registry)


def _drop(text: str, *lines: str) -> str:
    for line in lines:
        assert line in text
        text = text.replace(line, "", 1)
    return text


def test_where_a_knob_is_written_changes_no_cache_key(tmp_path):
    """The quickstart with its knobs at their earlier places and the same workflow with
    them in ``[<stage>.knobs]`` tables have identical keys for every node."""
    homes = (
        QUICKSTART.replace("[propermotions]\n", "[propermotions]\nclip_iterations = 5\n")
        + "\n[cluster.resolution]\nn_rows = 64\n"
    )
    nested = _drop(
        QUICKSTART,
        "n_nodes = 3\n",
        "pupil_sampling = 64\n",
        "epsf_iterations = 4\n",
        "grid_size = 24\n",
        "nlive = 60\n",
    )
    nested += (
        "\n[dynamics.knobs]\ngrid_size = 24\nnlive = 60\n"
        "\n[cluster.knobs]\nn_rows = 64\n"
        "\n[scene.optics.knobs]\nn_nodes = 3\npupil_sampling = 64\n"
        "\n[measure.knobs]\nepsf_iterations = 4\n"
        "\n[propermotions.knobs]\nclip_iterations = 5\n"
    )
    a, b = _keys(homes, tmp_path, "homes"), _keys(nested, tmp_path, "nested")
    assert set(a) == set(b) and len(a) >= 8
    assert a == b


@pytest.mark.parametrize(
    ("table", "changed"),
    [
        (
            "[cluster.knobs]\nn_rows = 96\n",
            {"cluster", "frames", "stars", "propermotions", "dynamics"},
        ),
        (
            "[scene.optics.knobs]\npsd_padding = 3\n",
            {"optics", "frames", "stars", "propermotions", "dynamics"},
        ),
        ("[propermotions.knobs]\nclip_iterations = 3\n", {"propermotions", "dynamics"}),
        ("[dynamics.knobs]\nradial_points_per_efold = 16\n", {"dynamics"}),
    ],
)
def test_a_knob_value_changes_its_node_and_the_nodes_downstream(tmp_path, table, changed):
    """Knobs change results (how accurately), so, like any setting that is not a UI key
    (docs/workflows.md, "Caching"), a new value re-runs its node and its dependants only."""
    base = _keys(QUICKSTART, tmp_path, "base")
    new = _keys(QUICKSTART + "\n" + table, tmp_path, "new")
    assert {nid.split("/")[0] for nid in base if new[nid] != base[nid]} == changed


def test_gather_and_scatter_are_inverse():
    homes = {"a": (), "b": ("t",), "c": ("t", "u")}
    spread = {"a": 1, "t": {"b": 2, "x": 0, "u": {"c": 3}}, "y": 4}
    gathered = gather_knobs(spread, homes)
    assert gathered == {"t": {"x": 0, "u": {}}, "y": 4, "knobs": {"a": 1, "b": 2, "c": 3}}
    assert scatter_knobs(gathered, homes) == spread
    assert spread["t"]["b"] == 2  # the input is not modified
    assert gather_knobs({"y": 4}, homes) == {"y": 4}  # no knob given: no knobs table


@pytest.mark.parametrize(
    ("page", "knobs_cls", "table"),
    [
        ("cluster.md", ClusterKnobs, "[cluster.knobs]"),
        ("optics.md", OpticsKnobs, "[scene.optics.knobs]"),
        ("propermotions.md", ProperMotionKnobs, "[propermotions.knobs]"),
        ("dynamics.md", DynamicsKnobs, "[dynamics.knobs]"),
    ],
)
def test_every_knob_is_documented_on_its_stage_page(page, knobs_cls, table):
    text = (ROOT / "docs" / page).read_text()
    assert knobs_cls.__name__ in text and table in text
    for f in dataclasses.fields(knobs_cls):
        assert f.name in text, f"{page} does not document {f.name}"
