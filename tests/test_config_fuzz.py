"""Fuzzing the config loader: whatever the bytes of a file or the text of a --set, the outcome is a valid
Config or a one-line ConfigError naming the problem; never another exception, never a NaN in the config."""
from __future__ import annotations

import dataclasses
import math
import typing

import pytest
import yaml

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is in the test extra: pip install -e '.[test]'")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from mipslam.config import Config, config_to_dict, load_config  # noqa: E402
from mipslam.errors import ConfigError  # noqa: E402

# Bounded: about 200 examples per property, a few seconds in all.
FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture],
                database=None)

SECTIONS = {name: [f.name for f in dataclasses.fields(section)] for name, section in typing.get_type_hints(Config).items()}

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-10**30, max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
)
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                           max_size=3), max_leaves=8)
# Sections with mostly real keys (so values reach the type and range checks), some unknown ones.
section_dicts = st.sampled_from(sorted(SECTIONS)).flatmap(
    lambda name: st.tuples(st.just(name), st.dictionaries(
        st.one_of(st.sampled_from(SECTIONS[name]), st.text(max_size=10)), values, max_size=4)))
configs = st.one_of(
    st.lists(section_dicts, max_size=4).map(dict),
    values,
    st.dictionaries(st.sampled_from(["inherit_from", *SECTIONS]), values, max_size=3),
)


def check_outcome(load) -> None:
    try:
        config = load()
    except ConfigError as exc:
        message = str(exc)
        assert message and "\n" not in message, message
        return
    assert isinstance(config, Config)
    entries = [v for section in config_to_dict(config).values() for v in section.values()]
    floats = [x for v in entries for x in (v if isinstance(v, list) else [v]) if isinstance(x, float)]
    assert all(math.isfinite(x) for x in floats), floats


@FUZZ
@given(data=st.binary(max_size=300))
def test_random_bytes_give_a_config_or_a_config_error(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_bytes(data)
    check_outcome(lambda: load_config(path))


@FUZZ
@given(text=st.text(alphabet=st.sampled_from(list("abcdefrunstkigy_:.-[]{},'\"!&*#|>?@%` \t\n0123456789")),
                    max_size=120))
def test_random_yaml_like_text_gives_a_config_or_a_config_error(tmp_path, text):
    path = tmp_path / "fuzz.yaml"
    path.write_text(text, encoding="utf-8")
    check_outcome(lambda: load_config(path))


@FUZZ
@given(data=configs)
def test_random_yaml_documents_give_a_config_or_a_config_error(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True), encoding="utf-8")
    check_outcome(lambda: load_config(path))


@FUZZ
@given(overrides=st.lists(st.one_of(
    st.text(max_size=40),
    st.builds(lambda s, k, v: f"{s}.{k}={v}", st.sampled_from(sorted(SECTIONS)),
              st.sampled_from(sorted({k for keys in SECTIONS.values() for k in keys})), st.text(max_size=20)),
), max_size=3))
def test_random_overrides_give_a_config_or_a_config_error(overrides):
    check_outcome(lambda: load_config(overrides=overrides))


def test_the_fuzzed_sections_are_the_configs_sections():
    assert set(SECTIONS) == {"run", "dataset", "render", "frontend", "tracking", "keyframes", "mapping", "local_ba",
                             "refine", "loop", "eval"}
    assert "iterations" in SECTIONS["tracking"] and "path" in SECTIONS["dataset"]
