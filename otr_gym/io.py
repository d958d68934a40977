"""Atomic file output: every file we write appears whole under its final name or not at all.

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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

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


def atomic_write(path: str | Path, write: Callable[[object], None], binary: bool = True) -> Path:
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
