"""Config loading and validation: every profile is valid; bad values name their key."""

import pytest

from physmorph.config import ConfigError, SamplingConfig, experiment, load_config

BASE = "config/config.yaml"


@pytest.mark.parametrize("profile", [[], ["config/test.yaml"], ["config/paper.yaml"]])
def test_profiles_validate(profile):
    cfg = load_config(BASE, *profile)
    assert cfg["sampling"]["grid_res"] >= 8


def test_profile_overlay_merges_nested_keys():
    cfg = load_config(BASE, "config/test.yaml")
    assert cfg["sampling"]["ppc_surface"] == 1
    assert cfg["sampling"]["density"] == 75.0  # inherited from the default profile


@pytest.mark.parametrize(
    "override, key",
    [
        ({"sampling": {"grid_res": "big"}}, "sampling.grid_res"),
        ({"sampling": {"gird_res": 32}}, "sampling.gird_res"),
        ({"target": {"cameras": 0}}, "target.cameras"),
        ({"device": "tpu"}, "device"),
        ({"shapes": {"bunny": {"kind": "file", "file": "nope.obj"}}}, "shapes.bunny.file"),
        ({"experiments": {"x": {"source": "iso", "target": "teapot", "method": "full"}}}, "experiments.x.target"),
        ({"experiments": {"x": {"source": "iso", "target": "bunny", "method": "magic"}}}, "experiments.x.method"),
        ({"tables": {"experiments": ["missing_run"]}}, "tables.experiments[0]"),
        ({"surprise": 1}, "surprise"),
    ],
)
def test_bad_config_names_the_key(override, key):
    with pytest.raises(ConfigError, match=f"'{key}'".replace("[", r"\[").replace("]", r"\]")):
        load_config(BASE, overrides=override)


def test_missing_required_key_is_named(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("profile: x\n")
    with pytest.raises(ConfigError, match="'device'"):
        load_config(p)


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)


def test_unknown_experiment_lists_known():
    cfg = load_config(BASE, overrides={"experiments": {"iso_bunny": {"source": "iso", "target": "bunny", "method": "full"}}})
    assert experiment(cfg, "iso_bunny")["target"] == "bunny"
    with pytest.raises(ConfigError, match="unknown experiment 'iso_teapot'.*iso_bunny"):
        experiment(cfg, "iso_teapot")


def test_resolution_tag_roundtrip():
    cfg = load_config(BASE)
    s = SamplingConfig.from_config(cfg)
    assert SamplingConfig.from_tag(s.tag, cfg) == s
    with pytest.raises(ConfigError, match="32x2x1"):
        SamplingConfig.from_tag("32", cfg)
