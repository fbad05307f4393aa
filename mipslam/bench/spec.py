"""What a bench runs: the target (config or sequence folder), the settings and the jobs (pure planning).

A *setting* is one preset (or the config as it is) combined with one value of every ``--sweep``
(the cartesian product); a *job* is one setting at one repeat index. Planning resolves every
setting's config once (``load_config``) so a bad key or value fails before anything runs, with the
key named. Jobs are ordered repeat-major (every setting once, then every setting again, ...) so a
change of the machine's load over the bench hits all settings alike instead of one setting's repeats.
"""
from __future__ import annotations

import dataclasses
import difflib
import re
import sys
import time
from dataclasses import dataclass, field
from itertools import product
from pathlib import Path
from typing import Any

import yaml

from mipslam.bench.peers import PeerOptions, check_peers_available, default_peer_repeats
from mipslam.config import CONFIG_DIR, PRESETS, Config, builtin_config_names, load_config, preset_path
from mipslam.errors import ConfigError, DatasetError, MipslamError

__all__ = [
    "BenchSpec", "Job", "Setting", "Sweep", "Target", "detect_sequence_kind", "parse_presets", "parse_sweep",
    "plan_jobs", "plan_settings", "resolve_target", "split_values",
]

NO_PRESET = "none"  # in --presets: the config as it is, without a preset overlay
EVAL_FILE = "bench_eval.json"  # the evaluation of a bench job, inside its run folder
PEER_JOB_FILE = "peer_job.json"  # a peer job's description, inside its run folder (the worker's input)


# ----------------------------------------------------------------------------- sweeps and presets

@dataclass(frozen=True)
class Sweep:
    """One ``--sweep KEY=V1,V2,...``: a config key and its values (parsed as YAML scalars/lists)."""

    key: str  # "section.field", e.g. "render.eaa_max_nodes"
    values: tuple[Any, ...]
    texts: tuple[str, ...]  # the values as written (labels, run folder names)

    def assignments(self) -> tuple[str, ...]:
        """The ``--set`` overrides of each value, e.g. ``("render.eaa_max_nodes=1", ...)``."""
        return tuple(f"{self.key}={text}" for text in self.texts)


def split_values(text: str) -> list[str]:
    """Split ``"1,2,[0.25,0.5]"`` at the commas outside brackets/quotes -> ``["1", "2", "[0.25,0.5]"]``."""
    parts, depth, quote, current = [], 0, "", []
    for char in text:
        if quote:
            quote = "" if char == quote else quote
        elif char in "\"'":
            quote = char
        elif char in "[{":
            depth += 1
        elif char in "]}":
            depth -= 1
        elif char == "," and depth == 0:
            parts.append("".join(current).strip())
            current = []
            continue
        current.append(char)
    parts.append("".join(current).strip())
    return parts


def _config_key_names() -> dict[str, list[str]]:
    """Section name -> its field names, from the Config dataclasses."""
    defaults = Config()
    return {section.name: [f.name for f in dataclasses.fields(getattr(defaults, section.name))]
            for section in dataclasses.fields(Config)}


def check_config_key(key: str, where: str = "--sweep") -> None:
    """Raise ConfigError naming ``key`` (with the nearest valid key) unless it is ``section.field``."""
    sections = _config_key_names()
    parts = key.split(".")
    every = [f"{s}.{k}" for s, keys in sections.items() for k in keys]
    if len(parts) != 2 or parts[0] not in sections or parts[1] not in sections[parts[0]]:
        near = difflib.get_close_matches(key, every, n=1, cutoff=0.5)
        hint = f"; did you mean '{near[0]}'?" if near else "; keys look like section.field, e.g. tracking.iterations"
        raise ConfigError(f"{where} {key}: unknown config key '{key}'{hint}")


