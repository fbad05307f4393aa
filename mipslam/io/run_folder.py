"""One run's output folder and the atomic file writes every output goes through.

Layout (docs/design.md, "Outputs of a run")::

    RUN/config.yaml      resolved config
    RUN/traj_est.txt     estimated trajectory, TUM format
    RUN/traj_gt.txt      ground truth resampled to the estimated stamps, TUM format
    RUN/keyframes.txt    keyframe list
    RUN/map.ply          the map in the standard 3DGS PLY layout
    RUN/checkpoints/     atomic checkpoints (mipslam.checkpoint)
    RUN/metrics.json     evaluation
    RUN/timings.json     per stage and per frame timings
    RUN/loops.json       accepted loop closures
    RUN/run.json         what the evaluation needs to know about the run (sequence, intrinsics)
    RUN/frames.json      per-frame records
    RUN/report/          plots
    RUN/refined/         ``mipslam refine``'s map, poses, progress, evaluation and checkpoints (:class:`RefinedFolder`)

A new run goes only into a folder that does not exist or is empty (:func:`prepare_new_run_folder`):
a folder holding a run is continued (``--resume``) or, when asked (``--overwrite``), emptied of the
entries above and nothing else; a folder holding anything else is never touched.

Atomic write protocol (used for every file above): the bytes go to a temporary file in the
*same* folder (so the rename never crosses a file system), the file is flushed and fsync'ed,
``os.replace`` puts it in place, and the folder is fsync'ed so the rename itself is durable.
A crash at any moment leaves either the old complete file or the new complete file under the
final name, never a partial one; a failed write removes its temporary file.
"""
from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Iterator

from mipslam.errors import MipslamError

logger = logging.getLogger(__name__)

TEMP_SUFFIX = ".tmp"


def fsync_directory(folder: str | Path) -> None:
    """Make a rename inside ``folder`` durable (no-op where the OS cannot open folders)."""
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    try:
        fd = os.open(str(folder), flags)
    except OSError as exc:  # e.g. Windows cannot open a directory; the rename is still atomic
        logger.debug("cannot open %s to fsync it: %s", folder, exc)
        return
    try:
        os.fsync(fd)
    except OSError as exc:  # some file systems (network, tmpfs variants) refuse fsync on folders
        logger.debug("fsync of folder %s failed: %s", folder, exc)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_write(path: str | Path, *, error_type: type[MipslamError] = MipslamError) -> Iterator[BinaryIO]:
    """Open a temporary binary file next to ``path``; on clean exit it atomically becomes ``path``.

    If the body raises (including KeyboardInterrupt), the temporary file is removed and
    ``path`` is untouched. An ``OSError`` (disk full, permission denied) is re-raised as
    ``error_type`` with a message naming ``path``.
    """
    path = Path(path)
    folder = path.parent
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TEMP_SUFFIX, dir=folder)
    except OSError as exc:
        raise error_type(
            f"{path}: cannot create a file in {folder} ({exc.strerror or exc}); "
            "check that the folder exists and is writable"
        ) from exc
    tmp_path = Path(tmp_name)
    completed = False
    try:
        with os.fdopen(fd, "wb") as handle:
            # mkstemp creates 0600; give the file the mode the old one had (or a normal 0644).
            try:
                mode = path.stat().st_mode & 0o777
            except FileNotFoundError:
                mode = 0o644
            if hasattr(os, "fchmod"):
                os.fchmod(handle.fileno(), mode)
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_path, path)
        completed = True
        fsync_directory(folder)
    except OSError as exc:
        raise error_type(
            f"{path}: write failed ({exc.strerror or exc}); the previous version (if any) is unchanged. "
            "Free disk space or choose another output folder"
        ) from exc
    finally:
        if not completed:
            with contextlib.suppress(FileNotFoundError):
                tmp_path.unlink()


def write_bytes_atomic(path: str | Path, data: bytes, *, error_type: type[MipslamError] = MipslamError) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring). Returns ``path``."""
    with atomic_write(path, error_type=error_type) as handle:
        handle.write(data)
    return Path(path)


def write_text_atomic(path: str | Path, text: str, *, error_type: type[MipslamError] = MipslamError) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically. Returns ``path``."""
    return write_bytes_atomic(path, text.encode("utf-8"), error_type=error_type)


