"""Running bench jobs: one ``mipslam run`` child process per job, its evaluation, and the executors.

:func:`execute_job` never raises for a job's own failure: a non-zero exit, a timeout, a missing
output or an unreadable evaluation becomes a :class:`JobResult` with ``error`` set (what the job
measured before it failed is kept). Executors map jobs to results in plan order:

* :class:`LocalExecutor` runs them one after the other (the default: on a small machine two SLAM
  runs at once would time each other), or ``parallel`` at once (recorded in the results);
* :class:`RayExecutor` runs each job as a Ray task (``ray`` imported only here), each task asking for
  the job's thread count as CPUs; every task writes its own run folder on the node that runs it.
"""
from __future__ import annotations

import json
import logging
import math
import os
import platform
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

from mipslam.optional import import_optional
from mipslam.bench.spec import EVAL_FILE, PEER_JOB_FILE, Job
from mipslam.errors import MipslamError

__all__ = ["Executor", "JobResult", "LocalExecutor", "RayExecutor", "execute_job", "read_job_outputs", "run_jobs"]

log = logging.getLogger(__name__)

ERROR_TEXT_LIMIT = 600  # characters of a failed process's stderr kept in the row


@dataclass(frozen=True)
class JobResult:
    """One row of the bench: a job's measurements, or its error (``error`` set, values that exist kept).

    fps: frames / seconds of the SLAM stages (timings.json; excludes start-up and writing outputs).
    stage_ms_per_frame: stage -> total seconds / frames * 1000 (sums to 1000 / fps).
    wall_s: wall time of the ``mipslam run`` process (start-up and outputs included).
    ate_rmse_cm: ATE RMSE after the run's alignment (se3 by default). psnr_db: novel-view PSNR (MonoGS's every
    5th frame that is not a keyframe, native resolution, the run's footprint mode); psnr_train_db: the same for the
    training views (the keyframes). device, torch_threads: from run.json.
    system: "mipslam" or the peer's name. rpe_trans_cm / rpe_rot_deg: RPE RMSE over consecutive matched
    frames. lost_frames: frames without a pose (peers) or flagged as tracking failures (mipslam, which keeps
    a motion-model pose for them). For a peer, fps counts the peer's own per-frame processing (reading
    images and ORB-SLAM3's pacing excluded).
    """

    setting_index: int
    setting: str
    preset: str | None
    assignments: tuple[str, ...]
    repeat: int
    seed: int
    threads: int
    run_dir: str
    host: str
    error: str | None = None
    returncode: int | None = None
    wall_s: float | None = None
    eval_wall_s: float | None = None
    frames: int | None = None
    fps: float | None = None
    stage_ms_per_frame: dict[str, float] = field(default_factory=dict)
    ate_rmse_cm: float | None = None
    psnr_db: float | None = None
    psnr_train_db: float | None = None
    gaussians: int | None = None
    keyframes: int | None = None
    device: str | None = None
    torch_threads: int | None = None
    render_backend: str | None = None
    system: str = "mipslam"
    rpe_trans_cm: float | None = None
    rpe_rot_deg: float | None = None
    lost_frames: int | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["assignments"] = list(self.assignments)
        out["ok"] = self.ok
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "JobResult":
        names = set(cls.__dataclass_fields__)
        values = {k: v for k, v in data.items() if k in names}
        values["assignments"] = tuple(values.get("assignments", ()))
        return cls(**values)


def _job_env(threads: int) -> dict[str, str]:
    """The job processes' environment: the caller's, with the OpenMP/MKL thread counts of the job."""
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = str(threads)
    env["MKL_NUM_THREADS"] = str(threads)
    return env


def _error_tail(text: str) -> str:
    """The last meaningful lines of a process's stderr (progress bars dropped), at most ERROR_TEXT_LIMIT chars."""
    lines = [line.strip() for line in text.replace("\r", "\n").splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith("mipslam:") or "error" in line.lower()] or lines
    tail = " | ".join(lines[-3:])
    return tail[-ERROR_TEXT_LIMIT:] if tail else "(no output on stderr)"


def _run_process(command: tuple[str, ...], timeout_s: float, env: dict[str, str], log_path: Path
                 ) -> tuple[int | None, float, str | None]:
    """Run ``command``; -> (exit code or None on timeout, wall seconds, error text or None). Output to log_path."""
    start = time.perf_counter()
    try:
        result = subprocess.run(list(command), capture_output=True, text=True, timeout=timeout_s, env=env, check=False)
    except subprocess.TimeoutExpired as exc:
        wall = time.perf_counter() - start
        _write_log(log_path, command, exc.stdout, exc.stderr, None)
        return None, wall, f"timed out after {timeout_s:g} s (killed)"
    except OSError as exc:
        return None, time.perf_counter() - start, f"cannot start {command[0]}: {exc}"
    wall = time.perf_counter() - start
    _write_log(log_path, command, result.stdout, result.stderr, result.returncode)
    if result.returncode != 0:
        return result.returncode, wall, f"exit code {result.returncode}: {_error_tail(result.stderr)}"
    return 0, wall, None