def parse_sweep(text: str) -> Sweep:
    """``"render.eaa_max_nodes=1,2,4"`` -> :class:`Sweep`; every value is checked against the config schema.

    Values are YAML (``true``, ``0.5``, ``[0.25,0.5]``); commas inside brackets do not split. Errors
    (ConfigError) name the key: unknown key (with the nearest one), no values, a value twice, a value the
    config rejects (type or range).
    """
    if "=" not in text:
        raise ConfigError(f"--sweep '{text}': expected KEY=V1,V2,... e.g. render.eaa_max_nodes=1,2,4")
    key, raw = (s.strip() for s in text.split("=", 1))
    check_config_key(key)
    texts = split_values(raw)
    if not raw or any(not t for t in texts):
        raise ConfigError(f"--sweep {key}: empty value in '{raw}'; give values separated by commas, e.g. {key}=1,2")
    if len(set(texts)) != len(texts):
        twice = sorted({t for t in texts if texts.count(t) > 1})
        raise ConfigError(f"--sweep {key}: value(s) {', '.join(twice)} listed twice")
    values = []
    section, name = key.split(".")
    for value_text in texts:
        try:
            value = yaml.safe_load(value_text)
        except yaml.YAMLError:
            value = value_text
        try:
            load_config(None, overrides=[f"{key}={value_text}"])
        except ConfigError as exc:
            raise ConfigError(f"--sweep {key}: value {value_text!r} rejected: {exc}") from None
        values.append(value)
    return Sweep(key, tuple(values), tuple(texts))


def parse_presets(text: str | None) -> tuple[str | None, ...]:
    """``"fast,balanced"`` -> ``("fast", "balanced")``; ``none`` (or nothing) = the config without a preset."""
    if text is None:
        return (None,)
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ConfigError(f"--presets '{text}': give preset names separated by commas ({', '.join(PRESETS)}, none)")
    out: list[str | None] = []
    for name in names:
        if name != NO_PRESET:
            preset_path(name)  # ConfigError with the nearest preset name
        value = None if name == NO_PRESET else name
        if value in out:
            raise ConfigError(f"--presets '{text}': preset '{name}' listed twice")
        out.append(value)
    return tuple(out)


# ----------------------------------------------------------------------------- target

@dataclass(frozen=True)
class Target:
    """What the bench runs on: a config file and the overrides that point it at the sequence."""

    config_path: Path
    base_overrides: tuple[str, ...]  # e.g. ("dataset.path=/data/seq",) for a sequence folder
    kind: str  # "config" for a YAML file, else the detected dataset kind
    name: str  # for the default output folder and the tables
    source: Path  # what the user named (the config file or the sequence folder), absolute


def detect_sequence_kind(folder: Path) -> str:
    """``synthetic`` (data_synth: ``synth.json``), ``replica`` (``results/`` [+ ``traj.txt``]) or ``tum``
    (``rgb.txt`` + ``depth.txt``); DatasetError naming the folder otherwise."""
    if (folder / "synth.json").is_file():
        return "synthetic"
    if (folder / "results").is_dir():
        return "replica"
    if (folder / "rgb.txt").is_file() and (folder / "depth.txt").is_file():
        return "tum"
    raise DatasetError(folder, "not a sequence folder mipslam knows: expected synth.json (data_synth), results/ and "
                               "traj.txt (Replica) or rgb.txt and depth.txt (TUM); or give a YAML config instead")


def resolve_target(path: str | Path, config_dir: Path = CONFIG_DIR) -> Target:
    """A YAML config as it is (or a built-in config by name, ``tum``), or a sequence folder with the built-in
    config of its kind (``config_dir/<kind>.yaml``) and ``dataset.path`` set."""
    path = Path(path).expanduser()
    if not path.exists() and str(path) in builtin_config_names():
        config = CONFIG_DIR / f"{path}.yaml"
        return Target(config, (), "config", str(path), config)
    if not path.exists():
        names = ", ".join(name for name in builtin_config_names() if name not in PRESETS)
        raise DatasetError(path, f"not found; give a YAML config, a built-in config's name ({names}) or a sequence "
                                 "folder (Replica, TUM or data_synth)")
    if path.is_file():
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise ConfigError(f"{path}: expected a YAML config (.yaml) or a sequence folder")
        return Target(path.resolve(), (), "config", path.stem, path.resolve())
    kind = detect_sequence_kind(path)
    config = config_dir / f"{kind}.yaml"
    if not config.is_file():
        raise ConfigError(f"{config}: dataset config missing; the installed package is incomplete, reinstall mipslam")
    return Target(config, (f"dataset.path={path.resolve()}",), kind, path.resolve().name, path.resolve())


