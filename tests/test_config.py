"""Config: YAML + inherit_from + presets + --set, typed and validated, safe to load."""
from __future__ import annotations

import inspect
import sys
from pathlib import Path

import pytest

from mipslam.config import (
    CONFIG_DIR,
    PRESETS,
    Config,
    builtin_config_names,
    builtin_configs,
    config_from_dict,
    config_to_dict,
    config_to_yaml,
    load_config,
    load_yaml_tree,
)
from mipslam.errors import ConfigError

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "mipslam" / "configs"


def test_defaults_round_trip_through_yaml(tmp_path):
    config = load_config(CONFIGS / "replica.yaml", preset="balanced", overrides=["tracking.iterations=17"])
    path = tmp_path / "resolved.yaml"
    path.write_text(config_to_yaml(config))
    again = load_config(path)
    assert again == config
    assert config_to_dict(again) == config_to_dict(config)


@pytest.mark.parametrize("name", ["base", "replica", "tum", "synthetic", *PRESETS])
def test_every_shipped_config_loads(name):
    config = load_config(CONFIGS / f"{name}.yaml")
    assert isinstance(config, Config)


def test_dataset_configs_name_their_kind():
    assert load_config(CONFIGS / "replica.yaml").dataset.kind == "replica"
    assert load_config(CONFIGS / "tum.yaml").dataset.kind == "tum"
    assert load_config(CONFIGS / "synthetic.yaml").dataset.kind == "synthetic"


def test_unknown_key_names_the_key_and_the_nearest_valid_one():
    with pytest.raises(ConfigError, match=r"tracking\.iteratons.*did you mean 'tracking\.iterations'"):
        load_config(overrides=["tracking.iteratons=3"])
    with pytest.raises(ConfigError, match=r"unknown config key 'trackin'.*'tracking'"):
        config_from_dict({"trackin": {}})