def _json_default(value: Any) -> Any:
    """Plain values for numpy/torch scalars and arrays, paths, sets (anything else is an error)."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (set, frozenset)):
        return sorted(value)
    if hasattr(value, "tolist"):  # numpy arrays/scalars, torch tensors
        return value.tolist()
    raise TypeError(f"object of type {type(value).__name__} is not JSON serialisable")


def _first_non_finite(obj: Any, where: str = "") -> str | None:
    """Dotted key of the first NaN/inf float inside ``obj`` (None when all finite)."""
    if isinstance(obj, float):
        return None if math.isfinite(obj) else (where or "<root>")
    if isinstance(obj, dict):
        for key, value in obj.items():
            found = _first_non_finite(value, f"{where}.{key}" if where else str(key))
            if found is not None:
                return found
    if isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            found = _first_non_finite(value, f"{where}[{i}]")
            if found is not None:
                return found
    return None


def write_json_atomic(path: str | Path, obj: Any, *, indent: int | None = 2,
                      error_type: type[MipslamError] = MipslamError) -> Path:
    """Write ``obj`` as strict JSON (no NaN/Infinity, which JSON does not have) atomically.

    numpy/torch values are converted with ``.tolist()``. A non-finite float is refused with an
    error naming its key, so callers decide explicitly (e.g. write ``None``) instead of producing
    a file that strict JSON readers reject.
    """
    try:
        text = json.dumps(obj, indent=indent, default=_json_default, allow_nan=False)
    except ValueError as exc:
        plain = json.loads(json.dumps(obj, default=_json_default))  # NaN survives this round trip
        key = _first_non_finite(plain)
        raise error_type(f"{path}: value at '{key}' is not finite; JSON cannot hold NaN/inf (write null instead)") from exc
    except TypeError as exc:
        raise error_type(f"{path}: cannot encode as JSON ({exc})") from exc
    return write_text_atomic(path, text + "\n", error_type=error_type)


class RunFolder:
    """Paths of one run's outputs (see the module docstring); :meth:`create` makes and checks them."""

    CHECKPOINTS = "checkpoints"
    REPORT = "report"
    REFINED = "refined"

    def __init__(self, path: str | Path):
        self.root = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.root)!r})"

    # --------------------------------------------------------------------------- paths
    @property
    def config_yaml(self) -> Path:
        return self.root / "config.yaml"

    @property
    def traj_est(self) -> Path:
        return self.root / "traj_est.txt"

    @property
    def traj_gt(self) -> Path:
        return self.root / "traj_gt.txt"

    @property
    def keyframes(self) -> Path:
        return self.root / "keyframes.txt"

    @property
    def map_ply(self) -> Path:
        return self.root / "map.ply"

    @property
    def checkpoints(self) -> Path:
        return self.root / self.CHECKPOINTS

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def timings(self) -> Path:
        return self.root / "timings.json"

    @property
    def loops(self) -> Path:
        return self.root / "loops.json"

    @property
    def report(self) -> Path:
        return self.root / self.REPORT

    @property
    def refined(self) -> "RefinedFolder":
        return RefinedFolder(self.root / self.REFINED)

    # --------------------------------------------------------------------------- creation
    def create(self) -> "RunFolder":
        """Create the folder, ``checkpoints/`` and ``report/``; check that files can be written.

        Raises MipslamError naming the folder when it cannot be created or written (read-only
        location, a file in the way, permission denied). Existing outputs are left alone.
        """
        if self.root.exists() and not self.root.is_dir():
            raise MipslamError(f"{self.root}: run folder path exists and is not a folder; choose another output path")
        for folder in (self.root, self.checkpoints, self.report):
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise MipslamError(
                    f"{folder}: cannot create the run folder ({exc.strerror or exc}); choose a writable output path"
                ) from exc
        self.check_writable()
        return self

    def check_writable(self) -> None:
        """Write and delete a probe file in the run folder; MipslamError if that fails."""
        try:
            fd, probe = tempfile.mkstemp(prefix=".write_probe.", dir=self.root)
        except OSError as exc:
            raise MipslamError(
                f"{self.root}: run folder is not writable ({exc.strerror or exc}); "
                "fix its permissions or choose another output path"
            ) from exc
        os.close(fd)
        os.unlink(probe)

    # --------------------------------------------------------------------------- what the folder holds
    def inspect(self) -> "RunFolderContents":
        """What the folder holds: nothing, the remains of a run that never checkpointed, a run, or other files."""
        if not self.root.exists():
            return RunFolderContents(self.root, exists=False)
        if not self.root.is_dir():
            return RunFolderContents(self.root, exists=True, is_folder=False)
        entries = sorted(self.root.iterdir())
        # Every run makes checkpoints/ first: without it the files here (a config.yaml, a map.ply) are someone else's.
        is_run = self.checkpoints.is_dir() and not self.checkpoints.is_symlink()
        foreign = tuple(p.name for p in entries
                        if not (_is_temporary(p.name) or (is_run and _written_by_a_run(p))))
        checkpoints = tuple(p for p in (self.checkpoints.iterdir() if self.checkpoints.is_dir() else ())
                            if _CHECKPOINT_FILE.match(p.name) and p.is_file())
        outputs = tuple(p.name for p in entries if p.name in RUN_OUTPUTS)
        return RunFolderContents(self.root, exists=True, is_folder=True, entries=tuple(p.name for p in entries),
                                 foreign=foreign, checkpoints=tuple(sorted(checkpoints)), outputs=outputs)

    def remove_run_entries(self) -> None:
        """Delete the entries a run writes (never anything else); the folder itself stays.

        Checkpoints go first, so an interrupted removal never leaves a resumable state beside
        outputs of another session. MipslamError naming the entry when one cannot be removed.
        """
        # a refinement first: without the run it refined it means nothing
        order = [self.root / self.REFINED, self.checkpoints, *(self.root / name for name in sorted(RUN_OUTPUTS)),
                 self.report, self.config_yaml]
        order += [p for p in self.root.iterdir() if _is_temporary(p.name)] if self.root.is_dir() else []
        for path in order:
            try:
                if path.is_dir() and not path.is_symlink():
                    shutil.rmtree(path)
                elif path.exists() or path.is_symlink():
                    path.unlink()
            except OSError as exc:
                raise MipslamError(f"{path}: cannot remove it ({exc.strerror or exc}); remove it by hand or choose "
                                   "another --out") from exc

    def remove_if_unstarted(self, *, remove_root: bool) -> bool:
        """After a run failed before its first checkpoint: delete what it created (``config.yaml``, the empty
        ``checkpoints/`` and ``report/``, temporaries) and, with ``remove_root``, the folder once empty.

        Anything else in the folder stays (then so does the folder). Returns True if the folder is gone.
        """
        if not self.root.is_dir() or self.inspect().checkpoints:
            return False
        for path in [self.config_yaml, *(p for p in self.root.iterdir() if _is_temporary(p.name))]:
            with contextlib.suppress(OSError):
                path.unlink()
        for folder in (self.checkpoints, self.report, *([self.root] if remove_root else [])):
            with contextlib.suppress(OSError):  # not empty (or not there): it stays
                folder.rmdir()
        return not self.root.exists()

    def remove_stale_temporaries(self) -> list[Path]:
        """Delete temporary files a killed process left behind (``.NAME.*.tmp``); returns them."""
        removed = []
        for folder in (self.root, self.checkpoints, self.report):
            if not folder.is_dir():
                continue
            for tmp in folder.glob(f".*{TEMP_SUFFIX}"):
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
                    removed.append(tmp)
        if removed:
            logger.info("removed %d temporary file(s) left by an interrupted run in %s", len(removed), self.root)
        return removed