# ----------------------------------------------------------------------------- spec, settings, jobs

@dataclass(frozen=True)
class BenchSpec:
    """Everything ``mipslam bench`` was asked to do (frozen; :func:`plan_jobs` turns it into jobs).

    overrides: ``--set`` (win over the bench's own seed/threads/max-frames); sweeps win over both.
    timeout_s: per ``mipslam run`` process. python: the interpreter of the job processes.
    peers: peer systems run on the same frames (:mod:`mipslam.bench.peers`); they take the ``dataset.*``
    sweep values (other keys do not concern them). peer_repeat: runs per peer setting (None: each peer's
    default, 3 for ORB-SLAM3, 1 for the Open3D peers, whose runs differ only in the 4th digit).
    peer_python: the peers' interpreter. run_mipslam: False = peers only.
    """

    target: Target
    out_dir: Path
    presets: tuple[str | None, ...] = (None,)
    sweeps: tuple[Sweep, ...] = ()
    overrides: tuple[str, ...] = ()
    repeat: int = 3
    threads: int = 2
    seed: int = 0
    max_frames: int | None = None
    timeout_s: float = 3600.0
    python: str = field(default_factory=lambda: sys.executable)
    peers: tuple[str, ...] = ()
    peer_repeat: int | None = None
    peer_python: str = field(default_factory=lambda: sys.executable)
    peer_options: PeerOptions = field(default_factory=PeerOptions)
    run_mipslam: bool = True

    def __post_init__(self):
        if not self.run_mipslam and not self.peers:
            raise ConfigError("--peers-only needs --peers (e.g. --peers open3d)")
        if self.peer_repeat is not None and self.peer_repeat < 1:
            raise ConfigError(f"--peer-repeat {self.peer_repeat}: must be >= 1")
        if self.peers:
            check_peers_available(self.peers, self.peer_options, self.peer_python)
        if self.repeat < 1:
            raise ConfigError(f"--repeat {self.repeat}: must be >= 1")
        if self.threads < 1:
            raise ConfigError(f"--threads {self.threads}: must be >= 1")
        if self.max_frames is not None and self.max_frames < 1:
            raise ConfigError(f"--max-frames {self.max_frames}: must be >= 1")
        if self.timeout_s <= 0:
            raise ConfigError(f"--timeout {self.timeout_s}: must be positive (seconds)")
        keys = [s.key for s in self.sweeps]
        twice = sorted({k for k in keys if keys.count(k) > 1})
        if twice:
            raise ConfigError(f"--sweep {twice[0]}: key swept twice; give all its values in one --sweep")

    def bench_overrides(self) -> tuple[str, ...]:
        """The bench's own settings, before ``--set``: seed, threads, frame limit."""
        out = [f"run.seed={self.seed}", f"run.threads={self.threads}"]
        if self.max_frames is not None:
            out.append(f"dataset.max_frames={self.max_frames}")
        return tuple(out)


@dataclass(frozen=True)
class Setting:
    """One point of the bench: a preset (None = the config as it is) and one value per sweep key."""

    index: int
    preset: str | None
    assignments: tuple[str, ...]  # sweep overrides, e.g. ("render.eaa_max_nodes=2",)
    overrides: tuple[str, ...]  # every override of the job's command line, in order
    threads: int  # run.threads of the resolved config
    seed: int  # run.seed of the resolved config
    render_mode: str  # render.mode of the resolved config (the mode the evaluation renders)
    render_backend: str  # render.backend of the resolved config (auto | torch | cpu)
    peer: str | None = None  # a peer system (mipslam.bench.peers.PEERS) instead of mipslam
    repeats: int | None = None  # runs of this setting (None: the bench's --repeat)

    @property
    def system(self) -> str:
        return self.peer or "mipslam"

    @property
    def label(self) -> str:
        parts = [self.peer or self.preset or "config", *self.assignments]
        return " ".join(parts)

    @property
    def slug(self) -> str:
        return f"s{self.index:02d}-" + re.sub(r"[^A-Za-z0-9_.=-]+", "_", "-".join(
            [self.peer or self.preset or "config", *(a.split(".", 1)[-1] for a in self.assignments)]))[:80]


