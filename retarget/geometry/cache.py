"""An on-disk cache of arrays keyed by a hash of what made them (distance grids, geodesics,
optimal-transport plans): written atomically, read back safely, rebuilt when unreadable."""

from __future__ import annotations

import hashlib
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from otr_gym.io import load_npz, save_npz


def default_cache_dir() -> Path:
    """$OTR_CACHE_DIR, else ~/.cache/otr-gym."""
    return Path(os.environ.get("OTR_CACHE_DIR", Path.home() / ".cache" / "otr-gym"))


def cached_arrays(path: Path, key: str, build: Callable[[], dict[str, np.ndarray]],
                  check: Callable[[dict[str, np.ndarray]], None]) -> dict[str, np.ndarray]:
    """Load ``path`` if it holds ``key`` and passes ``check``; otherwise build, save, return.

    A file that cannot be read, holds another key, or fails ``check`` (which raises) is
    rebuilt with a warning naming it.
    """
    if path.is_file():
        try:
            arrays = load_npz(path)
            if str(arrays.pop("cache_key", "")) != key:
                raise ValueError("cache key mismatch")
            check(arrays)
            return arrays
        except Exception as exc:  # noqa: BLE001 - any unreadable or invalid file is rebuilt, never trusted
            warnings.warn(f"{path}: invalid cache file ({type(exc).__name__}: {exc}); rebuilding", stacklevel=3)
    arrays = build()
    save_npz(path, {**arrays, "cache_key": np.array(key)}, compressed=False)
    return arrays


def hash_key(*parts: object) -> str:
    return hashlib.sha256("|".join(str(p) for p in parts).encode()).hexdigest()
