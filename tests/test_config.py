"""Typed configs: unknown keys, wrong types and out-of-range values fail with the field's name and range."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from sim.config import ConfigError, load_config, load_toml, merge_flat, spec
from sim.dr_config import load_dr


@dataclass(frozen=True)
class Inner:
    gain: float = field(default=1.0, metadata=spec(0.0, 2.0, "x"))


@dataclass(frozen=True)
class Outer:
    mode: str = field(default="fast", metadata=spec(choices=("full", "fast")))
    size: tuple[int, int] = field(default=(128, 128), metadata=spec(16, 4096, "px"))
    inner: Inner = field(default_factory=Inner)


def test_defaults_and_nested_values_load():
    cfg = load_config(Outer, {"mode": "full", "size": [64, 48], "inner": {"gain": 1.5}})
    assert cfg == Outer("full", (64, 48), Inner(1.5))


def test_unknown_key_names_close_match():
    with pytest.raises(ConfigError, match=r"unknown field 'inner.gian'.*did you mean 'gain'"):
        load_config(Outer, {"inner": {"gian": 1.0}})


def test_out_of_range_names_field_value_and_range():
    with pytest.raises(ConfigError) as err:
        load_config(Outer, {"inner": {"gain": 3.0}})
    msg = str(err.value)
    assert "inner.gain" in msg and "3.0" in msg and "[0.0, 2.0] x" in msg


def test_choice_and_type_errors():
    with pytest.raises(ConfigError, match="mode = 'medium' is not allowed; expected one of"):
        load_config(Outer, {"mode": "medium"})
    with pytest.raises(ConfigError, match="size must have 2 elements"):
        load_config(Outer, {"size": [1, 2, 3]})
    with pytest.raises(ConfigError, match="must be a number"):
        load_config(Outer, {"inner": {"gain": "high"}})
    with pytest.raises(ConfigError, match="out of range"):
        load_config(Outer, {"inner": {"gain": float("nan")}})


def test_toml_file_and_flat_overrides(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('mode = "full"\n[inner]\ngain = 0.5\n')
    assert load_toml(Outer, path).inner.gain == 0.5
    assert load_toml(Outer, path, {"inner.gain": 0.25}).inner.gain == 0.25
    assert merge_flat({"a": {"b": 1}}, {"a.c": 2}) == {"a": {"b": 1, "c": 2}}
    with pytest.raises(ConfigError, match="does not exist"):
        load_toml(Outer, tmp_path / "missing.toml")
    (tmp_path / "bad.toml").write_text("mode = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_toml(Outer, tmp_path / "bad.toml")


def test_dr_preset_names_and_bad_names():
    assert load_dr("heavy").preset == "heavy"
    with pytest.raises(ConfigError, match=r"expected a preset \['off', 'light', 'heavy'\] or a .toml file"):
        load_dr("medium")
