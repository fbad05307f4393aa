"""``mipslam bench --scenario``: the registry, option parsing in the CLI, every scenario at its smallest size, and
every ``mipslam bench --scenario`` command quoted in README.md and docs/ parsed by the real parser."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from mipslam.bench.scenarios import SCENARIOS, load_scenario, run_scenario, smoke_options
from mipslam.cli import _build_parser, _scenario_request, _UsageError, main
from mipslam.errors import MipslamError

REPO = Path(__file__).resolve().parent.parent
NEEDS_CPU_BACKEND = {"render_speed", "scaling"}  # they time the C++ rasterizer
NUMBER_CELL = re.compile(r"\|\s*[-+]?\d+(\.\d+)?(e[-+]?\d+)?\s*(ms|%|cm|dB)?\s*\|")


def _request(*argv: str):
    return _scenario_request(_build_parser().parse_args(["bench", *argv]))


# ----------------------------------------------------------------------------- registry and options

def test_every_scenario_module_is_registered_with_frozen_options_and_a_smoke_size():
    modules = {p.stem for p in (REPO / "mipslam" / "bench" / "scenarios").glob("*.py")} - {"__init__", "checkout"}
    assert modules == set(SCENARIOS)
    for name in SCENARIOS:
        module = load_scenario(name)
        assert dataclasses.is_dataclass(module.Options) and module.Options.__dataclass_params__.frozen
        fields = {f.name for f in dataclasses.fields(module.Options)}
        assert set(module.SMOKE) <= fields, name
        assert callable(module.run)


def test_list_scenarios_prints_one_line_each(capsys):
    assert main(["bench", "--list-scenarios"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split()[0] for line in lines] == list(SCENARIOS)


def test_set_routes_scenario_options_and_config_values():
    name, options = _request("--scenario", "multiscale", "--set", "multiscale.frames=8", "--set",
                             "multiscale.own_maps=yes", "--set", "mapping.iterations=3")
    assert name == "multiscale" and options.frames == 8 and options.own_maps is True
    assert options.config_overrides == ("mapping.iterations=3",)
    _, options = _request("--scenario", "frequency_loss", "--set", "frequency_loss.lambdas=0,10")
    assert options.lambdas == (0.0, 10.0)
    _, options = _request("--scenario", "render_speed", "--threads", "1", "--set", "render_speed.runs=a,b")
    assert options.threads == 1 and options.runs == ("a", "b")


def test_smoke_starts_from_the_smallest_size_and_set_wins():
    _, options = _request("--scenario", "aliasing", "--smoke", "--set", "aliasing.gaussians=7")
    module = load_scenario("aliasing")
    assert options == dataclasses.replace(module.Options(**module.SMOKE), gaussians=7)


@pytest.mark.parametrize("argv, needle", [
    (["--scenario", "aliasng"], "did you mean 'aliasing'"),
    (["--scenario", "aliasing", "--set", "aliasing.widht=8"], "did you mean 'aliasing.width'"),
    (["--scenario", "aliasing", "--set", "aliasing.width=eight"], "expected int"),
    (["--scenario", "aliasing", "--set", "aliasing.tune=maybe"], "expected bool"),
    (["--scenario", "aliasing", "--set", "mapping.iterations=3"], "takes no config values"),
    (["--scenario", "aliasing", "--set", "novalue"], "expected KEY=VALUE"),
    (["--scenario", "pgo", "--presets", "fast"], "takes no --presets"),
])
def test_bad_scenario_requests_name_what_is_wrong(argv, needle):
    with pytest.raises(_UsageError, match=re.escape(needle)):
        _request(*argv)


def test_cli_exit_codes_for_bad_requests(tmp_path, capsys):
    assert main(["bench", "--smoke"]) == 2
    assert "--smoke goes with --scenario" in capsys.readouterr().err
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "earlier.txt").write_text("kept")
    assert main(["bench", "--scenario", "pgo", "--smoke", "--out", str(occupied)]) == 2
    assert "not empty" in capsys.readouterr().err and (occupied / "earlier.txt").read_text() == "kept"


def test_test_helpers_are_found_only_in_a_source_checkout(tmp_path, monkeypatch):
    from mipslam.bench.scenarios import checkout

    assert checkout.import_test_helper("synthetic_pose_graphs").make_synthetic_pose_graph
    monkeypatch.setattr(checkout, "REPO", tmp_path)  # an installed copy: no tests/ beside the package
    with pytest.raises(MipslamError, match="source checkout"):
        checkout.import_test_helper("no_such_helper")


# ----------------------------------------------------------------------------- every scenario, smallest size

@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_runs_at_its_smallest_size(name, tmp_path):
    if name in NEEDS_CPU_BACKEND:
        from mipslam.render import cpu as cpu_backend

        if not cpu_backend.is_available():
            pytest.skip(f"the cpu backend cannot be built here: {cpu_backend.unavailable_reason()}")
    result = run_scenario(name, smoke_options(name), tmp_path / "out")
    record = json.loads((tmp_path / "out" / "bench.json").read_text())
    assert record["format"] == "mipslam benchmark 1" and record["benchmark"] == "bench"
    assert isinstance(record["machine"]["threads_per_job"], int) and record["machine"]["cpu_model"]
    assert set(dataclasses.asdict(smoke_options(name))) <= set(record["parameters"])
    assert record["results"]
    table = result.files.markdown.read_text()
    assert table.startswith("Machine: ") and result.files.markdown == tmp_path / "out" / "bench.md"
    rows = [line for line in table.splitlines() if line.startswith("|") and not set(line) <= set("|-: ")]
    assert rows and any(NUMBER_CELL.search(line) for line in rows), table
    for plot in result.plots:
        assert plot.is_file() and plot.stat().st_size > 0


def test_a_scenario_refuses_an_occupied_output_folder(tmp_path):
    (tmp_path / "bench.json").write_text("{}")
    with pytest.raises(MipslamError, match="not empty"):
        run_scenario("pgo", smoke_options("pgo"), tmp_path)
    assert (tmp_path / "bench.json").read_text() == "{}"


# ----------------------------------------------------------------------------- commands quoted in the docs

def _quoted_commands() -> list[tuple[str, str]]:
    """(file, command) for every ``mipslam bench --scenario`` command in README.md and docs/*.md."""
    found = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8").replace("\\\n", " ")
        for line in text.splitlines():
            for match in re.finditer(r"mipslam bench --scenario[^`\n]*", line):
                command = match.group(0).split("  #")[0].strip()
                found.append((path.name, command))
    return found


def test_the_docs_quote_scenario_commands():
    assert len({command.split()[3] for _, command in _quoted_commands()}) >= 8


PLACEHOLDER_VALUES = {"N": "2", "R": "1", "S": "0"}  # "--set long_run.frames=N": a number the text chooses


@pytest.mark.parametrize("where, command", _quoted_commands())
def test_every_quoted_scenario_command_parses(where, command):
    argv = [token for token in shlex.split(command.replace("[", " ").replace("]", " ")) if token != "..."]
    assert argv[:2] == ["mipslam", "bench"], (where, command)
    if argv[3] == "NAME":  # the synopsis
        return
    argv = [re.sub(r"=([NRS])$", lambda m: "=" + PLACEHOLDER_VALUES[m.group(1)], token) for token in argv]
    name, options = _request(*[token for token in argv[2:] if token != "ARGS"])
    assert name in SCENARIOS


def test_sequence_scenarios_read_a_folder_with_its_own_kinds_config(tmp_path):
    from mipslam.bench.scenarios.checkout import CONFIGS, sequence_config

    synth, tum, replica = tmp_path / "synth", tmp_path / "tum", tmp_path / "replica"
    for folder in (synth, tum, replica / "results"):
        folder.mkdir(parents=True)
    (synth / "synth.json").write_text("{}")
    (tum / "rgb.txt").write_text(""), (tum / "depth.txt").write_text("")
    assert sequence_config("", [f"dataset.path={synth}"]) == str(CONFIGS / "synthetic.yaml")
    assert sequence_config("", [f"dataset.path={tum}", "loop.enabled=true"]) == str(CONFIGS / "tum.yaml")
    assert sequence_config("", [f"dataset.path={tum}", f"dataset.path={replica}"]) == str(CONFIGS / "replica.yaml")
    assert sequence_config("", []) == str(CONFIGS / "tum.yaml")  # no folder: the real-data default
    assert sequence_config("mine.yaml", [f"dataset.path={synth}"]) == "mine.yaml"  # an explicit config wins


def test_loop_edges_reads_the_ground_truth_shifted_in_time(tmp_path):
    from types import SimpleNamespace

    from mipslam.bench.scenarios.loop_edges import _shifted_ground_truth

    # A camera sliding along x at 1 m/s, sampled every 10 ms; frames at 0.30 s and 0.50 s.
    lines = [f"{0.01 * k:.2f} {0.01 * k:.2f} 0 0 0 0 0 1" for k in range(101)]
    (tmp_path / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    config = SimpleNamespace(dataset=SimpleNamespace(kind="tum", path=str(tmp_path), association_tolerance_s=0.02))
    T_wc, valid = _shifted_ground_truth(config, np.array([0.30, 0.50]), 0.05)
    assert valid.all()
    # Stamps 50 ms later: the pose stamped 0.30 s is the one recorded at 0.25 s.
    np.testing.assert_allclose(T_wc[:, 0, 3].numpy(), [0.25, 0.45], atol=1e-9)
    synthetic = SimpleNamespace(dataset=SimpleNamespace(kind="synthetic", path=str(tmp_path), association_tolerance_s=0.02))
    with pytest.raises(MipslamError, match="read as synthetic"):
        _shifted_ground_truth(synthetic, np.array([0.3]), 0.05)


def test_loop_edges_splits_the_accepted_pairs_by_their_overlap():
    from mipslam.bench.scenarios.loop_edges import _by_fitness

    rows = _by_fitness((0.3, 0.5, 1.0), fitness=[0.35, 0.45, 0.5, 0.9, 1.0], errors_t=[4.0, 2.0, 1.0, 3.0, 5.0],
                       errors_r=[1.0, 3.0, 0.5, 0.7, 0.9], claimed_t=[0.4, 0.4, 0.2, 0.2, 0.2])
    # [0.3, 0.5) holds the first two; the last bin is closed, so 0.5 and 1.0 both fall into [0.5, 1.0]
    assert [row["accepted"] for row in rows] == [2, 3]
    assert rows[0]["error_t_cm_median"] == 3.0 and rows[0]["error_r_deg_median"] == 2.0
    assert rows[1]["error_t_cm_median"] == 3.0 and rows[1]["claimed_t_cm_median"] == 0.2
    empty = _by_fitness((0.3, 0.5), [0.9], [1.0], [1.0], [1.0])
    assert empty[0]["accepted"] == 0 and math.isnan(empty[0]["error_t_cm_median"])