@dataclass(frozen=True)
class Job:
    """One run of one setting: its ``mipslam run`` command line, run folder, log folder and time limit."""

    setting: Setting
    repeat: int
    run_dir: Path
    log_dir: Path
    run_command: tuple[str, ...]
    timeout_s: float
    peer_job: dict | None = field(default=None, compare=False)  # a peer's job description (worker JOB.json)

    @property
    def name(self) -> str:
        return f"{self.setting.slug}-r{self.repeat}"


def plan_settings(spec: BenchSpec) -> list[Setting]:
    """Presets x sweep values (cartesian product, in the order given), each config resolved and validated;
    then every peer x the values of the ``dataset.*`` sweeps."""
    value_lists = [s.assignments() for s in spec.sweeps]
    settings = []
    for combo in product(spec.presets if spec.run_mipslam else (), *value_lists):
        preset, assignments = combo[0], tuple(combo[1:])
        overrides = (*spec.target.base_overrides, *spec.bench_overrides(), *spec.overrides, *assignments)
        label = " ".join([preset or "config", *assignments])
        try:
            config = load_config(spec.target.config_path, preset=preset, overrides=list(overrides))
        except ConfigError as exc:
            raise ConfigError(f"bench setting '{label}': {exc}") from None
        settings.append(Setting(len(settings), preset, assignments, overrides, config.run.threads, config.run.seed,
                                config.render.mode, config.render.backend))
    dataset_lists = [s.assignments() for s in spec.sweeps if s.key.startswith("dataset.")]
    for peer in spec.peers:
        repeats = spec.peer_repeat or default_peer_repeats(peer)
        for assignments in product(*dataset_lists):
            overrides = (*spec.target.base_overrides, *spec.bench_overrides(), *spec.overrides, *assignments)
            label = " ".join([peer, *assignments])
            try:
                config = load_config(spec.target.config_path, overrides=list(overrides))
            except ConfigError as exc:
                raise ConfigError(f"bench setting '{label}': {exc}") from None
            settings.append(Setting(len(settings), None, tuple(assignments), overrides, config.run.threads,
                                    config.run.seed, "-", "-", peer=peer, repeats=repeats))
    return settings


def plan_jobs(spec: BenchSpec, settings: list[Setting] | None = None) -> list[Job]:
    """Every (setting, repeat) as a :class:`Job`, repeat-major; run folders under ``OUT/runs/``."""
    settings = plan_settings(spec) if settings is None else settings
    out = Path(spec.out_dir).resolve()
    jobs = []
    most = max([spec.repeat if s.repeats is None else s.repeats for s in settings], default=0)
    for repeat in range(most):
        for setting in settings:
            if repeat >= (spec.repeat if setting.repeats is None else setting.repeats):
                continue
            name = f"{setting.slug}-r{repeat}"
            run_dir = out / "runs" / name
            if setting.peer is not None:
                peer_job = {"peer": setting.peer, "config": str(spec.target.config_path), "preset": None,
                            "overrides": list(setting.overrides), "out": str(run_dir),
                            "options": spec.peer_options.to_dict()}
                command = (spec.peer_python, "-m", "mipslam.bench.peers.worker", str(run_dir / PEER_JOB_FILE))
                jobs.append(Job(setting, repeat, run_dir, out / "logs", command, spec.timeout_s, peer_job))
                continue
            run_command = [spec.python, "-m", "mipslam.cli", "-q", "run", str(spec.target.config_path)]
            if setting.preset:
                run_command += ["--preset", setting.preset]
            for item in setting.overrides:
                run_command += ["--set", item]
            run_command += ["--out", str(run_dir), "--no-eval"]
            jobs.append(Job(setting, repeat, run_dir, out / "logs", tuple(run_command), spec.timeout_s))
    return jobs


def default_out_dir(target: Target) -> Path:
    return Path("runs") / f"bench-{target.name}-{time.strftime('%Y%m%d-%H%M%S')}"


def check_out_dir(out_dir: Path) -> None:
    """A bench writes into a fresh folder (or an empty one): results of two benches never mix."""
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise MipslamError(f"{out_dir}: output folder exists and is not empty; choose another --out or remove it")
