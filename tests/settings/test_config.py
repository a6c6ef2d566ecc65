"""Typed settings: every profile is valid, defaults are defined once and agree with the YAML,
bad values name their key (and the allowed values), numbers come as int, float or string,
every experiment is resolved and a memory estimate is checked before any job runs."""

import dataclasses
import itertools
import json
import re
from pathlib import Path

import jsonschema
import pytest
import yaml

from physmorph.settings.docs import schema_keys
from physmorph.settings.errors import ConfigError
from physmorph.settings.sections import SamplingConfig
from physmorph.settings.workflow import Settings, load_settings
from physmorph.settings.schema import current_defaults, defaults_changed, record_first_defaults, schema_text, settings_classes
from physmorph.settings.params import morph_params, params_json, without_defaults
from physmorph.settings.build import build, load_mapping
from physmorph.base.grid import DOMAIN_HI, DOMAIN_LO, Grid
from physmorph.settings.morph import MorphConfig
from physmorph.settings.mpm import MPMConfig

BASE = "config/config.yaml"
# the workflow's generated schema and its record of first defaults (python -m physmorph.settings)
SCHEMA_PATH = Path(__file__).resolve().parents[2] / "workflow" / "schemas" / "config.schema.yaml"
FIRST_DEFAULTS_PATH = SCHEMA_PATH.with_name("first_defaults.json")
# every profile overlay in config/ (paper_results.yaml is the paper's tables, not a profile)
PROFILES = [[]] + [[str(p)] for p in sorted(Path("config").glob("*.yaml"))
                   if p.name not in ("config.yaml", "paper_results.yaml")]


@pytest.mark.parametrize("profile", PROFILES)
def test_profiles_validate(profile):
    assert len(PROFILES) >= 5 and ["config/test.yaml"] in PROFILES  # the glob found the overlays
    s = load_settings(BASE, *profile)
    assert s.sampling.grid_res >= 8
    assert s.mpm.grid_res == s.sampling.grid_res and s.mpm.density == s.sampling.density
    for name in s.experiments:
        assert isinstance(s.experiment_config(name), MorphConfig)


def test_profile_overlay_merges_nested_keys():
    s = load_settings(BASE, "config/test.yaml")
    assert s.profile == "test" and s.sampling.ppc_surface == 1
    assert s.sampling.density == 75.0  # inherited from the default profile