# Everything a run writes at its top level besides config.yaml, checkpoints/ and report/.
RUN_OUTPUTS = frozenset({"traj_est.txt", "traj_gt.txt", "keyframes.txt", "map.ply", "metrics.json", "timings.json",
                         "loops.json", "run.json", "frames.json", "bench_eval.json"})
RUN_ENTRIES = RUN_OUTPUTS | {"config.yaml", RunFolder.CHECKPOINTS, RunFolder.REPORT}
_CHECKPOINT_FILE = re.compile(r"^checkpoint-\d{6,}\.ckpt$")  # mipslam.checkpoint.CHECKPOINT_PATTERN
_REPORT_SUFFIXES = (".png", ".html", ".svg", ".json", ".csv", ".txt")


def _is_temporary(name: str) -> bool:
    """A temporary of an atomic write or a write probe (``.NAME.XXXX.tmp``, ``.write_probe.XXXX``)."""
    return name.startswith(".") and (name.endswith(TEMP_SUFFIX) or name.startswith(".write_probe."))


def _written_by_a_run(path: Path) -> bool:
    """Whether ``path`` (an entry of a run folder) is something a run writes: a known output, a temporary,
    or one of its two folders holding only what a run puts there (checkpoints; plots and the report page)."""
    name = path.name
    if _is_temporary(name):
        return True
    if name == RunFolder.REFINED and not path.is_symlink():
        return path.is_dir() and not RefinedFolder(path).foreign()
    if name not in RUN_ENTRIES or path.is_symlink():
        return False
    if name == RunFolder.CHECKPOINTS:
        return path.is_dir() and all(p.is_file() and (_CHECKPOINT_FILE.match(p.name) or _is_temporary(p.name))
                                     for p in path.iterdir())
    if name == RunFolder.REPORT:
        return path.is_dir() and all(p.is_file() and (p.suffix.lower() in _REPORT_SUFFIXES or _is_temporary(p.name))
                                     for p in path.iterdir())
    return path.is_file()


