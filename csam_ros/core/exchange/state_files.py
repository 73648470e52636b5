"""The file of every checkpoint and saved state: one ``.npz`` (numpy arrays, never pickles)
whose ``header`` entry is a JSON document with ``format``, ``version`` and ``kind`` and the
scalar parts, written atomically (:func:`write_npz`) and read back bounded and checked
(:func:`read_npz`, sizes before decompression; :class:`CheckpointError` names file and
fault). What each kind holds is :mod:`~csam_ros.core.exchange.checkpoint`'s.
"""

from __future__ import annotations

import errno
import io
import json
import math
import os
import tokenize
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from csam_ros.core.exchange.state_checks import (
    MAX_STAMP_S,
    StateFieldError,
    check_integer,
)
from csam_ros.core.model.regular_files import check_replaceable, read_regular

FORMAT = "csam_ros state"
VERSION = 2  # 2: a state's result keeps its per-pose series as arrays
READABLE_VERSIONS = (1, VERSION)  # 1: the whole result in the header

# The most bytes a state file may hold, and its arrays uncompressed (their sizes in its zip
# directory are checked before any is read): a checkpoint of an MR.CLAM robot is 8.6 MB.
MAX_STATE_BYTES = 512 * 2**20

R = TypeVar("R")
STAMP_RANGE = (-MAX_STAMP_S, MAX_STAMP_S)  # the range of a stamp in seconds


class CheckpointError(ValueError):
    """A checkpoint or state file that cannot be used; the message names file and fault."""


# --------------------------------------------------------------------------- the file


def write_npz(path: Path, kind: str, header: Mapping[str, Any], arrays: Mapping[str, Any]) -> int:
    """Write ``header`` (JSON) and ``arrays`` to ``path`` atomically; the bytes written.

    OSError, with nothing written, when ``path`` is a FIFO, a device or a socket (a rename
    would replace it) or the file would hold more than :data:`MAX_STATE_BYTES`; the
    temporary file is removed whenever the write fails."""
    path = Path(path)
    document = {"format": FORMAT, "version": VERSION, "kind": kind, **header}
    buffer = io.BytesIO()
    np.savez(
        buffer,
        header=np.array(json.dumps(document)),
        **{k: np.asarray(v) for k, v in arrays.items()},
    )
    data = buffer.getvalue()
    if len(data) > MAX_STATE_BYTES:
        raise OSError(errno.EFBIG, f"{len(data)} bytes, more than a state file holds", str(path))
    check_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    check_replaceable(tmp)  # the leftover of a writer killed before its rename is replaced
    tmp.unlink(missing_ok=True)
    out = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
    try:
        with os.fdopen(out, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)
    return len(data)


def _npy_array(raw: bytes) -> np.ndarray:
    """The array of one ``.npy`` entry, its header checked against its size before any array
    is made (numpy's reader would allocate the shape its header names first)."""
    stream = io.BytesIO(raw)
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
    else:
        raise ValueError(f"unsupported .npy version {version}")
    if dtype.hasobject or dtype.itemsize == 0:
        raise ValueError(f"an array of {dtype}")
    count = math.prod(shape)
    if count * dtype.itemsize != len(raw) - stream.tell():
        raise ValueError(
            f"shape {shape} of {dtype} in {len(raw) - stream.tell()} bytes of array data"
        )
    array = np.frombuffer(raw, dtype=dtype, count=count, offset=stream.tell())
    return array.reshape(shape, order="F" if fortran else "C").copy()


def _npz_arrays(path: Path, data: bytes) -> dict[str, np.ndarray]:
    """The arrays of an .npz file's bytes; the sizes its zip directory declares are checked
    first (no entry is decompressed beyond its declared size), then every entry whole (its
    CRC)."""
    arrays = {}
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        entries = archive.infolist()
        declared = sum(entry.file_size for entry in entries)
        if declared > MAX_STATE_BYTES:
            raise CheckpointError(
                f"{path}: its entries declare {declared} bytes, more than the "
                f"{MAX_STATE_BYTES} a state file may hold"
            )
        for entry in entries:
            name = entry.filename.removesuffix(".npy")
            if name == entry.filename or name in arrays:
                raise CheckpointError(f"{path}: entry {entry.filename!r:.80} is not one array")
            arrays[name] = _npy_array(archive.read(entry))
    return arrays


