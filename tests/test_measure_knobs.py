"""The stars stage's accuracy/speed knobs: one object apart from the method, documented."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest

from mavispm.core.errors import ConfigError
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.settings import KNOB_NAMES, MeasureKnobs, MeasureSettings

DOCS = Path(__file__).resolve().parents[1] / "docs" / "measure.md"


def test_flat_and_nested_knobs_give_the_same_settings():
    flat = validate_settings({"psf_variation": "constant", "epsf_iterations": 4, "chunk": 64})
    nested = validate_settings(
        {"psf_variation": "constant", "knobs": {"epsf_iterations": 4, "chunk": 64}}
    )
    assert flat == nested
    assert flat.knobs == MeasureKnobs(epsf_iterations=4, chunk=64)
    assert flat.epsf_iterations == 4 and flat.stamp_radius == MeasureKnobs().stamp_radius
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        flat.nope  # noqa: B018


@pytest.mark.parametrize(
    ("mapping", "message"),
    [
        ({"chunk": 8, "knobs": {"chunk": 8}}, "key 'chunk': given both flat and in"),
        ({"epsf_sise": 21}, "key 'epsf_sise': unknown key; did you mean 'epsf_size'"),
        ({"knobs": {"epsf_size": 20}}, "key 'knobs.epsf_size': must be an odd integer"),
        ({"psf_grid": 0}, "key 'psf_grid': must be a positive integer"),
    ],
)
def test_bad_knobs_name_the_key(mapping, message):
    with pytest.raises(ConfigError, match=message):
        validate_settings(mapping)


def test_knobs_and_method_are_disjoint_and_documented_with_their_defaults():
    method = {f.name for f in fields(MeasureSettings)} - {"knobs"}
    assert not method & set(KNOB_NAMES)
    text = DOCS.read_text()
    knob_table = text.split("The accuracy and speed knobs", 1)[1].split("\n\n", 2)[1]
    documented = [
        row.split("|")[1].strip() for row in knob_table.split("\n") if row.startswith("| ")
    ]
    documented = [k for k in documented if k not in ("key", "---")]
    assert sorted(documented) == sorted(KNOB_NAMES)