def _leaves(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def test_yaml_restates_the_settings_defaults():
    """config/config.yaml's settings (everything but the data: meshes, shapes, experiments, the
    study and the table lists) equal the dataclasses' defaults: defaults are defined once."""
    raw = yaml.safe_load(open(BASE))
    defaults = Settings.from_mapping({})
    data = {"raw_meshes", "shapes", "experiments", "tradeoff", "tables"}
    checked = 0
    for key, value in _leaves({k: v for k, v in raw.items() if k not in data}):
        obj = defaults
        for part in key.split("."):
            obj = getattr(obj, part)
        want = tuple(value) if isinstance(value, list) else value
        assert obj == want and type(obj) is type(want) or isinstance(obj, float) and obj == float(want), \
            f"{key}: YAML {value!r}, default {obj!r}"
        checked += 1
    assert checked > 30
    # values that once disagreed between the YAML and the dataclasses
    assert defaults.target.distance == 36.0 and defaults.mpm.learning_rate == 0.004
    assert defaults.plasticity.correspondence == "transport" and defaults.mpm.mass_loss == "log"
    assert defaults.morph.injection_calibration == "every_frame"


def test_the_domain_is_defined_once_and_reaches_the_solver():
    assert (DOMAIN_LO, DOMAIN_HI) == (-16.0, 16.0) == (Grid(16).lo, Grid(16).hi)
    assert (MPMConfig().domain_lo, MPMConfig().domain_hi) == (DOMAIN_LO, DOMAIN_HI)
    s = load_settings(BASE, overrides={"domain": [-20, 20]})
    cfg = s.experiment_config("iso_bunny_full")
    assert (cfg.mpm.domain_lo, cfg.mpm.domain_hi) == (-20.0, 20.0) and cfg.mpm.dx == 40 / 32
    with pytest.raises(ConfigError, match="'domain'"):
        load_settings(BASE, overrides={"domain": [5, -5]})


def test_schema_is_generated_from_the_settings():
    assert SCHEMA_PATH.read_text() == schema_text(), "run: python -m physmorph.settings --schema"
    schema = yaml.safe_load(SCHEMA_PATH.read_text())
    for profile in PROFILES:
        jsonschema.Draft202012Validator(schema).validate(load_mapping(BASE, *profile))
    optimizer = schema["properties"]["mpm"]["properties"]["optimizer"]
    assert (optimizer["enum"], optimizer["default"]) == (["adam", "normalized_gd"], "normalized_gd")
    assert "normalised descent" in optimizer["description"]  # the meaning comes with the declaration
    assert "grid_res" not in schema["properties"]["mpm"]["properties"]  # set by sampling.grid_res


EXP = {"source": "iso", "target": "bunny", "method": "full"}


@pytest.mark.parametrize(
    "override, message",
    [
        ({"sampling": {"grid_res": "big"}}, "'sampling.grid_res': expected an integer, got 'big'"),
        ({"sampling": {"gird_res": 32}}, "'sampling.gird_res': unknown key (allowed: density, grid_res"),
        ({"target": {"cameras": 0}}, "'target.cameras': cameras must be >= 1"),
        ({"device": "tpu"}, "'device': 'tpu' is not allowed (allowed: auto, cpu, cuda)"),
        ({"shapes": {"bunny": {"kind": "file", "file": "nope.obj"}}}, "'shapes.bunny.file': 'nope.obj' is not listed"),
        ({"shapes": {"mine": {"kind": "file"}}}, "'shapes.mine.file': file or path: kind 'file' takes exactly one of"),
        ({"experiments": {"x": {"source": "iso", "target": "teapot", "method": "full"}}}, "'experiments.x.target'"),
        ({"experiments": {"x": {"source": "iso", "target": "bunny", "method": "magic"}}},
         "'experiments.x.method': 'magic' is not allowed (allowed: physics_only, f_inject, full, position_inject)"),
        ({"tables": {"experiments": ["missing_run"]}}, "'tables.experiments[0]'"),
        ({"surprise": 1}, "'surprise': unknown key"),
        ({"mpm": {"dt": -0.01}}, "'mpm.dt': dt must be > 0, got -0.01"),
        ({"mpm": {"substeps": 0}}, "'mpm.substeps': substeps must be >= 1, got 0"),
        ({"mpm": {"smoothing": 1}}, "'mpm.smoothing': smoothing must be in [0, 1), got 1"),
        ({"mpm": {"optimizer": "sgd"}}, "'mpm.optimizer': 'sgd' is not allowed (allowed: adam, normalized_gd)"),
        ({"mpm": {"grid_res": 64}}, "'mpm.grid_res': not settable here: it is set by sampling.grid_res"),
        ({"plasticity": {"correspondence": "exact"}}, "'plasticity.correspondence': 'exact' is not allowed (allowed: nearest, transport)"),
        # a setting the code no longer has: named as such, with the value the method runs at
        ({"mpm": {"control_in_F": True}}, "'mpm.control_in_F': no longer a setting: the method runs as it did with False"),
        ({"morph": {"step_backoff": 0.5}}, "'morph.step_backoff': no longer a setting: the method runs as it did with 1.0"),
        ({"tables": {"noise": ["iso_bunny_full"]}}, "'tables.noise': two experiments (one morph from two particle samples) or none"),
        ({"tables": {"noise": ["iso_bunny_full", "nope"]}}, "'tables.noise[1]': 'nope' is not one of tables.experiments"),
        ({"shapes": {"iso": {"kind": "isosphere", "seed": -1}}}, "'shapes.iso.seed': seed must be >= 0, got -1"),
        ({"morph": {"frames": 0}}, "'morph.frames': frames must be >= 1, got 0"),
        ({"morph": {"method": "full"}}, "'morph.method': not settable here: it is set by experiments.<name>.method"),
        ({"morph": {"cameras": 100}}, "'morph.cameras': 100 render-loss views, but the target has only 8"),
        ({"experiments": {"x": {**EXP, "cameras": 9}}}, "'experiments.x.cameras': 9 render-loss views"),
        ({"experiments": {"x": {**EXP, "frames": 0}}}, "'experiments.x.frames': frames must be >= 1"),
        ({"experiments": {"x": {**EXP, "drag": -1}}}, "'experiments.x.drag': drag must satisfy"),
        ({"render": {"kernel": "gpu"}}, "'render.kernel': 'gpu' is not allowed (allowed: auto, tile, pixel)"),
        ({"profile": "../x"}, "'profile': must be a plain name"),
    ],
)
def test_bad_config_names_the_key(override, message):
    with pytest.raises(ConfigError) as err:
        load_settings(BASE, overrides=override)
    assert message in str(err.value)
    # the key and the reason are the error's data; the message is made of them
    assert err.value.key == message.split("'")[1]
    assert str(err.value) == f"config key '{err.value.key}': {err.value.reason}"


def test_a_shape_entry_with_its_own_seed_is_a_second_particle_sample():
    """shapes.<name>.seed sets that shape's sampling seed (the top-level seed otherwise): the
    paper profile's isob is the isosphere sampled again, and its iso -> bunny full run pairs with
    the first as the directions table's noise."""
    s = load_settings(BASE, "config/paper.yaml")
    assert s.particle_seed("iso") == s.seed == 0 and s.particle_seed("isob") == 1
    iso, isob = s.shape("iso"), s.shape("isob")
    assert dataclasses.replace(isob, seed=None) == iso
    assert s.tables.noise == ("iso_bunny_full", "isob_bunny_full")
    a, b = (s.experiment_config(n) for n in s.tables.noise)
    assert dataclasses.replace(b, release_frames=a.release_frames) == a  # the same morph (no release probe)
    assert load_settings(BASE).tables.noise == ()  # the default profile measures no noise


def test_numbers_as_ints_floats_and_strings():
    """--config 'mpm={smoothing: 0.5}' hands over '0.5'; YAML 1.1 reads 1.4e5 as a string; drag: 0
    and smoothing: 1 are ints. All become the field's type."""
    s = load_settings(BASE, overrides={"mpm": {"smoothing": "0.5", "youngs_modulus": "1.4e5", "drag": 0,
                                               "substeps": "20", "step_per_volume": "false"},
                                       "plasticity": {"eta": 1}, "target": {"distance": 36}, "morph": {"frames": 40.0}})
    assert s.mpm.smoothing == 0.5 and s.mpm.youngs_modulus == 1.4e5 and s.mpm.substeps == 20
    assert type(s.mpm.drag) is float and s.mpm.drag == 0.0 and s.mpm.step_per_volume is False
    assert type(s.plasticity.eta) is float and type(s.target.distance) is float and s.morph.frames == 40
    with pytest.raises(ConfigError, match="'morph.frames': expected an integer, got 40.5"):
        load_settings(BASE, overrides={"morph": {"frames": 40.5}})
    with pytest.raises(ConfigError, match="'mpm.smoothing': expected a number, got True"):
        load_settings(BASE, overrides={"mpm": {"smoothing": True}})


def test_memory_estimate_refuses_a_grid_too_big_for_the_machine():
    with pytest.raises(ConfigError, match=r"needs an estimated [\d,]+ MB .*512\^3.*above the limit of [\d,]+ MB"):
        load_settings(BASE, overrides={"sampling": {"grid_res": 512}})
    # the limit is a setting: the paper profile fits 24 GB but not 2 GB
    load_settings(BASE, "config/paper.yaml", overrides={"max_memory_mb": 24000})
    with pytest.raises(ConfigError, match=r"morph .* above the limit of 2,000 MB \(max_memory_mb\)") as err:
        load_settings(BASE, "config/paper.yaml", overrides={"max_memory_mb": 2000})
    assert err.value.key == "max_memory_mb"
    est = {e.stage: e.mb for e in load_settings(BASE).memory_estimates()}
    assert 600 < est["morph iso_bunny_full"] < 1500  # measured peak RSS at this profile: 510-590 MB


def test_morph_memory_from_the_sampled_count_covers_the_measured_peak():
    """With the particles sampled, the morph rule asks for memory from their real count: the paper
    profile's iso -> bunny full (471,282 particles) peaked at 7,038 MB (docs/study/performance_history.md)."""
    from physmorph.settings.memory_model import morph_memory

    s = load_settings(BASE, "config/paper.yaml")
    args = (s.shape("iso"), s.sampling, s.target, s.mpm, s.domain, "")
    assert 7038 < morph_memory(*args, n_particles=471_282).mb < 1.25 * 7038
    assert morph_memory(*args).mb == morph_memory(*args, n_particles=None).mb  # the estimate before


def test_experiment_resolution_and_its_params():
    s = load_settings(BASE)
    full, po = s.experiment_config("iso_bunny_full"), s.experiment_config("iso_bunny_physics_only")
    d05 = s.experiment_config("iso_bunny_full_d05")
    assert d05.mpm.drag == 0.5 and full.mpm.drag == 0.9 and full.frames == 40 and full.method == "full"
    # params round trip: the run rebuilds exactly its settings from the string
    back = build(MorphConfig, json.loads(morph_params(full)), "morph")
    assert back == dataclasses.replace(full, progress=back.progress)
    # a setting only plasticity reads changes the full run's params, not physics-only's
    s2 = load_settings(BASE, overrides={"plasticity": {"eta": 0.1}})
    assert morph_params(s2.experiment_config("iso_bunny_full")) != morph_params(full)
    assert morph_params(s2.experiment_config("iso_bunny_physics_only")) == morph_params(po)
    assert morph_params(s2.experiment_config("iso_bunny_f_inject")) == morph_params(s.experiment_config("iso_bunny_f_inject"))
    # so does the stray pull (the full method's alone)
    s4 = load_settings(BASE, overrides={"morph": {"stray_pull": 2.0, "stray_pull_onset": 2.0, "stray_pull_density": 0.2}})
    assert morph_params(s4.experiment_config("iso_bunny_full")) != morph_params(full)
    for name in ("iso_bunny_physics_only", "iso_bunny_f_inject", "iso_bunny_position_inject"):
        assert morph_params(s4.experiment_config(name)) == morph_params(s.experiment_config(name)), name
    # the spray's links, only where spray is put back (the full method with reabsorb_strays)
    corners = {"spray_links": "corners"}
    s5 = load_settings(BASE, overrides={"morph": corners})
    assert morph_params(s5.experiment_config("iso_bunny_full")) != morph_params(full)
    assert morph_params(s5.experiment_config("iso_bunny_f_inject")) == morph_params(s.experiment_config("iso_bunny_f_inject"))
    s6, s7 = (load_settings(BASE, overrides={"morph": {"reabsorb_strays": False, **extra}}) for extra in ({}, corners))
    assert morph_params(s7.experiment_config("iso_bunny_full")) == morph_params(s6.experiment_config("iso_bunny_full"))
    # the gain's interval, only where the gain is measured (not physics-only) and every frame
    s8 = load_settings(BASE, overrides={"morph": {"injection_calibration_every": 1}})
    for name in ("iso_bunny_full", "iso_bunny_f_inject"):
        assert morph_params(s8.experiment_config(name)) != morph_params(s.experiment_config(name)), name
    assert morph_params(s8.experiment_config("iso_bunny_physics_only")) == morph_params(po)
    s9, s10 = (load_settings(BASE, overrides={"morph": {"injection_calibration": "first_frame", **extra}})
               for extra in ({}, {"injection_calibration_every": 1}))
    assert morph_params(s10.experiment_config("iso_bunny_full")) == morph_params(s9.experiment_config("iso_bunny_full"))
    # the held frames' step share, only where a settle phase backs the step off
    s11 = load_settings(BASE, overrides={"morph": {"settle_hold_below": 0.0}})
    assert morph_params(s11.experiment_config("iso_bunny_full")) != morph_params(full)
    s12, s13 = (load_settings(BASE, overrides={"morph": {"settle": "off", **extra}})
                for extra in ({}, {"settle_hold_below": 0.0}))
    assert morph_params(s13.experiment_config("iso_bunny_full")) == morph_params(s12.experiment_config("iso_bunny_full"))
    # threads change no params
    s3 = load_settings(BASE, overrides={"threads": 1})
    assert morph_params(s3.experiment_config("iso_bunny_full")) == morph_params(full)


@pytest.mark.parametrize("profile", PROFILES)
def test_every_run_rebuilds_its_settings_from_its_params(profile):
    s = load_settings(BASE, *profile)
    for name in s.experiments:
        cfg = s.experiment_config(name)
        back = build(MorphConfig, json.loads(morph_params(cfg)), "morph")
        # what the method never reads may differ (it is left out); what it reads may not
        assert morph_params(back) == morph_params(cfg), name
        assert back.mpm == dataclasses.replace(cfg.mpm, threads=back.mpm.threads), name
        if cfg.method == "full":
            assert back.plasticity == cfg.plasticity, name


def test_params_leave_out_defaults_so_a_new_option_reruns_nothing():
    full = load_settings(BASE).experiment_config("iso_bunny_full")
    # an option added later, at a default that changes nothing, leaves every params string as it was
    @dataclasses.dataclass(frozen=True)
    class MPMWithNewOption(MPMConfig):
        new_option: int = 1

    mpm_plus = MPMWithNewOption(**{f.name: getattr(full.mpm, f.name) for f in dataclasses.fields(MPMConfig)})
    with_option = dataclasses.replace(full, mpm=mpm_plus)
    assert morph_params(with_option) == morph_params(full)
    assert params_json(mpm_plus) == params_json(full.mpm)
    # set to anything else, it is in the params
    assert '"new_option":2' in morph_params(dataclasses.replace(with_option, mpm=dataclasses.replace(mpm_plus, new_option=2)))
    # a setting given explicitly at its default is the same as not giving it
    s_explicit = load_settings(BASE, overrides={"mpm": {"mass_loss_blur_weight": 1.0}, "plasticity": {"max_anisotropy": 4.0}})
    assert morph_params(s_explicit.experiment_config("iso_bunny_full")) == morph_params(full)
    # fields at their defaults are absent, others present; ALWAYS_IN_PARAMS fields always
    d = json.loads(morph_params(full))
    assert "mass_loss_blur_weight" not in d["mpm"] and "max_anisotropy" not in d.get("plasticity", {})
    assert d["method"] == "full" and "drag" not in d["mpm"] and d["release_frames"] == 40  # the YAML sets 40
    assert without_defaults(SamplingConfig()) == {} and without_defaults(SamplingConfig(grid_res=64)) == {"grid_res": 64}
    # a default that changed (mpm.learning_rate, 0.001 -> 0.002 -> 0.004, docs/study/CHANGELOG.md) is always there, so
    # runs made with the old default, whose params left it out, rerun
    assert json.loads(FIRST_DEFAULTS_PATH.read_text())["MPMConfig.learning_rate"] == 0.001
    assert d["mpm"]["learning_rate"] == 0.004 and "learning_rate" in MPMConfig.ALWAYS_IN_PARAMS


def test_first_defaults_are_recorded_and_a_changed_default_must_stay_in_params(tmp_path):
    # the committed record holds every field, and no default changed behind the params' back
    assert defaults_changed(FIRST_DEFAULTS_PATH) == []
    names = [c.__name__ for c in settings_classes()]
    assert len(names) == len(set(names)) and {"MPMConfig", "MorphConfig", "SamplingConfig", "Experiment"} <= set(names)
    # a changed default is caught, named, and told where to go
    recorded = json.loads(FIRST_DEFAULTS_PATH.read_text())
    path = tmp_path / "first_defaults.json"
    path.write_text(json.dumps({**recorded, "MPMConfig.smoothing": 0.5, "MorphConfig.method": "f_inject"}))
    problems = defaults_changed(path)
    assert len(problems) == 1 and "MPMConfig.smoothing" in problems[0] and "MPMConfig.ALWAYS_IN_PARAMS" in problems[0]
    # (MorphConfig.method is always in the params: its change needs nothing more)
    # recording never rewrites a recorded default, and adds what is missing
    del recorded["MPMConfig.drag"]
    path.write_text(json.dumps({**recorded, "MPMConfig.smoothing": 0.5}))
    assert any("MPMConfig.drag: not recorded" in p for p in defaults_changed(path))
    assert record_first_defaults(path) == ["MPMConfig.drag"]
    after = json.loads(path.read_text())
    assert after["MPMConfig.smoothing"] == 0.5 and after["MPMConfig.drag"] == current_defaults()["MPMConfig.drag"]


def test_unknown_experiment_lists_known():
    s = load_settings(BASE, overrides={"experiments": {"iso_bunny": {"source": "iso", "target": "bunny", "method": "full"}}})
    assert s.experiment("iso_bunny").target == "bunny"
    with pytest.raises(ConfigError, match="unknown experiment 'iso_teapot'.*iso_bunny"):
        s.experiment("iso_teapot")


def test_a_shape_given_by_path_needs_no_raw_mesh_entry():
    s = load_settings(BASE, overrides={"shapes": {"mine": {"kind": "file", "path": "my/mesh.obj", "size": 18}}})
    assert s.shapes["mine"].path == "my/mesh.obj" and s.shapes["mine"].file is None
    with pytest.raises(ConfigError, match="'shapes.mine.file': file or path: kind 'file' takes exactly one"):
        load_settings(BASE, overrides={"shapes": {"mine": {"kind": "file", "path": "a.obj", "file": "spot.obj"}}})


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_settings(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_settings(bad)


def test_resolution_tag_roundtrip():
    s = load_settings(BASE).sampling
    assert s.with_tag(s.tag) == s and s.with_tag("64x5x1") == SamplingConfig(64, 5, 1, 75.0, 0.7)
    with pytest.raises(ConfigError, match="32x2x1"):
        s.with_tag("32")


@pytest.mark.parametrize("quick", ["1", None])
def test_quick_compile_turns_off_taichis_ir_optimisation_only_when_asked(monkeypatch, quick):
    """PHYSMORPH_QUICK_COMPILE=1 (the suite sets it) initialises Taichi without its IR optimisation
    passes; unset (every run), Taichi keeps its defaults."""
    import taichi as ti

    import physmorph.base.taichi_runtime as rt

    seen = {}
    monkeypatch.setattr(ti, "init", lambda **kw: seen.update(kw))
    monkeypatch.setattr(rt, "_state", {})
    if quick:
        monkeypatch.setenv("PHYSMORPH_QUICK_COMPILE", quick)
    else:
        monkeypatch.delenv("PHYSMORPH_QUICK_COMPILE", raising=False)
    rt.init_taichi("cpu")
    assert seen["offline_cache"] is True
    # the cache keeps a gigabyte of kernels: the suite's do not push a profile's out
    assert seen["offline_cache_max_size_of_files"] == rt.OFFLINE_CACHE_BYTES >= 1 << 30
    assert seen.get("advanced_optimization", True) is (quick is None)


def test_cached_function_sources_keep_each_closures_own_values():
    """init_taichi makes Taichi's frontend read a function's source once (use_cached_function_sources:
    re-reading it at every inlining was a quarter of a solver's kernel build). The cache is keyed
    by the code, shared by closures made from one definition (the stress functions are made anew
    for each solver): each closure still compiles with its own captured values."""
    import taichi as ti
    from taichi.lang import kernel_impl

    from physmorph.base.taichi_runtime import init_taichi

    init_taichi("cpu")
    assert getattr(kernel_impl._get_tree_and_ctx, "cached_sources", False)

    def adder(c):
        @ti.func
        def add(x):
            return x + c
        return add

    out = ti.field(ti.f64, shape=2)

    def kernel_of(add, slot):
        @ti.kernel
        def run():
            out[slot] = add(1.0)
        return run

    kernel_of(adder(2.0), 0)()
    kernel_of(adder(40.0), 1)()
    assert out.to_numpy().tolist() == [3.0, 41.0]


def test_taichi_errors_still_name_file_line_and_source_with_short_positions():
    """init_taichi makes Taichi's frontend record one-line source positions (use_short_source_positions:
    the caret lines it formatted for every node were a third of a cached kernel build); a kernel
    that fails to compile is still reported with its file, line, function and source line."""
    import taichi as ti
    from taichi.lang.ast.ast_transformer_utils import ASTTransformerContext

    from physmorph.base.taichi_runtime import init_taichi

    init_taichi("cpu")
    assert getattr(ASTTransformerContext.get_pos_info, "short_positions", False)
    values = ti.field(ti.f32, shape=2)

    @ti.kernel
    def broken():
        for i in values:
            values[i] = name_defined_nowhere + 1.0  # noqa: F821

    with pytest.raises(Exception) as err:
        broken()
    msg = str(err.value)
    assert "test_config.py\", line" in msg and "in broken" in msg, msg
    assert "values[i] = name_defined_nowhere + 1.0" in msg and "name_defined_nowhere" in msg.splitlines()[-1], msg


def _table_cells(row: str) -> list[str]:
    """A markdown table row's cells: split at every | not escaped as \\|, the outer ones dropped."""
    return re.split(r"(?<!\\)\|", row.strip())[1:-1]


def test_every_config_reference_row_has_its_headers_cells():
    """config/README.md's tables render as tables: no row holds an unescaped | that splits a cell,
    and the choices a key allows are its declaration's (plasticity.correspondence: two)."""
    lines = (Path(__file__).resolve().parents[2] / "config" / "README.md").read_text().splitlines()
    tables = rows = 0
    for i, line in enumerate(lines[:-1]):
        if line.startswith("|") and re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", lines[i + 1].strip()):
            tables += 1
            width = len(_table_cells(line))
            for row in itertools.takewhile(lambda r: r.startswith("|"), lines[i + 2:]):
                assert len(_table_cells(row)) == width, f"config/README.md row with a cell too many or few: {row}"
                rows += 1
    keys = [key for key, _ in schema_keys()]
    leaves = [key for key in keys if not any(k.startswith(key + ".") for k in keys) and key not in
              ("raw_meshes", "shapes", "experiments", "tables", "export")]  # a section is a table's title
    text = "\n".join(lines)
    assert tables >= 10 and rows >= len(leaves) and all(f"| `{key}`" in text for key in leaves)
    row = next(r for r in lines if r.startswith("| `plasticity.correspondence`"))
    assert _table_cells(row)[4].strip() == "`nearest` \\| `transport`"


def test_schema_accepts_what_the_settings_accept_and_refuses_what_they_refuse():
    """The Snakefile validates with the schema before the settings build: numbers and booleans as
    strings (--config) pass both; an unknown key, a value out of range or a key set elsewhere fails both."""
    validator = jsonschema.Draft202012Validator(yaml.safe_load(SCHEMA_PATH.read_text()))
    good = {"mpm": {"smoothing": "0.5", "youngs_modulus": "1.4e5", "substeps": "20", "step_per_volume": "false"},
            "morph": {"frames": 40.0}, "threads": "1", "max_memory_mb": None}
    assert not list(validator.iter_errors(good))
    load_settings(BASE, overrides=good)
    for bad in ({"mpm": {"grid_res": 64}}, {"surprise": 1}, {"threads": 0}, {"mpm": {"smoothing": 1.0}},
                {"mpm": {"optimizer": "sgd"}}, {"mpm": {"step_per_volume": "maybe"}}, {"sampling": {"grid_res": "big"}},
                {"profile": "../x"}):
        assert list(validator.iter_errors(bad)), bad
        with pytest.raises(ConfigError):
            load_settings(BASE, overrides=bad)
