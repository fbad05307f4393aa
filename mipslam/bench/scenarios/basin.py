"""Basin of convergence, measured: ATE and lost frames against the frame stride, mipslam beside its peers.

A sweep of ``mipslam bench`` per sequence: ``--presets PRESETS --sweep dataset.stride=1,2,4,8 --peers PEERS``,
so every stride is a setting of mipslam and of every peer. Larger strides mean larger motion between
consecutive frames: where a system's ATE jumps or its lost frames climb, the motion has left its basin
of convergence. Each sequence gets OUT/bench_<sequence>/ with its bench.md (the sweep table: ATE cm and lost
frames per stride), bench_sweep.png (ATE and lost frames against the stride, a line per system), bench.png and
bench.json (machine, every run); OUT/bench.md gathers the tables.

Sequences: TUM fr1_rpy (``basin.tum``, default ../shared/data/tum_fr1_rpy_300; skipped with a message when
absent) and a data_synth loop generated into OUT/synth_loop (``basin.synth_frames`` frames at
``basin.synth_size``).

    mipslam bench --scenario basin --out bench_out/basin --set basin.vocab=orbvoc.txt
    mipslam bench --scenario basin --out bench_out/basin_small --set basin.max_frames=60 --set basin.peers=open3d
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from mipslam.bench.record import write_benchmark
from mipslam.bench.scenarios import RECORD_NAME, ScenarioResult
from mipslam.bench.scenarios.checkout import SHARED_DATA, optional_path, parameters

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Options:
    presets: str = "fast"  # mipslam presets, comma-separated
    peers: str = "open3d,orbslam3"  # peers, comma-separated ("" for none)
    vocab: str = ""  # ORB vocabulary for orbslam3 (mipslam bench --train-vocab)
    strides: tuple[int, ...] = (1, 2, 4, 8)  # dataset.stride values
    max_frames: int = 0  # frames per run after the stride (0: all)
    repeat: int = 1  # runs per mipslam setting
    threads: int = 2  # run.threads of every run
    tum: str = str(SHARED_DATA / "tum_fr1_rpy_300")  # "" to leave the TUM sequence out
    synth_frames: int = 120
    synth_size: str = "320x240"  # WIDTHxHEIGHT of the data_synth loop
    config_overrides: tuple[str, ...] = ()  # config KEY=VALUE for every mipslam run


SMOKE = dict(presets="fast", peers="", strides=(2,), max_frames=3, tum="", synth_frames=6, synth_size="40x30",
             config_overrides=("mapping.first_frame_iterations=10", "mapping.iterations=3", "tracking.iterations=3",
                               "loop.enabled=false"))


def run(options: Options, out_dir: Path) -> ScenarioResult:
    import data_synth
    from mipslam.bench import BenchSpec, LocalExecutor, parse_presets, parse_sweep, resolve_target, run_bench
    from mipslam.bench.peers import parse_peer_sets, parse_peers

    width, height = (int(v) for v in options.synth_size.lower().split("x"))
    synth = out_dir / "synth_loop"
    data_synth.generate(synth, layout="replica", trajectory="loop", width=width, height=height,
                        frames=options.synth_frames, seed=0, supersample=2)
    sequences = [synth]
    notes = []
    tum = optional_path(options.tum)
    if tum is not None and tum.is_dir():
        sequences.insert(0, tum)
    elif tum is not None:
        notes.append(f"{tum} not found: TUM part skipped")
        log.warning("%s", notes[-1])
    peer_options = parse_peer_sets([f"orbslam3.vocabulary={Path(options.vocab).expanduser().resolve()}"]
                                   if options.vocab else [])
    sections, results, plots = [], {}, []
    for sequence in sequences:
        bench_dir = out_dir / f"bench_{sequence.name}"
        spec = BenchSpec(target=resolve_target(sequence), out_dir=bench_dir, presets=parse_presets(options.presets),
                         sweeps=(parse_sweep("dataset.stride=" + ",".join(str(s) for s in options.strides)),),
                         overrides=options.config_overrides, repeat=options.repeat, threads=options.threads,
                         max_frames=options.max_frames or None, peers=parse_peers(options.peers or None),
                         peer_options=peer_options)
        outcome = run_bench(spec, LocalExecutor())
        sections.append(f"## {sequence.name}\n\n" + outcome.files.markdown.read_text(encoding="utf-8"))
        results[sequence.name] = {"bench_folder": str(bench_dir), "jobs": len(outcome.rows), "failed": outcome.failed,
                                  "settings": [s.to_dict() for s in outcome.settings]}
        plots += [outcome.files.plot, *outcome.files.sweep_plots]
    markdown = "\n\n".join([*notes, *sections])
    files = write_benchmark(out_dir, RECORD_NAME, parameters(options), results, threads=options.threads,
                            markdown=markdown)
    return ScenarioResult(files, "\n".join(f"{name}: {r['jobs']} jobs, {r['failed']} failed, in {r['bench_folder']}"
                                           for name, r in results.items()),
                          plots=tuple(p for p in plots if p.is_file()))