def test_unknown_key_in_a_file_is_rejected(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("mapping:\n  iterations: 3\n  initial_opacty: 0.9\n")
    with pytest.raises(ConfigError, match="mapping.initial_opacty.*mapping.initial_opacity"):
        load_config(path)


def test_a_retired_key_says_what_replaced_it(tmp_path):
    path = tmp_path / "old_run_config.yaml"
    path.write_text("render:\n  eaa_point_area: 16\n")
    with pytest.raises(ConfigError, match=r"render\.eaa_point_area.*retired.*eaa_single_node_sigma"):
        load_config(path)


@pytest.mark.parametrize(
    "override, message",
    [
        ("tracking.iterations=-1", "tracking.iterations"),
        ("tracking.iterations=abc", "expected an integer"),
        ("tracking.iterations=2.5", "expected an integer"),
        ("render.eaa_max_nodes=0", "render.eaa_max_nodes"),
        ("render.mode=eea", "did you mean 'ewa'"),
        ("dataset.downscale=0", "dataset.downscale"),
        ("dataset.width=0", "dataset.width"),
        ("run.evaluate_at_end=maybe", "expected true or false"),
        ("eval.scales=[0.5,-1]", "eval.scales"),
        ("tracking.resolution_scale=fast", "expected a number"),
        ("tracking.resolution_scale=nan", "expected a number"),
        ("tracking.resolution_scale=0", "tracking.resolution_scale"),
        ("tracking.relocalise_loss_ratio=0.5", "tracking.relocalise_loss_ratio"),
        ("mapping.initial_opacity=1", "mapping.initial_opacity"),
        ("loop.fitness_threshold=1.5", "loop.fitness_threshold"),
        ("dataset.depth_noise_power=-1", "dataset.depth_noise_power"),
    ],
)
def test_wrong_types_and_out_of_range_values(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=[override])


def test_override_values_are_typed():
    config = load_config(overrides=["eval.scales=[0.25,0.5,1]", "dataset.fx=585", "tracking.use_exposure=true"])
    assert config.eval.scales == (0.25, 0.5, 1.0)
    assert config.dataset.fx == 585.0 and isinstance(config.dataset.fx, float)
    assert config.tracking.use_exposure is True


def test_exponent_without_a_dot_is_a_number():
    # YAML 1.1 reads 5e-4 as a string; a float field takes it as the number the user meant.
    config = load_config(overrides=["mapping.lr_poses=5e-4", "refine.lr_poses=1E-3"])
    assert config.mapping.lr_poses == 5e-4 and config.refine.lr_poses == 1e-3


def test_malformed_override():
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(overrides=["tracking.iterations"])
    with pytest.raises(ConfigError, match="name a section and a key"):
        load_config(overrides=["iterations=3"])


def test_inherit_from_merges_deeply_and_child_wins(tmp_path):
    (tmp_path / "parent.yaml").write_text("tracking:\n  iterations: 11\n  resolution_scale: 0.3\nmapping:\n  iterations: 5\n")
    (tmp_path / "child.yaml").write_text("inherit_from: parent.yaml\ntracking:\n  iterations: 22\n")
    config = load_config(tmp_path / "child.yaml")
    assert config.tracking.iterations == 22
    assert config.tracking.resolution_scale == 0.3
    assert config.mapping.iterations == 5


def test_preset_then_overrides_order():
    config = load_config(CONFIGS / "synthetic.yaml", preset="fast", overrides=["tracking.iterations=7"])
    fast = load_config(CONFIGS / "synthetic.yaml", preset="fast")
    assert config.tracking.iterations == 7
    assert fast.tracking.iterations < load_config(CONFIGS / "synthetic.yaml", preset="accurate").tracking.iterations


def test_unknown_preset():
    with pytest.raises(ConfigError, match="unknown preset 'fats'.*'fast'"):
        load_config(preset="fats")


def test_cyclic_inherit_from_is_an_error(tmp_path):
    (tmp_path / "a.yaml").write_text("inherit_from: b.yaml\n")
    (tmp_path / "b.yaml").write_text("inherit_from: a.yaml\n")
    with pytest.raises(ConfigError, match="cyclic inherit_from"):
        load_config(tmp_path / "a.yaml")


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("tracking: [1, 2\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(bad)
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load_config(top)


def test_yaml_is_read_safely(tmp_path):
    marker = tmp_path / "executed"
    evil = tmp_path / "evil.yaml"
    evil.write_text(f"run: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_config(evil)
    assert not marker.exists()


def test_relative_dataset_path_is_relative_to_the_file(tmp_path):
    sub = tmp_path / "cfg"
    sub.mkdir()
    (sub / "c.yaml").write_text("dataset:\n  kind: replica\n  path: ../data/seq\n")
    assert load_yaml_tree(sub / "c.yaml")["dataset"]["path"] == str((tmp_path / "data" / "seq").resolve())
    # A relative path given on the command line is relative to the working directory; both come out absolute.
    assert load_config(sub / "c.yaml", overrides=["dataset.path=other"]).dataset.path == str(Path.cwd() / "other")


def test_a_written_config_means_the_same_wherever_it_is_read(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = load_config(CONFIGS / "synthetic.yaml", overrides=["dataset.path=data/seq/"])
    assert config.dataset.path == str(tmp_path / "data" / "seq")
    run_dir = tmp_path / "runs" / "a"
    run_dir.mkdir(parents=True)
    (run_dir / "config.yaml").write_text(config_to_yaml(config))
    monkeypatch.chdir(run_dir)
    assert load_config(run_dir / "config.yaml") == config
    # a config built in code with a relative path is written with the path it meant in this process
    relative = config_from_dict({"dataset": {"path": "seq"}})
    assert f"path: {run_dir / 'seq'}" in config_to_yaml(relative)


def test_a_file_that_is_not_yaml_text(tmp_path):
    png = tmp_path / "config.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR")
    with pytest.raises(ConfigError, match=r"config.png: not a YAML text file \(byte 0x89 at offset 0"):
        load_config(png)
    nul = tmp_path / "nul.yaml"
    nul.write_bytes(b"run:\n  seed: 1\x00\n")
    with pytest.raises(ConfigError, match="not a YAML text file .it contains NUL bytes"):
        load_config(nul)
    with pytest.raises(ConfigError, match="is a folder, not a YAML config file"):
        load_config(tmp_path)


@pytest.mark.parametrize("text, where, problem", [
    ("tracking:\n  iterations: 3\n   alpha_color: 0.5\n", ":3:15", "mapping values are not allowed"),
    ("tracking: [1, 2\nmapping: {}\n", ":2:8", "expected ',' or ']'"),
    ("run:\n\tseed: 1\n", ":2:1", "found character '\\t'"),
])
def test_yaml_syntax_errors_give_line_and_column(tmp_path, text, where, problem):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}{where}: invalid YAML (") and problem in message and "\n" not in message


def test_values_yaml_cannot_build_are_config_errors(tmp_path):
    path = tmp_path / "date.yaml"
    path.write_text("run:\n  seed: 2001-13-45\n")  # a date with month 13
    with pytest.raises(ConfigError, match="date.yaml: invalid YAML .month must be in 1..12"):
        load_config(path)
    path.write_text("[" * 400)  # deeper than the (here lowered) recursion limit: PyYAML's parser recurses
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(len(inspect.stack()) + 300)
    try:
        with pytest.raises(ConfigError, match="nested too deeply"):
            load_config(path)
    finally:
        sys.setrecursionlimit(limit)


@pytest.mark.parametrize("override", ["mapping.lr_poses=.nan", "mapping.lr_poses=.inf",
                                      "mapping.lr_poses=-.inf", f"mapping.lr_poses={10 ** 400}"])
def test_non_finite_numbers_are_refused(override):
    with pytest.raises(ConfigError, match="mapping.lr_poses"):
        load_config(overrides=[override])


def test_a_misspelt_file_name_suggests_the_nearest_file(tmp_path):
    with pytest.raises(ConfigError, match=r"replca.yaml: config file not found; did you mean .*configs/replica.yaml\?"):
        load_config(CONFIGS / "replca.yaml")
    (tmp_path / "child.yaml").write_text("inherit_from: parnet.yaml\n")
    (tmp_path / "parent.yaml").write_text("run:\n  seed: 3\n")
    with pytest.raises(ConfigError, match=r"parnet.yaml: config file not found; did you mean .*parent.yaml\?"):
        load_config(tmp_path / "child.yaml")
    with pytest.raises(ConfigError, match=r"folder .*no_such_folder does not exist"):
        load_config(tmp_path / "no_such_folder" / "c.yaml")
    with pytest.raises(ConfigError, match=r"zzz.yaml: config file not found \(YAML files there: child.yaml, parent.yaml\)"):
        load_config(tmp_path / "zzz.yaml")


# ----------------------------------------------------------------------------- built-in configs by name

def test_the_built_in_configs_are_package_data_inside_the_package():
    assert CONFIG_DIR == REPO / "mipslam" / "configs" and not (REPO / "configs").exists()
    assert builtin_config_names() == ("base", "replica", "synthetic", "tum", *PRESETS)
    assert sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")) == sorted(builtin_config_names())
    listed = {c.name: c for c in builtin_configs()}
    assert [name for name, c in listed.items() if c.preset] == list(PRESETS)
    assert all(c.description and not c.description.startswith("#") for c in listed.values())
    assert listed["tum"].description.startswith("TUM RGB-D")


@pytest.mark.parametrize("name", ["base", "replica", "tum", "synthetic", *PRESETS])
def test_a_built_in_config_points_at_no_folder(name):
    """A packaged config cannot name a sequence: no checkout's sibling folder exists beside an installed package."""
    tree = load_yaml_tree(CONFIG_DIR / f"{name}.yaml")
    assert not (tree.get("dataset") or {}).get("path")
    assert load_config(name).dataset.path == ""


def test_a_built_in_config_by_name_is_its_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # any folder: nothing is read relative to the working directory
    assert load_config("tum") == load_config(CONFIG_DIR / "tum.yaml")
    assert load_config("replica", preset="fast") == load_config(CONFIG_DIR / "replica.yaml", preset="fast")
    assert load_config("tum").dataset.kind == "tum"
    # an existing file wins over the built-in of the same name
    (tmp_path / "tum").write_text("dataset:\n  kind: replica\n")
    assert load_config("tum").dataset.kind == "replica"
    # ... but a folder of that name (a sequence called tum, say) does not hide the built-in
    (tmp_path / "replica").mkdir()
    assert load_config("replica").dataset.kind == "replica"
    assert load_config("replica").dataset.depth_scale == 6553.5


def test_an_unknown_config_name_lists_the_built_ins(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=r"unknown config 'tmu' \(did you mean 'tum'\?\); built-in configs: base, "
                                          r"replica, synthetic, tum \(presets: fast, balanced, accurate\); or give a "
                                          r"YAML file"):
        load_config("tmu")
    (tmp_path / "mine.yaml").write_text("run:\n  seed: 1\n")
    with pytest.raises(ConfigError, match=r"unknown config 'mine' \(did you mean .*mine.yaml\?\)"):
        load_config("mine")
    # a file path stays a file path: not found, with the built-in's name where the file was a built-in's
    with pytest.raises(ConfigError, match=r"tum.yaml: config file not found; for the built-in config give its name: "
                                          r"tum"):
        load_config("tum.yaml")
    with pytest.raises(ConfigError, match=r"configs/tum.yaml: config file not found \(folder .* does not exist\); "
                                          r"for the built-in config give its name: tum"):
        load_config("configs/tum.yaml")


def test_inherit_from_may_name_a_built_in(tmp_path):
    (tmp_path / "mycam.yaml").write_text("inherit_from: tum\ndataset:\n  path: seq\n  camera: ''\n  fx: 500\n")
    config = load_config(tmp_path / "mycam.yaml", preset="fast")
    tum = load_config("tum", preset="fast")
    assert config.dataset.kind == "tum" and config.dataset.fx == 500 and config.dataset.camera == ""
    assert config.dataset.path == str(tmp_path / "seq")  # relative to the file that names it
    assert config.dataset.depth_scale == tum.dataset.depth_scale and config.tracking == tum.tracking
    # a file beside it wins over a built-in of the same name; a list may mix both
    (tmp_path / "base").write_text("run:\n  seed: 7\n")
    (tmp_path / "mix.yaml").write_text("inherit_from: [replica, base]\n")
    mixed = load_config(tmp_path / "mix.yaml")
    assert mixed.run.seed == 7 and mixed.dataset.kind == "replica"
    (tmp_path / "typo.yaml").write_text("inherit_from: tmu\n")
    with pytest.raises(ConfigError, match=r"typo.yaml: inherit_from: unknown config 'tmu' \(did you mean 'tum'\?\); "
                                          r"built-in configs: base, replica, synthetic, tum"):
        load_config(tmp_path / "typo.yaml")


def test_presets_are_read_from_the_package_wherever_the_run_starts(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fast = load_config(preset="fast")
    assert fast == load_config(overrides=[], preset="fast") and fast != load_config()
    assert load_config("synthetic", preset="accurate").render.eaa_max_nodes == \
        load_yaml_tree(CONFIG_DIR / "accurate.yaml")["render"]["eaa_max_nodes"]


def test_config_objects_are_frozen():
    config = load_config()
    with pytest.raises(Exception):
        config.tracking.iterations = 3  # type: ignore[misc]
