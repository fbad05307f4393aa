"""Atomic checkpoints in a plain, pickle-free file format; safe loading; RNG capture.

A checkpoint is a state given as a flat ``dict[str, Tensor]`` plus JSON-able metadata, written
with the resolved config and a format version. Nothing in a checkpoint is ever unpickled: the
file is our own plain format (below), read with ``json.loads`` and ``torch.frombuffer``, so a
planted pickle payload is just bytes that fail the magic/checksum test.

File layout (all integers little endian)::

    MAGIC                  12 bytes  b"MIPSLAMCKPT\\n"
    header_length           8 bytes  uint64
    header               N bytes     UTF-8 JSON: format_version, byteorder (of the tensors), created_utc, config,
                                     metadata, tensors = [{name, dtype, shape, offset, nbytes}]
    payload                          the tensors' raw bytes, C order, at their offsets
    sha256                 32 bytes  SHA-256 of every byte before it

Writing (:func:`write_checkpoint`) goes through :func:`mipslam.io.run_folder.atomic_write`:
temporary file in the same folder, fsync of file and folder, rename. :func:`save_checkpoint`
numbers checkpoints ``checkpoint-000001.ckpt``, ``-000002``, ... and deletes the oldest only
after the new one is complete, keeping ``keep`` of them (``mipslam.run_control.KEEP_CHECKPOINTS``).
:func:`load_latest_checkpoint` verifies the checksum of the newest; a corrupt or truncated one
is reported with a warning and the previous good one is used.

Resume compatibility: :func:`config_differences` compares the saved and the current resolved
config key by key (paths compared as absolute paths); every key must match except those in
:data:`RESUME_FREE_KEYS` (settings that do not change the computation's result, such as how often
to checkpoint), whose changes are allowed and logged (:func:`free_config_differences`).
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import math
import random
import re
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch

from mipslam.config import Config, config_to_dict, with_absolute_paths
from mipslam.errors import CheckpointError
from mipslam.io.run_folder import atomic_write

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
MAGIC = b"MIPSLAMCKPT\n"
_LEN = struct.Struct("<Q")
_DIGEST_SIZE = 32
CHECKPOINT_PATTERN = re.compile(r"^checkpoint-(\d{6,})\.ckpt$")
MAX_HEADER_BYTES = 256 * 1024 * 1024

# Config keys that may differ between the run that wrote a checkpoint and the run resuming it:
# they change how often/where outputs are written or how fast, not what is computed.
# An entry names a key or a whole section (every key below it).
RESUME_FREE_KEYS: tuple[str, ...] = (
    "run.checkpoint_every",
    "run.threads",
    "run.evaluate_at_end",
    "run.device",
    "run.diagnostics",
    "dataset.max_frames",
    "eval",
)

_DTYPES: dict[str, torch.dtype] = {
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float32": torch.float32,
    "float64": torch.float64,
    "uint8": torch.uint8,
    "int8": torch.int8,
    "int16": torch.int16,
    "int32": torch.int32,
    "int64": torch.int64,
    "bool": torch.bool,
    "complex64": torch.complex64,
    "complex128": torch.complex128,
}
_DTYPE_NAMES = {dtype: name for name, dtype in _DTYPES.items()}


@dataclass(frozen=True)
class Checkpoint:
    """A checkpoint as read back (tensors on CPU unless a device was asked for)."""

    path: Path
    tensors: dict[str, torch.Tensor]
    metadata: dict[str, Any]
    config: dict[str, Any]
    format_version: int = FORMAT_VERSION
    created_utc: str = ""
    serial: int | None = field(default=None)


# ----------------------------------------------------------------------------- encoding


def _tensor_bytes(name: str, tensor: torch.Tensor) -> tuple[dict[str, Any], memoryview]:
    """The table entry of one tensor and a view of its raw bytes (C order, CPU).

    The view shares memory with ``tensor`` when it is already a contiguous CPU tensor (no copy: a
    checkpoint of a large map then needs no second copy of it in memory while it is written)."""
    if not isinstance(tensor, torch.Tensor):
        raise CheckpointError(f"checkpoint entry '{name}' is a {type(tensor).__name__}, not a tensor; "
                              "put plain values in the metadata instead")
    if tensor.dtype not in _DTYPE_NAMES:
        raise CheckpointError(f"checkpoint entry '{name}' has unsupported dtype {tensor.dtype}")
    if tensor.is_sparse or tensor.layout != torch.strided:
        raise CheckpointError(f"checkpoint entry '{name}' is not a dense tensor")
    flat = tensor.detach().to("cpu").contiguous().reshape(-1)
    data = memoryview(flat.view(torch.uint8).numpy()) if flat.numel() else memoryview(b"")
    entry = {"name": name, "dtype": _DTYPE_NAMES[tensor.dtype], "shape": list(tensor.shape), "nbytes": data.nbytes}
    return entry, data


def write_checkpoint(path: str | Path, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, Any],
                     config: Mapping[str, Any]) -> Path:
    """Write one checkpoint file atomically (temporary file, fsync, rename, fsync folder).

    tensors: flat mapping name -> tensor (any device; written from CPU copies)
    metadata: JSON-able values (frame index, keyframe ids, RNG scalars, ...)
    config: the resolved config as a plain dict (``mipslam.config.config_to_dict``)
    Raises CheckpointError (naming the file) when an entry cannot be encoded or the write fails.
    """
    path = Path(path)
    entries, blobs, offset = [], [], 0
    for name, tensor in tensors.items():
        entry, data = _tensor_bytes(str(name), tensor)
        entry["offset"] = offset
        offset += len(data)
        entries.append(entry)
        blobs.append(data)
    header = {
        "format_version": FORMAT_VERSION,
        "byteorder": sys.byteorder,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "config": config,
        "metadata": metadata,
        "tensors": entries,
    }
    try:
        header_bytes = json.dumps(header, separators=(",", ":")).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: metadata or config is not JSON-serialisable ({exc})") from exc
    digest = hashlib.sha256()
    with atomic_write(path, error_type=CheckpointError) as handle:
        for chunk in (MAGIC, _LEN.pack(len(header_bytes)), header_bytes, *blobs):
            digest.update(chunk)
            handle.write(chunk)
        handle.write(digest.digest())
    logger.debug("wrote checkpoint %s (%d tensors, %d payload bytes)", path, len(entries), offset)
    return path


def _describe_foreign(data: bytes) -> str:
    if data[:1] == b"\x80" or data[:2] in (b"(d", b"(l", b"}q", b"]q"):
        return " (it looks like a Python pickle; mipslam never unpickles files)"
    if data[:4] == b"PK\x03\x04":
        return " (it looks like a zip/torch.save file; mipslam never unpickles files)"
    return ""


def read_checkpoint_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a checkpoint (config, metadata, tensor table) without reading its payload.

    For a quick look (how far a run got); the checksum is not verified, so resuming still goes through
    :func:`read_checkpoint`. CheckpointError when the file has no readable mipslam header.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            start = handle.read(len(MAGIC) + _LEN.size)
            if len(start) < len(MAGIC) + _LEN.size or not start.startswith(MAGIC):
                raise CheckpointError(f"{path}: not a mipslam checkpoint (bad magic bytes){_describe_foreign(start)}")
            (header_length,) = _LEN.unpack_from(start, len(MAGIC))
            if header_length > MAX_HEADER_BYTES:
                raise CheckpointError(f"{path}: header length {header_length} is implausible; the file is corrupt")
            raw = handle.read(header_length)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint ({exc.strerror or exc})") from exc
    try:
        header = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: unreadable header ({exc})") from exc
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: header is not a JSON object")
    return header


def read_checkpoint(path: str | Path, *, map_location: torch.device | str | None = None) -> Checkpoint:
    """Read and verify one checkpoint file; never executes code from it.

    Checks, in order: magic bytes, length, SHA-256 of the content, header JSON, format
    version, byte order, that every tensor lies inside the payload with the size its dtype and
    shape imply. Any failure raises CheckpointError naming the file and what is wrong.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read checkpoint ({exc.strerror or exc})") from exc
    minimum = len(MAGIC) + _LEN.size + _DIGEST_SIZE
    if len(data) < minimum or not data.startswith(MAGIC):
        if data.startswith(MAGIC):
            raise CheckpointError(f"{path}: truncated checkpoint ({len(data)} bytes)")
        raise CheckpointError(f"{path}: not a mipslam checkpoint (bad magic bytes){_describe_foreign(data)}")
    body, stored_digest = memoryview(data)[:-_DIGEST_SIZE], data[-_DIGEST_SIZE:]  # a view: no copy of the file
    if hashlib.sha256(body).digest() != stored_digest:
        raise CheckpointError(f"{path}: checksum mismatch, the file is corrupt or truncated")
    (header_length,) = _LEN.unpack_from(body, len(MAGIC))
    header_start = len(MAGIC) + _LEN.size
    if header_length > min(MAX_HEADER_BYTES, len(body) - header_start):
        raise CheckpointError(f"{path}: header length {header_length} exceeds the file")
    try:
        header = json.loads(bytes(body[header_start:header_start + header_length]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"{path}: unreadable header ({exc})") from exc
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: header is not a JSON object")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"{path}: checkpoint format version {version!r}, this mipslam reads version {FORMAT_VERSION}; "
            "start a new run (or resume with the mipslam version that wrote it)"
        )
    if header.get("byteorder") != sys.byteorder:
        raise CheckpointError(f"{path}: written on a {header.get('byteorder')!r}-endian machine, "
                              f"this one is {sys.byteorder}-endian")
    payload = body[header_start + header_length:]
    tensors: dict[str, torch.Tensor] = {}
    entries = header.get("tensors")
    if not isinstance(entries, list):
        raise CheckpointError(f"{path}: header has no tensor table")
    for entry in entries:
        try:
            name, dtype_name = str(entry["name"]), entry["dtype"]
            shape, offset, nbytes = [int(s) for s in entry["shape"]], int(entry["offset"]), int(entry["nbytes"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{path}: malformed tensor entry {entry!r}") from exc
        dtype = _DTYPES.get(dtype_name)
        if dtype is None:
            raise CheckpointError(f"{path}: tensor '{name}' has unknown dtype {dtype_name!r}")
        itemsize = torch.empty((), dtype=dtype).element_size()
        if any(s < 0 for s in shape) or nbytes != math.prod(shape) * itemsize:
            raise CheckpointError(f"{path}: tensor '{name}' size {nbytes} does not match shape {shape} {dtype_name}")
        if offset < 0 or offset + nbytes > len(payload):
            raise CheckpointError(f"{path}: tensor '{name}' lies outside the file")
        raw = bytearray(payload[offset:offset + nbytes])
        if nbytes:
            tensor = torch.frombuffer(raw, dtype=torch.uint8).view(dtype).reshape(shape)
        else:
            tensor = torch.empty(shape, dtype=dtype)
        tensors[name] = tensor if map_location is None else tensor.to(map_location)
    match = CHECKPOINT_PATTERN.match(path.name)
    return Checkpoint(
        path=path,
        tensors=tensors,
        metadata=header.get("metadata") or {},
        config=header.get("config") or {},
        format_version=version,
        created_utc=str(header.get("created_utc", "")),
        serial=int(match.group(1)) if match else None,
    )


# ----------------------------------------------------------------------------- a folder of checkpoints


def list_checkpoints(folder: str | Path) -> list[Path]:
    """Checkpoint files in ``folder``, oldest first (by serial number; temporaries excluded)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = []
    for path in folder.iterdir():
        match = CHECKPOINT_PATTERN.match(path.name)
        if match and path.is_file():
            found.append((int(match.group(1)), path))
    return [path for _, path in sorted(found)]


def save_checkpoint(folder: str | Path, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, Any], *,
                    config: Mapping[str, Any], keep: int = 2) -> Path:
    """Write the next numbered checkpoint in ``folder`` and then keep only the newest ``keep``.

    The previous checkpoints stay untouched until the new file is complete (renamed into
    place and the folder fsync'ed); only then are the oldest beyond ``keep`` deleted.
    Returns the new checkpoint's path.
    """
    if keep < 1:
        raise CheckpointError(f"keep must be >= 1 (KEEP_CHECKPOINTS), got {keep}")
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CheckpointError(f"{folder}: cannot create the checkpoint folder ({exc.strerror or exc})") from exc
    existing = list_checkpoints(folder)
    serial = 1 + (int(CHECKPOINT_PATTERN.match(existing[-1].name).group(1)) if existing else 0)
    path = write_checkpoint(folder / f"checkpoint-{serial:06d}.ckpt", tensors, metadata, config)
    for old in list_checkpoints(folder)[:-keep]:
        try:
            old.unlink()
        except FileNotFoundError:
            continue
        except OSError as exc:
            logger.warning("could not delete old checkpoint %s (%s); delete it by hand", old, exc.strerror or exc)
    return path


def load_latest_checkpoint(folder: str | Path, *, current_config: Mapping[str, Any] | None = None,
                           free_keys: Iterable[str] = RESUME_FREE_KEYS,
                           map_location: torch.device | str | None = None) -> Checkpoint:
    """The newest checkpoint in ``folder`` that passes verification.

    A corrupt, truncated or foreign file is reported with a warning and the next older one is
    tried. With ``current_config``, the chosen checkpoint's config must be compatible
    (:func:`check_config_compatible`), else CheckpointError naming the differing keys.
    Raises CheckpointError when no checkpoint is usable.
    """
    folder = Path(folder)
    candidates = list_checkpoints(folder)
    if not candidates:
        raise CheckpointError(f"{folder}: no checkpoint found (expected files named checkpoint-NNNNNN.ckpt)")
    problems = []
    for path in reversed(candidates):
        try:
            checkpoint = read_checkpoint(path, map_location=map_location)
        except CheckpointError as exc:
            logger.warning("skipping unusable checkpoint: %s; trying the previous one", exc)
            problems.append(str(exc))
            continue
        if current_config is not None:
            check_config_compatible(checkpoint.config, current_config, free_keys=free_keys, source=path)
            changed = free_config_differences(checkpoint.config, current_config, free_keys=free_keys)
            if changed:
                logger.info("resuming with settings that do not change results changed (%s); the run's config.yaml "
                            "records the new values", "; ".join(changed))
        if problems:
            logger.warning("resuming from older checkpoint %s", path)
        return checkpoint
    raise CheckpointError(f"{folder}: no usable checkpoint; " + "; ".join(problems))


# ----------------------------------------------------------------------------- config compatibility


def _flatten(mapping: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(_flatten(value, dotted + "."))
        else:
            out[dotted] = value
    return out


def _is_free(key: str, free_keys: Iterable[str]) -> bool:
    return any(key == free or key.startswith(free + ".") for free in free_keys)


def _differing_keys(saved: Mapping[str, Any], current: Mapping[str, Any]) -> list[tuple[str, str, str]]:
    """(dotted key, saved value, current value) of every differing key, values shown with repr.

    Both sides are normalised through JSON (tuples become lists) and their path keys made absolute
    (a folder written relative and absolute is one folder). A key present on one side only differs, except a
    key that a checkpoint written before the key existed lacks while the current config holds its default
    (the older code behaved as that default).
    """
    flat_saved = _flatten(with_absolute_paths(json.loads(json.dumps(saved))))
    flat_current = _flatten(with_absolute_paths(json.loads(json.dumps(current))))
    flat_defaults = _flatten(json.loads(json.dumps(config_to_dict(Config()))))
    missing = object()
    differences = []
    for key in sorted(set(flat_saved) | set(flat_current)):
        old, new = flat_saved.get(key, missing), flat_current.get(key, missing)
        if old is missing and key in flat_defaults and new == flat_defaults[key]:
            continue
        if old != new:
            differences.append((key, "<absent>" if old is missing else repr(old),
                                "<absent>" if new is missing else repr(new)))
    return differences


def config_differences(saved: Mapping[str, Any], current: Mapping[str, Any], *,
                       free_keys: Iterable[str] = RESUME_FREE_KEYS) -> list[str]:
    """Keys that change results and differ between two resolved configs, as ``"key: checkpoint X, now Y"``.

    Keys in ``free_keys`` (or below a section named there) are left out (:func:`free_config_differences`).
    """
    free_keys = tuple(free_keys)
    return [f"{key}: checkpoint {old}, now {new}" for key, old, new in _differing_keys(saved, current)
            if not _is_free(key, free_keys)]


def free_config_differences(saved: Mapping[str, Any], current: Mapping[str, Any], *,
                            free_keys: Iterable[str] = RESUME_FREE_KEYS) -> list[str]:
    """The differing keys that cannot change results (``free_keys``), as ``"key: X -> Y"``."""
    free_keys = tuple(free_keys)
    return [f"{key}: {old} -> {new}" for key, old, new in _differing_keys(saved, current) if _is_free(key, free_keys)]


def check_config_compatible(saved: Mapping[str, Any], current: Mapping[str, Any], *,
                            free_keys: Iterable[str] = RESUME_FREE_KEYS, source: str | Path = "checkpoint") -> None:
    """Raise CheckpointError naming every differing key when resuming would not continue the same run."""
    differences = config_differences(saved, current, free_keys=free_keys)
    if differences:
        source = Path(source)
        run_dir = source.parent.parent if source.parent.name == "checkpoints" else "RUN_DIR"
        raise CheckpointError(
            f"{source}: config differs from the one the run was started with in keys that change results ("
            + "; ".join(differences)
            + f"); continue with the run's own config (mipslam run --resume {run_dir}, without a config or --set) "
              "or start a new run with --out"
        )


# ----------------------------------------------------------------------------- random number generators


def capture_rng_state(generators: Mapping[str, torch.Generator] | None = None) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Random states of torch (CPU, and CUDA when initialised), numpy's global RNG, Python's
    ``random`` and the named ``generators``, as plain tensors plus JSON-able scalars.

    Returns (tensors with keys ``rng.*``, metadata dict) for :func:`restore_rng_state`.
    """
    tensors: dict[str, torch.Tensor] = {"rng.torch": torch.get_rng_state().clone()}
    meta: dict[str, Any] = {}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        tensors["rng.torch_cuda"] = torch.stack(torch.cuda.get_rng_state_all())
    kind, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    tensors["rng.numpy.keys"] = torch.from_numpy(np.asarray(keys, dtype=np.int64).copy())
    meta["numpy"] = {"kind": str(kind), "pos": int(pos), "has_gauss": int(has_gauss),
                     "cached_gaussian": float(cached_gaussian)}
    version, internal, gauss_next = random.getstate()
    tensors["rng.python.internal"] = torch.tensor(list(internal), dtype=torch.int64)
    meta["python"] = {"version": int(version), "gauss_next": gauss_next}
    for name, generator in (generators or {}).items():
        tensors[f"rng.generator.{name}"] = generator.get_state().clone()
    meta["generators"] = sorted((generators or {}).keys())
    return tensors, meta


def restore_rng_state(tensors: Mapping[str, torch.Tensor], meta: Mapping[str, Any],
                      generators: Mapping[str, torch.Generator] | None = None) -> None:
    """Inverse of :func:`capture_rng_state`; CheckpointError when an entry is missing."""
    try:
        torch.set_rng_state(tensors["rng.torch"].to(torch.uint8).cpu())
        if "rng.torch_cuda" in tensors and torch.cuda.is_available():
            states = tensors["rng.torch_cuda"].to(torch.uint8).cpu()
            if states.shape[0] == torch.cuda.device_count():
                torch.cuda.set_rng_state_all(list(states))
            else:
                logger.warning("checkpoint holds %d CUDA RNG states, this machine has %d devices; not restored",
                               states.shape[0], torch.cuda.device_count())
        numpy_meta = meta["numpy"]
        keys = tensors["rng.numpy.keys"].cpu().numpy().astype(np.uint32)
        np.random.set_state((numpy_meta["kind"], keys, numpy_meta["pos"], numpy_meta["has_gauss"],
                             numpy_meta["cached_gaussian"]))
        python_meta = meta["python"]
        internal = tuple(int(v) for v in tensors["rng.python.internal"].tolist())
        random.setstate((python_meta["version"], internal, python_meta["gauss_next"]))
        for name, generator in (generators or {}).items():
            generator.set_state(tensors[f"rng.generator.{name}"].to(torch.uint8).cpu())
    except KeyError as exc:
        raise CheckpointError(f"checkpoint lacks random state entry {exc}; it cannot be resumed exactly") from exc


# ----------------------------------------------------------------------------- prefixes


def with_prefix(prefix: str, tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``{"a": t}`` -> ``{"prefix.a": t}`` (to combine several components' states in one file)."""
    return {f"{prefix}.{key}": value for key, value in tensors.items()}


def select_prefix(prefix: str, tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Entries under ``prefix.`` with the prefix removed (inverse of :func:`with_prefix`)."""
    start = prefix + "."
    return {key[len(start):]: value for key, value in tensors.items() if key.startswith(start)}