def read_npz(path: Path, kind: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and arrays of a file of ``kind`` written by :func:`write_npz`; at most
    :data:`MAX_STATE_BYTES` of file and of arrays, a regular file only."""
    path = Path(path)
    try:
        arrays = _npz_arrays(path, read_regular(path, MAX_STATE_BYTES))
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such file") from None
    # zipfile raises NotImplementedError and RuntimeError for damaged flags and methods,
    # numpy's .npy header parser TokenError; an OSError may be a FIFO or a file too large
    except (
        OSError,
        ValueError,
        zipfile.BadZipFile,
        EOFError,
        NotImplementedError,
        RuntimeError,
        tokenize.TokenError,
        zlib.error,
    ) as err:
        if isinstance(err, CheckpointError):
            raise
        cause = err.strerror if isinstance(err, OSError) and err.strerror else err
        raise CheckpointError(f"{path}: not a readable .npz file ({cause})") from None
    raw = arrays.pop("header", None)
    if raw is None or raw.shape != () or raw.dtype.kind != "U":
        raise CheckpointError(f"{path}: not a {FORMAT} file (no header)")
    try:
        header = json.loads(str(raw))
    except (ValueError, RecursionError) as err:  # JSONDecodeError, or an int of 5000 digits
        raise CheckpointError(f"{path}: damaged header ({err})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a {FORMAT} file")
    if header.get("version") not in READABLE_VERSIONS:
        raise CheckpointError(
            f"{path}: version {header.get('version')!r:.40}, this csam_ros reads versions "
            f"{', '.join(map(str, READABLE_VERSIONS))}"
        )
    if header.get("kind") != kind:
        raise CheckpointError(f"{path}: a {header.get('kind')!r:.40} file, not a {kind!r} one")
    return header, arrays


class StateReader:
    """Typed access to a file's header and arrays; a missing or bad entry is a
    :class:`CheckpointError` naming it."""

    def __init__(self, path: Path, header: Mapping[str, Any], arrays: Mapping[str, np.ndarray]):
        self.path, self.header, self.arrays = path, header, arrays

    def fail(self, what: str) -> CheckpointError:
        return CheckpointError(f"{self.path}: {what}")

    def value(self, key: str, kind: type | tuple[type, ...]) -> Any:
        if key not in self.header:
            raise self.fail(f"no {key!r} in the header")
        value = self.header[key]
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is not bool):
            raise self.fail(f"header {key!r}: unexpected value {value!r:.80}")
        return value

    def integer(self, key: str, low: int, high: int) -> int:
        """A header integer within ``[low, high]``."""
        return self.checked(check_integer, key, self.value(key, int), low, high)

    def checked(self, check: Callable[..., R], *args: Any) -> R:
        """``check(*args)`` (a check of :mod:`state_checks`), its fault a CheckpointError."""
        try:
            return check(*args)
        except StateFieldError as err:
            raise self.fail(str(err)) from None

    def array(
        self,
        key: str,
        dtype: Any = float,
        tail: tuple[int, ...] | None = None,
        finite: bool = True,
    ) -> np.ndarray:
        """An array of numbers (never a scalar), as ``dtype``; of shape ``(n, *tail)`` when
        ``tail`` is given. Floats must be finite unless ``finite`` is False."""
        if key not in self.arrays:
            raise self.fail(f"no array {key!r}")
        value = self.arrays[key]
        if value.dtype.kind not in ("f", "i", "u", "b") or (
            np.dtype(dtype).kind in "iu" and value.dtype.kind == "f"
        ):
            raise self.fail(f"array {key!r} holds {value.dtype}, not numbers")
        if value.ndim == 0:
            raise self.fail(f"array {key!r} is a scalar, not an array")
        if value.dtype.kind in "iu" and value.size and np.dtype(dtype).kind == "i":
            info = np.iinfo(dtype)
            if value.min() < info.min or value.max() > info.max:
                raise self.fail(f"array {key!r} holds integers beyond {np.dtype(dtype)}")
        value = value.astype(dtype)
        if tail is not None and (value.ndim != len(tail) + 1 or value.shape[1:] != tail):
            raise self.fail(f"array {key!r} has shape {value.shape}, expected (n, {tail})")
        if finite and value.dtype.kind == "f" and not np.isfinite(value).all():
            raise self.fail(f"array {key!r} holds a number that is not finite")
        return value


def stamp_to_json(value: float) -> float | None:
    return None if not np.isfinite(value) else float(value)


def stamp_from_json(value: Any) -> float:
    return -np.inf if value is None else float(value)
