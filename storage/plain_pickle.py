"""Pickles of plain data that old and new numpy alike can read (training infos, SMPL model files).

numpy 2 pickles an array through ``numpy._core.multiarray._reconstruct``, a module numpy < 1.26
does not have (tried: numpy 1.23.5 raises "No module named 'numpy._core'"; 1.26.4 reads it), so
trainers pinned to old numpy (mmdet3d 1.0 / FlashOcc setups) fail on them.
:func:`dumps_plain` writes every array as ``numpy.ndarray(shape, dtype_str, bytearray(data))``
(globals ``numpy.ndarray`` and ``builtins.bytearray`` only, present in every numpy and Python 3),
which unpickles to an ordinary writable array. Allowed inside: dict, list, tuple, str, bytes,
int, float, bool, None and numpy arrays of numeric, bool or fixed-width string dtype; anything
else (numpy scalars included: use Python numbers) raises TypeError naming its path in the object.
"""

from __future__ import annotations

import io
import pickle

import numpy as np

#: protocol 4: Python >= 3.4 reads it (trainers still run 3.7)
PROTOCOL = 4


def _rebuild_args(a: np.ndarray) -> tuple:
    a = np.ascontiguousarray(a)
    return (a.shape, a.dtype.str, bytearray(a.tobytes()), 0, None, None)


def _check(obj, path: str) -> None:
    if obj is None or type(obj) in (bool, int, float, str, bytes):  # exact: np.float64 is a float
        return
    if type(obj) is np.ndarray:
        if obj.dtype.kind not in "biufcU" or obj.dtype.fields is not None:
            raise TypeError(f"{path}: array of dtype {obj.dtype} is not plain data")
        return
    if type(obj) is dict:
        for k, v in obj.items():
            if type(k) not in (str, int):
                raise TypeError(f"{path}: dict key {k!r} of type {type(k).__name__}")
            _check(v, f"{path}[{k!r}]")
        return
    if type(obj) in (list, tuple):
        for i, v in enumerate(obj):
            _check(v, f"{path}[{i}]")
        return
    raise TypeError(f"{path}: {type(obj).__module__}.{type(obj).__name__} is not plain data")


class _PlainPickler(pickle.Pickler):
    def reducer_override(self, obj):
        if isinstance(obj, np.ndarray):
            return (np.ndarray, _rebuild_args(obj))
        return NotImplemented


def dumps_plain(obj) -> bytes:
    """``obj`` (plain data, see the module docstring) as pickle bytes, deterministic for equal input."""
    _check(obj, "object")
    buffer = io.BytesIO()
    _PlainPickler(buffer, protocol=PROTOCOL).dump(obj)
    return buffer.getvalue()


def pickle_globals(data: bytes) -> set[tuple[str, str]]:
    """The (module, name) globals a pickle refers to, read without unpickling it."""
    import pickletools

    found, pushed, memo = set(), [], {}
    for op, arg, _ in pickletools.genops(data):
        if op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"):
            pushed.append(arg)
        elif op.name == "MEMOIZE":
            memo[len(memo)] = pushed[-1] if pushed else None
        elif op.name in ("BINGET", "LONG_BINGET", "GET"):
            pushed.append(memo.get(int(arg)))
        elif op.name == "STACK_GLOBAL":
            found.add((pushed[-2], pushed[-1]))
            pushed.append(None)
        elif op.name == "GLOBAL":
            found.add(tuple(arg.split(" ", 1)))
        else:
            pushed.append(None)
    return found