def _write_log(path: Path, command, stdout, stderr, returncode) -> None:
    def text(value) -> str:
        if value is None:
            return ""
        return value.decode(errors="replace") if isinstance(value, bytes) else value

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"$ {' '.join(command)}\n# exit code: {returncode}\n# stdout\n{text(stdout)}\n# stderr\n"
                        f"{text(stderr)}", encoding="utf-8")
    except OSError as exc:  # a log is a convenience; the row still carries the error
        log.warning("%s: cannot write the job log (%s)", path, exc)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MipslamError(f"{path} is missing") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise MipslamError(f"{path} is unreadable ({exc})") from None


def _finite(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def read_job_outputs(run_dir: Path) -> dict[str, Any]:
    """Measurements of a finished run folder from timings.json and run.json.

    Raises MipslamError naming the missing or unreadable file.
    """
    run_dir = Path(run_dir)
    timings = _read_json(run_dir / "timings.json")
    info = _read_json(run_dir / "run.json")
    frames = int(timings.get("frames") or 0)
    stage_ms = {stage: 1000.0 * float(values["total_s"]) / frames
                for stage, values in timings.get("stages", {}).items()} if frames else {}
    out: dict[str, Any] = {
        "frames": frames, "fps": _finite(timings.get("frames_per_second")), "stage_ms_per_frame": stage_ms,
        "gaussians": info.get("gaussians"), "keyframes": info.get("keyframes"), "device": info.get("device"),
        "torch_threads": info.get("torch_threads"),
        "backend_used": (info.get("render_backend") or {}).get("used"),
    }
    return out


def read_evaluation(metrics: dict, render_mode: str, where: str) -> dict[str, Any]:
    """ATE RMSE (cm) and the PSNR (dB) of the ``render_mode`` rows at scale 1 of a metrics dict (from ``where``):
    ``psnr_db`` of the novel views, ``psnr_train_db`` of the training views (an evaluation of one frame set gives
    its PSNR as ``psnr_db``).

    PSNR None: not finite (an exact render), not computed, or no such view set (a clip without novel views)."""
    ate = (metrics.get("trajectory") or {}).get("ate") or {}
    if _finite(ate.get("rmse")) is None:
        raise MipslamError(f"{where}: no ATE RMSE in the evaluation")
    rows = (metrics.get("render") or {}).get("rows") or []
    if not rows:
        unavailable = (metrics.get("render") or {}).get("unavailable", "no render rows")
        raise MipslamError(f"{where}: no PSNR in the evaluation ({unavailable})")

    def psnr_of(views: str | None) -> float | None:
        of_views = [r for r in rows if views is None or r.get("views") == views]
        row = next((r for r in of_views if r.get("mode") == render_mode and r.get("scale") == 1),
                   of_views[0] if of_views else None)
        return None if row is None else _finite(row.get("psnr"))

    split = any(r.get("views") in ("novel", "training") for r in rows)
    return {"ate_rmse_cm": 100.0 * float(ate["rmse"]), "psnr_db": psnr_of("novel" if split else None),
            "psnr_train_db": psnr_of("training") if split else None, **_rpe_and_lost(metrics)}


def _rpe_and_lost(metrics: dict) -> dict[str, Any]:
    """RPE RMSE (cm, degrees) and the tracking-failure count of a metrics dict (None where absent)."""
    trajectory = metrics.get("trajectory") or {}
    rpe_t = _finite((trajectory.get("rpe_translation") or {}).get("rmse"))
    rpe_r = _finite((trajectory.get("rpe_rotation") or {}).get("rmse"))
    lost = (metrics.get("tracking_failures") or metrics.get("lost_frames") or {}).get("count")
    return {"rpe_trans_cm": None if rpe_t is None else 100.0 * rpe_t, "rpe_rot_deg": rpe_r,
            "lost_frames": int(lost) if isinstance(lost, int) else None}


def evaluate_job_run(run_dir: Path, render_mode: str) -> dict[str, Any]:
    """Evaluate a finished run folder in this process (:func:`~mipslam.evaluation.run_eval.evaluate_run`):
    ATE of all frames, PSNR of the novel and the training views (``split``) at the native resolution in
    ``render_mode``, no LPIPS, no report. The metrics go to ``RUN/bench_eval.json``; returns ATE (cm) and the two
    PSNRs (dB)."""
    from mipslam.evaluation.render_eval import RenderEvalOptions
    from mipslam.evaluation.run_eval import evaluate_run
    from mipslam.io.run_folder import write_json_atomic

    options = RenderEvalOptions(frames="split", resolution="native", scales=(1.0,), modes=(render_mode,), lpips=False,
                                showcase=False)
    metrics = evaluate_run(run_dir, render_options=options, report=False)
    path = write_json_atomic(Path(run_dir) / EVAL_FILE, metrics)
    return read_evaluation(metrics, render_mode, str(path))


def resolved_render_backend(configured: str, device: str | None) -> str:
    """The renderer backend a run used: ``torch`` or ``cpu``, as ``auto`` resolves it on this machine.

    ``auto`` takes the compiled cpu backend for CPU tensors when it is built (it may still hand single
    calls it does not support to torch; those are not counted here).
    """
    if configured != "auto":
        return configured
    if device is not None and not device.startswith("cpu"):
        return "torch"
    from mipslam.render import available_backends

    return "cpu (auto)" if "cpu" in available_backends() else "torch (auto)"


def execute_peer_job(job: Job) -> JobResult:
    """Run one peer job: the peer worker in a child process, then mipslam's trajectory evaluation here.

    Never raises for the job's own failure: the row carries the error and whatever was measured."""
    from mipslam.bench.peers import evaluate_peer_run

    setting = job.setting
    base = dict(setting_index=setting.index, setting=setting.label, preset=None, assignments=setting.assignments,
                repeat=job.repeat, seed=setting.seed, threads=setting.threads, run_dir=str(job.run_dir),
                host=platform.node(), system=setting.system, device="cpu", render_backend="-")
    try:
        job.run_dir.mkdir(parents=True, exist_ok=True)
        (job.run_dir / PEER_JOB_FILE).write_text(json.dumps(job.peer_job, indent=2), encoding="utf-8")
    except OSError as exc:
        return JobResult(**base, error=f"cannot write {job.run_dir / PEER_JOB_FILE}: {exc}")
    code, wall, error = _run_process(job.run_command, job.timeout_s, _job_env(setting.threads),
                                     job.log_dir / f"{job.name}.run.log")
    measured: dict[str, Any] = {}
    eval_wall = None
    if error is None:
        start = time.perf_counter()
        try:
            info = _read_json(job.run_dir / "peer.json")
            measured = {"frames": info.get("frames"), "fps": _finite(info.get("frames_per_second")),
                        "lost_frames": info.get("lost_frames")}
            data = evaluate_peer_run(job.run_dir)
            measured.update({"ate_rmse_cm": 100.0 * float(data["trajectory"]["ate"]["rmse"]), **_rpe_and_lost(data)})
        except MipslamError as exc:
            error = f"evaluation failed: {exc}"
        except (OSError, KeyError, ValueError) as exc:
            error = f"evaluation failed: {type(exc).__name__}: {str(exc)[:ERROR_TEXT_LIMIT]}"
        eval_wall = time.perf_counter() - start
    return JobResult(**base, error=error, returncode=code, wall_s=wall, eval_wall_s=eval_wall, **measured)


def execute_job(job: Job) -> JobResult:
    """Run one job: ``mipslam run`` in a child process, then its evaluation here; read the measurements.
    Peer jobs go to :func:`execute_peer_job`.

    Never raises for the job's own failure: the row carries the error and whatever was measured."""
    if job.setting.peer is not None:
        return execute_peer_job(job)
    setting = job.setting
    base = dict(setting_index=setting.index, setting=setting.label, preset=setting.preset,
                assignments=setting.assignments, repeat=job.repeat, seed=setting.seed, threads=setting.threads,
                run_dir=str(job.run_dir), host=platform.node())
    code, wall, error = _run_process(job.run_command, job.timeout_s, _job_env(setting.threads),
                                     job.log_dir / f"{job.name}.run.log")
    measured: dict[str, Any] = {}
    if error is None:
        try:
            measured = read_job_outputs(job.run_dir)
        except MipslamError as exc:
            error = f"run finished but its outputs are incomplete: {exc}"
    eval_wall = None
    if error is None:
        start = time.perf_counter()
        try:
            measured.update(evaluate_job_run(job.run_dir, setting.render_mode))
        except MipslamError as exc:
            error = f"evaluation failed: {exc}"
        except (OSError, RuntimeError, ValueError) as exc:  # torch/numpy failures: a row, not a lost bench
            error = f"evaluation failed: {type(exc).__name__}: {str(exc)[:ERROR_TEXT_LIMIT]}"
        eval_wall = time.perf_counter() - start
    backend = measured.pop("backend_used", None)  # recorded by the run itself (run.json, render_backend.used)
    if backend is None and measured.get("device") is not None:
        try:
            backend = resolved_render_backend(setting.render_backend, measured.get("device"))
        except ImportError as exc:  # the renderer package itself cannot load here: say so instead of guessing
            backend = f"{setting.render_backend} (unresolved: {exc})"
    return JobResult(**base, error=error, returncode=code, wall_s=wall, eval_wall_s=eval_wall,
                     render_backend=backend, **measured)


# ----------------------------------------------------------------------------- executors

class Executor(Protocol):
    """Maps jobs to results (same order); ``describe()`` is recorded in bench.json."""

    def __call__(self, jobs: list[Job], on_result: Callable[[int, JobResult], None]) -> list[JobResult]: ...

    def describe(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class LocalExecutor:
    """Jobs as local processes, ``parallel`` at a time (1 = sequential, the honest default for timings)."""

    parallel: int = 1
    run: Callable[[Job], JobResult] = execute_job

    def __post_init__(self):
        if self.parallel < 1:
            raise MipslamError(f"--jobs {self.parallel}: must be >= 1")

    def describe(self) -> dict[str, Any]:
        note = ("one job at a time" if self.parallel == 1 else
                f"{self.parallel} jobs at once: they share the machine, so their timings are not those of a job alone")
        return {"executor": "local processes", "parallel_jobs": self.parallel, "note": note}

    def __call__(self, jobs: list[Job], on_result: Callable[[int, JobResult], None]) -> list[JobResult]:
        results: list[JobResult | None] = [None] * len(jobs)
        if self.parallel == 1 or len(jobs) <= 1:
            for i, job in enumerate(jobs):
                results[i] = self.run(job)
                on_result(i, results[i])
            return results  # type: ignore[return-value]
        with ThreadPoolExecutor(max_workers=self.parallel) as pool:
            futures = {pool.submit(self.run, job): i for i, job in enumerate(jobs)}
            for future in as_completed(futures):
                i = futures[future]
                results[i] = future.result()
                on_result(i, results[i])
        return results  # type: ignore[return-value]


def _import_ray():
    return import_optional("ray", package="Ray", needed_by="--ray",
                           install="install it with pip install 'mipslam[ray]' (or pip install 'ray>=2.9'), or run "
                                   "without --ray")


@dataclass(frozen=True)
class RayExecutor:
    """Jobs as Ray tasks. ``address``: None starts a local Ray instance; else ``ray.init(address=...)``
    (e.g. ``auto``, ``ray://head:10001``). Every node needs mipslam installed and the sequence and the
    output folder at the same paths (a shared file system), since each task writes its own run folder."""

    address: str | None = None
    num_cpus: int | None = None  # local instance only: CPUs it offers (default: all)

    def describe(self) -> dict[str, Any]:
        return {"executor": "ray", "address": self.address or "local instance",
                "note": "each job a Ray task asking for its thread count as CPUs; concurrent tasks share nodes"}

    def __call__(self, jobs: list[Job], on_result: Callable[[int, JobResult], None]) -> list[JobResult]:
        ray = _import_ray()
        started_here = not ray.is_initialized()
        if started_here:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if self.address:
                kwargs["address"] = self.address
            elif self.num_cpus is not None:
                kwargs["num_cpus"] = self.num_cpus
            try:
                ray.init(**kwargs)
            except (ConnectionError, RuntimeError, ValueError) as exc:
                raise MipslamError(f"--ray {self.address or ''}: cannot start or reach Ray ({exc})") from None
        try:
            remote = ray.remote(execute_job)
            refs = [remote.options(num_cpus=job.setting.threads, max_retries=0).remote(job) for job in jobs]
            index_of = {ref: i for i, ref in enumerate(refs)}
            results: list[JobResult | None] = [None] * len(jobs)
            pending = list(refs)
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                i = index_of[done[0]]
                try:
                    results[i] = ray.get(done[0])
                except ray.exceptions.RayError as exc:  # the task itself died (worker crash, node lost)
                    results[i] = _crashed(jobs[i], f"Ray task failed: {type(exc).__name__}: {str(exc)[:ERROR_TEXT_LIMIT]}")
                on_result(i, results[i])
            return results  # type: ignore[return-value]
        finally:
            if started_here:
                ray.shutdown()


def _crashed(job: Job, error: str) -> JobResult:
    s = job.setting
    return JobResult(setting_index=s.index, setting=s.label, preset=s.preset, assignments=s.assignments,
                     repeat=job.repeat, seed=s.seed, threads=s.threads, run_dir=str(job.run_dir), host="?", error=error,
                     system=s.system)


def run_jobs(jobs: list[Job], executor: Executor | None = None,
             on_result: Callable[[int, JobResult], None] | None = None) -> list[JobResult]:
    """Run ``jobs`` with ``executor`` (default: :class:`LocalExecutor`, sequential); results in plan order.

    on_result(i, result) is called as each job finishes (progress, incremental saving)."""
    executor = executor or LocalExecutor()
    return executor(jobs, on_result or (lambda i, r: None))
