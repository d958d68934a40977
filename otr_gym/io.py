"""Atomic file output: every file we write appears whole under its final name or not at all;
and the one safe ``.npz`` reader (``load_npz``) every file reader uses.

A writer gets a temporary file in the destination folder (same file system, so the final
``os.replace`` is atomic); on success it is renamed onto the destination, on any exception
(Ctrl-C included) it is deleted and the previous file, if any, stays untouched.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
import zipfile
import zlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path next to ``path`` (same suffix, for writers that want a file name);
    renamed onto ``path`` when the block succeeds, deleted when it raises."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs get the usual mode
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write(path: str | Path, write: Callable[[IO[Any]], object], binary: bool = True) -> Path:
    """Call ``write(file)`` on a temporary file next to ``path``, fsync, then rename it onto ``path``."""
    with atomic_path(path) as tmp, open(tmp, "wb" if binary else "w", encoding=None if binary else "utf-8") as f:
        write(f)
        f.flush()
        os.fsync(f.fileno())
    return Path(path)


#: Time stamp of every member of our .npz files: the same arrays always give the same bytes
#: (``np.savez`` stamps the current time), so two runs — serial or on a cluster — can be compared
#: byte for byte.
NPZ_MEMBER_TIME = (1980, 1, 1, 0, 0, 0)


def npz_bytes(arrays: dict[str, np.ndarray], compressed: bool = True) -> bytes:
    """The ``.npz`` (zip of ``.npy``, what ``np.load`` reads) of ``arrays``, reproducibly."""
    buffer = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with zipfile.ZipFile(buffer, "w", compression=method) as archive:
        for key, value in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=NPZ_MEMBER_TIME)
            info.compress_type = method
            with archive.open(info, "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
    return buffer.getvalue()


def save_npz(path: str | Path, arrays: dict[str, np.ndarray], compressed: bool = True) -> Path:
    """An ``.npz`` file written atomically and reproducibly (``npz_bytes``)."""
    data = npz_bytes(arrays, compressed)
    return atomic_write(path, lambda f: f.write(data))


class NpzError(ValueError):
    """A file that is not a readable NumPy ``.npz`` archive; the message names the file and the problem."""


#: First bytes of a zip archive (a local file header, or the end record of an empty archive).
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")


def _first_bytes(head: bytes) -> str:
    """What the first bytes of a file say it is, for an error message."""
    if head.startswith(b"\x93NUMPY"):
        return "a single-array .npy file"
    if head[:1] == b"\x80":
        return "starts like a Python pickle"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return f"starts with the bytes {head[:8]!r}"
    if all(c.isprintable() or c.isspace() for c in text):
        return f"starts with the text {text.strip()[:24]!r}"
    return f"starts with the bytes {head[:8]!r}"


def check_npz(path: str | Path) -> Path:
    """``path`` if it looks like an ``.npz`` archive (a non-empty file starting as a zip archive);
    FileNotFoundError or NpzError naming the file and the problem otherwise."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    except OSError as exc:
        raise NpzError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if not head:
        raise NpzError(f"{path}: empty file (0 bytes), not a NumPy .npz archive")
    if not head.startswith(_ZIP_MAGIC):
        raise NpzError(f"{path}: not a NumPy .npz archive ({_first_bytes(head)})")
    return path


def _open_npz(path: Path):
    """``np.load`` of a checked archive (a context manager), never unpickling; zip-level failures as NpzError."""
    try:
        return np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, EOFError, OSError) as exc:
        # a zip archive cut short loses its central directory at the end: "File is not a zip file"
        raise NpzError(f"{path}: not a NumPy .npz archive (truncated or not a zip archive: {exc})") from exc


def npz_keys(path: str | Path) -> tuple[str, ...]:
    """The array names in an ``.npz`` file, without reading the arrays (``load_npz``'s errors)."""
    path = check_npz(path)
    with _open_npz(path) as npz:
        return tuple(npz.files)


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read safely: object (pickled) members are refused, never
    unpickled. FileNotFoundError for a missing file; NpzError naming the file and the problem
    (empty, not an archive, truncated, a damaged or object member) for anything else."""
    path = check_npz(path)
    out = {}
    with _open_npz(path) as npz:
        for key in npz.files:
            try:
                out[key] = npz[key]
            except ValueError as exc:
                if "pickle" in str(exc):  # numpy's advice here is to unpickle: not for files we did not write
                    raise NpzError(f"{path}: member {key!r} holds Python objects (pickled data); only plain "
                                   f"arrays are read from .npz files") from None
                raise NpzError(f"{path}: member {key!r} is not a readable array ({exc})") from exc
            except (zipfile.BadZipFile, EOFError, OSError, zlib.error) as exc:
                raise NpzError(f"{path}: member {key!r} is damaged ({exc})") from exc
    return out


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """A matplotlib figure as PNG, atomically; the figure is closed either way."""
    import matplotlib.pyplot as plt

    try:
        return atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=dpi))
    finally:
        plt.close(fig)


def write_json(path: str | Path, payload, indent: int = 2) -> Path:
    """JSON atomically; NaN/inf are refused (they are not JSON)."""
    return atomic_write(path, lambda f: json.dump(payload, f, indent=indent, ensure_ascii=False, allow_nan=False),
                        binary=False)
