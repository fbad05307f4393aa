"""mipslam bench: sweep parsing, planning, statistics, Pareto front, failed jobs, outputs, and end to end
(local processes and, where Ray is installed, a local Ray instance) on a tiny synthetic sequence."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

import data_synth
from mipslam.bench import (BenchSpec, JobResult, LocalExecutor, RayExecutor, fit_power_law, pareto_front,
                           parse_presets, parse_sweep, plan_jobs, plan_settings, resolve_target, spread, summarize,
                           write_outputs)
from mipslam.bench.execute import execute_job
from mipslam.bench.spec import Job, Setting, split_values
from mipslam.cli import main
from mipslam.errors import ConfigError, DatasetError, MipslamError

REPO = Path(__file__).resolve().parent.parent
TINY = ["mapping.first_frame_iterations=20", "mapping.iterations=5", "mapping.densify_pixel_stride=2",
        "tracking.iterations=10", "keyframes.window_size=3", "keyframes.random_past=1", "loop.enabled=false"]


# ----------------------------------------------------------------------------- sweeps, presets, targets

def test_sweep_values_are_yaml_and_split_outside_brackets():
    assert split_values("1,2,[0.25,0.5],'a,b'") == ["1", "2", "[0.25,0.5]", "'a,b'"]
    sweep = parse_sweep("render.eaa_max_nodes=1,2,16")
    assert sweep.key == "render.eaa_max_nodes" and sweep.values == (1, 2, 16)
    assert sweep.assignments() == ("render.eaa_max_nodes=1", "render.eaa_max_nodes=2", "render.eaa_max_nodes=16")
    assert parse_sweep("eval.scales=[1],[0.5],[0.25,0.5]").values == ([1], [0.5], [0.25, 0.5])
    assert parse_sweep("loop.enabled=true,false").values == (True, False)


@pytest.mark.parametrize("text, needle", [
    ("render.eaa_max_node=1,2", "did you mean 'render.eaa_max_nodes'"),
    ("rendr.mode=eaa", "unknown config key 'rendr.mode'"),
    ("render.eaa_max_nodes=1,0", "render.eaa_max_nodes"),
    ("tracking.iterations=10,ten", "tracking.iterations"),
    ("render.mode=eaa,pointt", "did you mean 'point'"),
    ("tracking.iterations=10,,20", "empty value"),
    ("tracking.iterations=10,10", "listed twice"),
    ("tracking.iterations", "expected KEY=V1,V2"),
])
def test_bad_sweeps_name_the_key(text, needle):
    with pytest.raises(ConfigError) as info:
        parse_sweep(text)
    assert needle in str(info.value)
    if "=" in text:
        assert text.split("=")[0] in str(info.value)


def test_presets():
    assert parse_presets(None) == (None,)
    assert parse_presets("fast, balanced,none") == ("fast", "balanced", None)
    with pytest.raises(ConfigError, match="did you mean 'fast'"):
        parse_presets("fats")
    with pytest.raises(ConfigError, match="listed twice"):
        parse_presets("fast,fast")


def test_sequence_folders_are_detected(tmp_path):
    replica, tum, synth, other = (tmp_path / n for n in ("replica", "tum", "synth", "other"))
    (replica / "results").mkdir(parents=True)
    tum.mkdir()
    (tum / "rgb.txt").write_text("")
    (tum / "depth.txt").write_text("")
    synth.mkdir()
    (synth / "synth.json").write_text("{}")
    other.mkdir()
    for folder, kind in ((replica, "replica"), (tum, "tum"), (synth, "synthetic")):
        target = resolve_target(folder)
        assert target.kind == kind and target.config_path == REPO / "mipslam" / "configs" / f"{kind}.yaml"
        assert target.base_overrides == (f"dataset.path={folder.resolve()}",)
    config = resolve_target(REPO / "mipslam" / "configs" / "tum.yaml")
    assert config.kind == "config" and config.base_overrides == ()
    builtin = resolve_target("tum")  # a built-in config by name, as mipslam run takes it
    assert builtin.kind == "config" and builtin.config_path == config.config_path and builtin.name == "tum"
    with pytest.raises(DatasetError, match="not a sequence folder"):
        resolve_target(other)
    with pytest.raises(DatasetError, match="not found"):
        resolve_target(tmp_path / "missing")


# ----------------------------------------------------------------------------- planning

def _spec(tmp_path, **kw) -> BenchSpec:
    seq = tmp_path / "seq"
    (seq / "results").mkdir(parents=True, exist_ok=True)
    return BenchSpec(target=resolve_target(seq), out_dir=tmp_path / "out", **kw)


def test_plan_is_the_cartesian_product_repeat_major(tmp_path):
    spec = _spec(tmp_path, presets=("fast", "accurate"), sweeps=(parse_sweep("render.eaa_max_nodes=1,4"),
                                                                 parse_sweep("tracking.iterations=5,10,20")),
                 repeat=2, threads=2, overrides=("run.threads=1",), max_frames=7)
    settings = plan_settings(spec)
    assert len(settings) == 2 * 2 * 3
    labels = [s.label for s in settings]
    assert labels[0] == "fast render.eaa_max_nodes=1 tracking.iterations=5"
    assert labels[-1] == "accurate render.eaa_max_nodes=4 tracking.iterations=20"
    assert len(set(labels)) == len(labels)
    assert all(s.threads == 1 for s in settings)  # --set wins over --threads
    jobs = plan_jobs(spec, settings)
    assert len(jobs) == 24
    assert [j.repeat for j in jobs] == [0] * 12 + [1] * 12
    assert [j.setting.index for j in jobs[:12]] == list(range(12)) == [j.setting.index for j in jobs[12:]]
    assert len({j.run_dir for j in jobs}) == 24
    assert all(j.run_dir.parent == (tmp_path / "out" / "runs").resolve() for j in jobs)
    cmd = list(jobs[13].run_command)
    assert cmd[1:5] == ["-m", "mipslam.cli", "-q", "run"] and cmd[cmd.index("--preset") + 1] == "fast"
    sets = [cmd[i + 1] for i, a in enumerate(cmd) if a == "--set"]
    # dataset path, the bench's own keys, then --set, then the sweep values (later wins)
    assert sets[0].startswith("dataset.path=")
    assert sets[1:4] == ["run.seed=0", "run.threads=2", "dataset.max_frames=7"]
    assert sets[4:] == ["run.threads=1", "render.eaa_max_nodes=1", "tracking.iterations=10"]
    assert cmd[-3:] == ["--out", str(jobs[13].run_dir), "--no-eval"]
    assert jobs[13].setting.render_mode == "eaa" and jobs[13].setting.seed == 0


def test_plan_rejects_bad_settings_before_running(tmp_path):
    with pytest.raises(ConfigError, match="tracking.iteratons"):
        plan_settings(_spec(tmp_path, overrides=("tracking.iteratons=3",)))
    with pytest.raises(ConfigError, match="--repeat 0"):
        _spec(tmp_path, repeat=0)
    with pytest.raises(ConfigError, match="swept twice"):
        _spec(tmp_path, sweeps=(parse_sweep("tracking.iterations=1,2"), parse_sweep("tracking.iterations=3")))


# ----------------------------------------------------------------------------- statistics

def test_spread_median_iqr_and_skips_missing():
    s = spread([4.0, None, 1.0, 100.0, float("nan"), 3.0, 2.0])
    assert (s.n, s.median, s.min, s.max, s.q1, s.q3) == (5, 3.0, 1.0, 100.0, 2.0, 4.0)
    assert spread([None, float("inf")]) is None
    assert spread([2.5]).median == 2.5


def test_pareto_front_on_hand_built_points():
    # (frames/s, ATE cm): higher fps and lower ATE are better
    points = [(1.0, 1.0),   # best ATE: front
              (2.0, 2.0),   # fastest (tied): front
              (1.5, 2.5),   # dominated by (2.0, 2.0)
              (2.0, 2.0),   # equal to point 1: neither dominates the other
              (None, 0.1),  # failed: never on the front, dominates nothing
              (0.5, 1.0),   # same ATE as point 0, slower: dominated
              (2.0, 3.0)]   # same fps as point 1, worse ATE: dominated
    assert pareto_front(points, (True, False)) == [True, True, False, True, False, False, False]
    # (frames/s, PSNR dB): both higher is better
    assert pareto_front([(1, 30), (2, 25), (1.5, 24), (0.5, 30)], (True, True)) == [True, True, False, False]


def _row(index, setting, repeat, fps=None, ate=None, psnr=None, error=None, stages=None) -> JobResult:
    return JobResult(setting_index=index, setting=setting, preset=None, assignments=(), repeat=repeat, seed=0, threads=2,
                     run_dir=f"/x/{setting}-{repeat}", host="h", error=error, fps=fps, ate_rmse_cm=ate, psnr_db=psnr,
                     wall_s=None if error else 10.0 + repeat, gaussians=None if error else 1000, keyframes=None if error else 5,
                     stage_ms_per_frame=stages or {})


def _rows():
    return [
        _row(0, "fast", 0, 4.0, 2.0, 25.0, stages={"tracking": 150.0, "mapping": 100.0}),
        _row(1, "slow", 0, 1.0, 1.0, 30.0, stages={"tracking": 600.0, "mapping": 400.0}),
        _row(2, "broken", 0, error="exit code 2: error: boom"),
        _row(0, "fast", 1, 3.0, 2.2, 25.0, stages={"tracking": 200.0, "mapping": 133.0}),
        _row(1, "slow", 1, None, None, None, error="timed out after 5 s (killed)"),
        _row(2, "broken", 1, error="exit code 2: error: boom"),
        _row(0, "fast", 2, 5.0, 2.1, 25.0, stages={"tracking": 120.0, "mapping": 80.0}),
        _row(3, "dominated", 0, 0.9, 3.0, 20.0),
    ]


def test_summarize_medians_over_ok_rows_and_failed_rows_kept():
    summaries = summarize(_rows())
    assert [s.setting for s in summaries] == ["fast", "slow", "broken", "dominated"]
    fast, slow, broken, dominated = summaries
    assert (fast.jobs, fast.failed, fast.fps.median, fast.fps.min, fast.fps.max) == (3, 0, 4.0, 3.0, 5.0)
    assert fast.ate_rmse_cm.median == pytest.approx(2.1) and fast.stage_ms_per_frame["tracking"].median == 150.0
    assert (slow.jobs, slow.failed, slow.fps.n, slow.fps.median) == (2, 1, 1, 1.0)
    assert slow.errors == ("repeat 1: timed out after 5 s (killed)",)
    assert broken.failed == 2 and broken.fps is None and broken.ate_rmse_cm is None
    assert [s.on_front_ate for s in summaries] == [True, True, False, False]
    assert [s.on_front_psnr for s in summaries] == [True, True, False, False]


def test_fit_power_law_recovers_exponent():
    x = [1e3, 3e3, 1e4, 3e4, 1e5]
    fit = fit_power_law(x, [3.0 * v ** 1.5 for v in x])
    assert fit.exponent == pytest.approx(1.5) and fit.coefficient == pytest.approx(3.0) and fit.r2 == pytest.approx(1.0)
    noisy = fit_power_law(x, [2.0 * v * (1.1 if i % 2 else 0.9) for i, v in enumerate(x)])
    assert 0.9 < noisy.exponent < 1.1 and noisy.r2 < 1.0
    with pytest.raises(MipslamError, match="all x are equal"):
        fit_power_law([2.0, 2.0], [1.0, 3.0])
    with pytest.raises(MipslamError, match="positive"):
        fit_power_law([1.0, 2.0], [0.0, 3.0])


# ----------------------------------------------------------------------------- failed jobs, executors, outputs

def _fake_job(tmp_path, code: str, timeout_s: float = 60.0) -> Job:
    setting = Setting(0, None, (), (), 1, 0, "eaa", "auto")
    run_dir = tmp_path / "runs" / "job"
    return Job(setting, 0, run_dir, tmp_path / "logs", (sys.executable, "-c", code), timeout_s)


def test_failed_jobs_are_rows_with_their_error(tmp_path):
    crashed = execute_job(_fake_job(tmp_path, "import sys; print('error: map exploded', file=sys.stderr); sys.exit(3)"))
    assert not crashed.ok and crashed.returncode == 3 and "exit code 3" in crashed.error
    assert "map exploded" in crashed.error and crashed.wall_s > 0
    assert "map exploded" in (tmp_path / "logs" / "s00-config-r0.run.log").read_text()
    timed_out = execute_job(_fake_job(tmp_path, "import time; time.sleep(30)", timeout_s=0.5))
    assert not timed_out.ok and "timed out after 0.5 s" in timed_out.error and timed_out.wall_s < 20
    silent = execute_job(_fake_job(tmp_path, "pass"))
    assert not silent.ok and "timings.json is missing" in silent.error and silent.returncode == 0


def test_local_executor_keeps_plan_order_and_records_parallelism(tmp_path):
    jobs = [_fake_job(tmp_path, "") for _ in range(5)]
    jobs = [Job(j.setting, i, j.run_dir, j.log_dir, j.run_command, 1.0) for i, j in enumerate(jobs)]

    def fake(job):
        import time
        time.sleep(0.02 * (5 - job.repeat))  # later jobs finish first
        return _row(0, "s", job.repeat, 1.0 + job.repeat, 1.0, 20.0)

    seen = []
    rows = LocalExecutor(parallel=3, run=fake)(jobs, lambda i, r: seen.append(i))
    assert [r.repeat for r in rows] == [0, 1, 2, 3, 4] and sorted(seen) == [0, 1, 2, 3, 4]
    assert LocalExecutor(parallel=3).describe()["parallel_jobs"] == 3
    with pytest.raises(MipslamError, match="--jobs 0"):
        LocalExecutor(parallel=0)


def test_ray_missing_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MipslamError, match=r"pip install 'mipslam\[ray\]'"):
        RayExecutor()([_fake_job(tmp_path, "")], lambda i, r: None)


def test_outputs_from_hand_built_rows(tmp_path):
    rows = _rows()
    summaries = summarize(rows)
    machine = {"cpu_model": "Test CPU", "logical_cores": 2, "usable_cores": 2, "load_average_1_5_15_min_at_start": [0.1],
               "threads_per_job": 2, "torch": "x", "mipslam": "y", "git": None}
    files = write_outputs(tmp_path / "out", machine, {"executor": "local processes", "note": "one job at a time"},
                          {"target": "seq", "repeat": 3, "seed": 0}, rows, summaries)
    data = json.loads(files.json.read_text())  # strict JSON (no NaN)
    assert len(data["jobs"]) == 8 and sum(not j["ok"] for j in data["jobs"]) == 3
    assert data["settings"][0]["fps"]["median"] == 4.0 and data["settings"][2]["fps"] is None
    assert data["settings"][1]["pareto_front"] == {"fps_vs_ate": True, "fps_vs_psnr": True}
    md = files.markdown.read_text()
    assert "Test CPU" in md and "timed out after 5 s" in md and "| `fast` | mipslam | 3/3 | 4.00 [3.00–5.00] |" in md
    assert files.plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_bench_usage_errors(tmp_path, capsys):
    assert main(["bench", str(tmp_path / "nope")]) == 2
    assert "not found" in capsys.readouterr().err
    seq = tmp_path / "seq"
    (seq / "results").mkdir(parents=True)
    assert main(["bench", str(seq), "--sweep", "render.eaa_max_node=1,2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "render.eaa_max_node" in err and len(err.splitlines()) == 1
    assert main(["bench", str(seq), "--jobs", "2", "--ray"]) == 2
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    assert main(["bench", str(seq), "--out", str(tmp_path / "full")]) == 2
    assert "not empty" in capsys.readouterr().err


# ----------------------------------------------------------------------------- end to end

@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bench") / "seq"
    # 6 frames: frame 5 is the one novel view (MonoGS's every 5th frame that is not a keyframe)
    data_synth.generate(out, layout="replica", trajectory="loop", width=40, height=30, frames=6, seed=0, supersample=2)
    return out


def _bench_args(sequence: Path, out: Path, *extra: str) -> list[str]:
    args = ["-q", "bench", str(sequence), "--out", str(out), "--threads", "1", *extra]
    for item in TINY:
        args += ["--set", item]
    return args


def _check_good_jobs(good: list[dict]) -> None:
    for j in good:
        assert j["ok"] and j["error"] is None, j["error"]
        assert j["frames"] == 6 and j["fps"] > 0 and j["wall_s"] > 0
        # A sanity bound (a metre/centimetre mix-up or a lost track fails it), not an accuracy test: a few
        # frames at 40x30 with 10 tracking iterations land anywhere in 2.5-3.5 cm (adam and rprop alike).
        assert 0 <= j["ate_rmse_cm"] < 5.0 and j["psnr_db"] > 12.0 and j["psnr_train_db"] > 12.0
        assert j["gaussians"] > 0 and j["keyframes"] >= 1 and j["torch_threads"] == 1
        assert {"tracking", "mapping"} <= set(j["stage_ms_per_frame"])
        assert sum(j["stage_ms_per_frame"].values()) == pytest.approx(1000.0 / j["fps"], rel=1e-6)
        assert (Path(j["run_dir"]) / "traj_est.txt").is_file() and (Path(j["run_dir"]) / "bench_eval.json").is_file()
        assert j["eval_wall_s"] > 0


def test_bench_end_to_end_with_a_broken_setting(tiny_sequence, tmp_path, capsys):
    out = tmp_path / "bench"
    repeats = 2
    # dataset.first_frame=1000 passes the config check and fails at run time (the sequence has 6 frames)
    assert main(_bench_args(tiny_sequence, out, "--repeat", "2", "--sweep", "dataset.first_frame=0,1000")) == 0
    data = json.loads((out / "bench.json").read_text())
    jobs = data["jobs"]
    assert len(jobs) == 2 * repeats
    assert [(j["setting_index"], j["repeat"]) for j in jobs] == [(0, 0), (1, 0), (0, 1), (1, 1)]
    good = [j for j in jobs if j["assignments"] == ["dataset.first_frame=0"]]
    bad = [j for j in jobs if j["assignments"] == ["dataset.first_frame=1000"]]
    assert len(good) == len(bad) == repeats
    _check_good_jobs(good)
    for j in bad:
        assert not j["ok"] and j["returncode"] == 2 and "beyond the sequence" in j["error"]
    settings = data["settings"]
    assert settings[0]["failed"] == 0 and settings[1]["failed"] == repeats and settings[1]["fps"] is None
    assert settings[0]["pareto_front"] == {"fps_vs_ate": True, "fps_vs_psnr": True}
    assert data["machine"]["cpu_model"] and data["machine"]["torch"] and data["machine"]["backend_used"]
    md = (out / "bench.md").read_text()
    assert "beyond the sequence" in md and f"| `config dataset.first_frame=0` | mipslam | {repeats}/{repeats} |" in md
    assert (out / "bench.png").read_bytes()[:4] == b"\x89PNG"
    assert data["execution"]["executor"] == "local processes" and data["execution"]["parallel_jobs"] == 1
    good = [j for j in data["jobs"] if j["ok"]]
    # a fixed seed on CPU: the repeats measure time, the results are the same
    assert good[0]["ate_rmse_cm"] == good[1]["ate_rmse_cm"] and good[0]["gaussians"] == good[1]["gaussians"]
    assert len((out / "jobs.jsonl").read_text().splitlines()) == 4
    assert "2 of 4 jobs failed" in capsys.readouterr().err


def test_bench_on_a_local_ray_instance(tiny_sequence, tmp_path):
    pytest.importorskip("ray", reason="Ray is optional (pip install 'mipslam[ray]')")
    out = tmp_path / "bench_ray"
    assert main(_bench_args(tiny_sequence, out, "--repeat", "1", "--presets", "fast", "--ray")) == 0
    data = json.loads((out / "bench.json").read_text())
    assert data["execution"]["executor"] == "ray" and data["execution"]["address"] == "local instance"
    assert len(data["jobs"]) == 1 and data["jobs"][0]["setting"] == "fast"
    _check_good_jobs(data["jobs"])
    assert data["settings"][0]["fps"]["median"] == data["jobs"][0]["fps"]
    assert "| `fast` | mipslam | 1/1 |" in (out / "bench.md").read_text() and (out / "bench.png").is_file()