@dataclass(frozen=True)
class RunFolderContents:
    """What a would-be run folder holds (:meth:`RunFolder.inspect`)."""

    root: Path
    exists: bool
    is_folder: bool = True
    entries: tuple[str, ...] = ()
    foreign: tuple[str, ...] = ()  # entries a run does not write
    checkpoints: tuple[Path, ...] = ()  # checkpoint files, oldest first
    outputs: tuple[str, ...] = ()  # final outputs present (RUN_OUTPUTS)

    @property
    def empty(self) -> bool:
        return not self.entries

    @property
    def holds_run(self) -> bool:
        """A run that got somewhere: a checkpoint or an output (not just a config.yaml and empty folders)."""
        return bool(self.checkpoints or self.outputs)

    def describe_foreign(self, limit: int = 3) -> str:
        shown = ", ".join(self.foreign[:limit])
        return shown + (f" and {len(self.foreign) - limit} more" if len(self.foreign) > limit else "")


def prepare_new_run_folder(path: str | Path, *, overwrite: bool = False) -> bool:
    """Check that a new run may write into ``path``; with ``overwrite``, delete the earlier run there first.

    A new run starts in a folder that does not exist, is empty, or holds only the remains of a run that
    stopped before its first checkpoint. A folder holding a run is refused (MipslamError saying how to
    continue it, replace it, or go elsewhere) unless ``overwrite``; then only the entries a run writes are
    deleted, and a folder holding anything else is refused even with ``overwrite``. Returns whether the
    folder exists now (False: the run will create it, and may remove it if it fails before it starts).
    """
    folder = RunFolder(path)
    contents = folder.inspect()
    if not contents.exists:
        return False
    if not contents.is_folder:
        raise MipslamError(f"{folder.root}: exists and is not a folder; choose another --out")
    if contents.empty:
        return True
    if contents.foreign and contents.holds_run:
        raise MipslamError(f"{folder.root}: holds a mipslam run and files a run did not make "
                           f"({contents.describe_foreign()}); continue the run with --resume {folder.root}, or choose "
                           "another --out (--overwrite deletes only a run's own files: move the others away first)")
    if contents.foreign:
        raise MipslamError(f"{folder.root}: is not empty and holds no mipslam run ({contents.describe_foreign()}); "
                           "a run goes into a new or empty folder: choose another --out")
    if contents.holds_run and not overwrite:
        state = f"{len(contents.checkpoints)} checkpoint(s)" if contents.checkpoints else "no checkpoint"
        finished = "a finished run" if folder.traj_est.is_file() else "a partial run"
        raise MipslamError(f"{folder.root}: holds {finished} ({state}); continue it with --resume {folder.root}, "
                           f"replace it with --overwrite, or choose another --out")
    folder.remove_run_entries()
    if contents.holds_run:
        logger.warning("--overwrite: removed the earlier run in %s", folder.root)
    return True


