"""One tensor saved by ``torch.save`` read without importing torch (``read_tensor``).

Importing torch takes ~2 s, as long as the rest of ``otr retarget``'s imports together, and an
OMOMO clip (InterMimic's ``.pt``) is one float tensor: a zip archive holding a pickle that
rebuilds the tensor from one raw storage file. This reads that layout with numpy and a pickle
unpickler that knows only the names such a file uses (like ``torch.load(weights_only=True)``,
it builds nothing else); the array holds the storage's own bytes, so it equals
``torch.load(path).numpy()``. Anything else (torch's legacy format, other objects, several
tensors) returns None and the caller loads the file with torch.
"""

from __future__ import annotations

import collections
import pickle
import zipfile
from pathlib import Path

import numpy as np

#: Storage classes of a torch pickle and their numpy element types.
_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8,
    "ByteStorage": np.uint8, "BoolStorage": np.bool_,
}


class _Unsupported(Exception):
    """The file is not one plain tensor in torch's zip layout."""


class _Storage:
    def __init__(self, data: np.ndarray) -> None:
        self.data = data


class _StorageType:
    def __init__(self, dtype) -> None:
        self.dtype = np.dtype(dtype)


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None,
                       metadata=None) -> np.ndarray:
    if not isinstance(storage, _Storage) or metadata:
        raise _Unsupported("tensor metadata")
    data = storage.data
    size, stride = tuple(int(s) for s in size), tuple(int(s) for s in stride)
    if len(size) != len(stride) or any(s < 0 for s in stride):
        raise _Unsupported("tensor layout")
    last = storage_offset + sum((n - 1) * s for n, s in zip(size, stride)) if all(size) else storage_offset - 1
    if storage_offset < 0 or last >= len(data):
        raise _Unsupported("tensor outside its storage")
    view = np.lib.stride_tricks.as_strided(data[storage_offset:], shape=size,
                                           strides=tuple(s * data.itemsize for s in stride), writeable=False)
    return np.array(view)  # own, C-ordered memory, as Tensor.numpy() of a contiguous tensor


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, archive: zipfile.ZipFile, prefix: str, byteorder: str) -> None:
        super().__init__(file)
        self.archive, self.prefix, self.byteorder = archive, prefix, byteorder

    def find_class(self, module: str, name: str):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor_v2
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(_STORAGE_DTYPES[name])
        raise _Unsupported(f"{module}.{name}")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage" and isinstance(pid[1], _StorageType)):
            raise _Unsupported("storage record")
        _, kind, key, _location, numel = pid
        dtype = kind.dtype.newbyteorder("<" if self.byteorder == "little" else ">")
        raw = self.archive.read(f"{self.prefix}/data/{key}")
        if len(raw) != int(numel) * dtype.itemsize:
            raise _Unsupported("storage size")
        return _Storage(np.frombuffer(raw, dtype=dtype).astype(kind.dtype, copy=False))


def read_tensor(path: Path) -> np.ndarray | None:
    """The one tensor ``torch.save`` wrote to ``path``, as a numpy array, or None when the file
    is anything else (then ``torch.load`` must read it, and say what is wrong with it)."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            pickles = [n for n in names if n.endswith("/data.pkl") and n.count("/") == 1]
            if len(pickles) != 1:
                return None
            prefix = pickles[0].split("/")[0]
            byteorder = (archive.read(f"{prefix}/byteorder").decode().strip() if f"{prefix}/byteorder" in names
                         else "little")
            if byteorder not in ("little", "big"):
                return None
            with archive.open(pickles[0]) as f:
                tensor = _Unpickler(f, archive, prefix, byteorder).load()
    except (OSError, zipfile.BadZipFile, pickle.UnpicklingError, _Unsupported, EOFError, KeyError, ValueError,
            TypeError, AttributeError, IndexError):
        return None
    return tensor if isinstance(tensor, np.ndarray) else None