class RefinedFolder:
    """``RUN/refined/``: what ``mipslam refine`` writes beside a run's own files (:mod:`mipslam.refine_run`)::

        refined/map.ply        the refined map (3DGS PLY layout)
        refined/traj_est.txt   every frame's pose (the run's own unless keyframe poses were refined)
        refined/keyframes.txt  the keyframes' poses
        refined/progress.json  one record per evaluation during the refinement
        refined/metrics.json   the refined map evaluated with the run's own protocol
        refined/checkpoints/   resume state (mipslam.checkpoint)
    """

    FILES = ("map.ply", "traj_est.txt", "keyframes.txt", "progress.json", "metrics.json")
    CHECKPOINTS = "checkpoints"

    def __init__(self, path: str | Path):
        self.root = Path(path)

    def __repr__(self) -> str:
        return f"RefinedFolder({str(self.root)!r})"

    @property
    def map_ply(self) -> Path:
        return self.root / "map.ply"

    @property
    def traj_est(self) -> Path:
        return self.root / "traj_est.txt"

    @property
    def keyframes(self) -> Path:
        return self.root / "keyframes.txt"

    @property
    def progress(self) -> Path:
        return self.root / "progress.json"

    @property
    def metrics(self) -> Path:
        return self.root / "metrics.json"

    @property
    def checkpoints(self) -> Path:
        return self.root / self.CHECKPOINTS

    def create(self) -> "RefinedFolder":
        """Create the folder and its ``checkpoints/``; MipslamError naming the folder when that fails."""
        if self.root.exists() and not self.root.is_dir():
            raise MipslamError(f"{self.root}: exists and is not a folder; move it away (mipslam refine writes its "
                               "outputs there)")
        for folder in (self.root, self.checkpoints):
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise MipslamError(f"{folder}: cannot create it ({exc.strerror or exc}); fix the run folder's "
                                   "permissions") from exc
        return self

    def foreign(self) -> tuple[str, ...]:
        """Entries (relative to the folder) that ``mipslam refine`` does not write."""
        if not self.root.is_dir():
            return ()
        found = []
        for path in sorted(self.root.iterdir()):
            if _is_temporary(path.name) or (path.name in self.FILES and path.is_file() and not path.is_symlink()):
                continue
            if path.name == self.CHECKPOINTS and path.is_dir() and not path.is_symlink():
                found += [f"{self.CHECKPOINTS}/{p.name}" for p in sorted(path.iterdir())
                          if not (p.is_file() and (_CHECKPOINT_FILE.match(p.name) or _is_temporary(p.name)))]
                continue
            found.append(path.name)
        return tuple(found)

    def remove(self) -> None:
        """Delete the folder, which must hold only what ``mipslam refine`` writes (MipslamError naming the other
        entries otherwise, and nothing is deleted). Checkpoints go first: an interrupted removal never leaves a
        resumable state beside outputs of another refinement."""
        if not self.root.exists():
            return
        foreign = self.foreign()
        if foreign or not self.root.is_dir() or self.root.is_symlink():
            shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            raise MipslamError(f"{self.root}: holds files mipslam refine did not write ({shown or 'not a folder'}); "
                               "move them away first")
        try:
            if self.checkpoints.is_dir():
                shutil.rmtree(self.checkpoints)
            shutil.rmtree(self.root)
        except OSError as exc:
            raise MipslamError(f"{self.root}: cannot remove it ({exc.strerror or exc}); remove it by hand") from exc

    def remove_stale_temporaries(self) -> list[Path]:
        """Delete temporary files a killed ``mipslam refine`` left behind; returns them."""
        removed = []
        for folder in (self.root, self.checkpoints):
            if folder.is_dir():
                for tmp in folder.glob(f".*{TEMP_SUFFIX}"):
                    with contextlib.suppress(FileNotFoundError):
                        tmp.unlink()
                        removed.append(tmp)
        return removed
