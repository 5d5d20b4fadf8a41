"""Body model and pose prior files: SMPL-format ``.npz`` / official ``.pkl``, ``gmm_08.pkl``.

Formats (field by field):

- Body model (``.npz`` written by :func:`save_body_model_npz`, or the official SMPL ``.pkl``):
  ``v_template`` (V, 3) float metres, y-up template; ``f`` (F, 3) int faces; ``shapedirs``
  (V, 3, B); ``posedirs`` (V, 3, 207); ``weights`` (V, 24); ``kintree_table`` (2, 24) (row 0
  parents, root parent 2**32 - 1; row 1 joint ids); ``J_regressor`` (24, V) (scipy.sparse in the
  official pkl, returned dense); optional ``coco_vertex_ids`` (5,) and any other array keys.
- Body model as a plain-numpy SMPL pickle (:func:`save_body_model_pkl`): the official keys as
  numpy arrays (J_regressor dense), written with storage/plain_pickle.py (globals numpy.ndarray
  and builtins.bytearray only), so ``smplx.SMPL(model_path=...)`` (which reads SMPL only from a
  pickle) and numpy 1.x read it, and :func:`load_body_model` too.
- Pose prior (``gmm_08.pkl``, a Python-2 pickle, encoding latin1): a dict with ``means``
  (K, 69), ``covars`` (K, 69, 69), ``weights`` (K,), float64.

Pickles are read with a restricted unpickler: only numpy array / dtype reconstruction, the
copyreg helpers that rebuild plain objects, and stand-ins for scipy.sparse matrices and chumpy
arrays are allowed; any other global (os.system, builtins.eval, ...) raises
:class:`UnsafePickleError` before anything runs. Chumpy objects become plain numpy arrays.
"""

from __future__ import annotations

import collections
import copyreg
import io
import pickle
from pathlib import Path

import numpy as np
import scipy.sparse

from storage.atomic import atomic_write_bytes
from storage.files import InputError, open_regular, read_bytes
from storage.npzio import NPZ_ERRORS, load_npz, save_npz_deterministic
from tasks.conventions import SMPL_MODEL_KEYS

POSE_PRIOR_KEYS = ("means", "covars", "weights")

#: bounds of what a model file may hold, checked before memory is spent on it: the file's size
#: (the official SMPL pickles are 40-250 MB), how deep its pickle nests (a model's is < 20; a
#: flat batch of 1,000 dict items counts 2,000) and the cells of a pickled sparse matrix made dense
MAX_MODEL_FILE_BYTES = 1 << 30
MAX_PICKLE_DEPTH = 10_000
MAX_DENSE_CELLS = 1 << 27


class UnsafePickleError(ValueError):
    """A pickle asked for a global outside the allow-list (it could run code)."""


class BodyFileError(ValueError):
    """A body model / prior file with a missing key, a wrong shape or an unknown format."""


class _StandIn:
    """Receives the state of a pickled object in place of its class; ``to_array`` makes the
    array it stands for."""

    state = None  # pickles may build the object with __new__ only

    def __init__(self, *args, **kwargs):
        self.state = None

    def __setstate__(self, state):
        self.state = state

    def _state(self):
        st = self.state
        if isinstance(st, tuple) and len(st) == 2 and isinstance(st[0], dict):
            st = st[0]  # (dict state, slot state)
        return st


class _ChumpyStandIn(_StandIn):
    """Receives the state of a pickled chumpy object (``chumpy.ch.Ch`` and friends)."""

    def to_array(self) -> np.ndarray:
        st = self._state()
        if isinstance(st, dict):
            for key in ("x", "r", "a"):
                if key in st:
                    return _to_plain(st[key])
            arrays = [v for v in st.values() if isinstance(v, (np.ndarray, _ChumpyStandIn))]
            if len(arrays) == 1:
                return _to_plain(arrays[0])
        elif isinstance(st, np.ndarray):
            return st
        raise BodyFileError(
            f"a chumpy object without a recognisable array (state keys: "
            f"{sorted(st) if isinstance(st, dict) else type(st).__name__})"
        )


class _SparseStandIn(_StandIn):
    """Receives the state of a pickled scipy.sparse matrix (``data``/``indices``/``indptr``)."""

    kind = "csc"

    def to_array(self) -> np.ndarray:
        st = self._state()
        if not isinstance(st, dict):
            raise BodyFileError(f"a pickled sparse matrix with state {type(st).__name__}")
        shape = st.get("_shape", st.get("shape"))
        try:
            cells = int(np.prod([int(n) for n in shape], dtype=np.float64))
        except (TypeError, ValueError):
            raise BodyFileError(f"a pickled sparse matrix of shape {shape!r}") from None
        if cells > MAX_DENSE_CELLS:
            raise BodyFileError(
                f"a pickled sparse matrix of shape {tuple(shape)}: more than {MAX_DENSE_CELLS} "
                "cells dense (an SMPL J_regressor is 24 x V)"
            )
        fmt = st.get("format", self.kind)
        if isinstance(fmt, bytes):
            fmt = fmt.decode("latin1")
        if fmt in ("csc", "csr"):
            cls = scipy.sparse.csc_matrix if fmt == "csc" else scipy.sparse.csr_matrix
            m = cls((st["data"], st["indices"], st["indptr"]), shape=tuple(int(s) for s in shape))
        elif fmt == "coo":
            m = scipy.sparse.coo_matrix(
                (st["data"], (st["row"], st["col"])), shape=tuple(int(s) for s in shape)
            )
        else:
            raise BodyFileError(f"unsupported pickled sparse format {fmt!r}")
        return np.asarray(m.toarray())


_SPARSE_STAND_INS = {
    kind: type(f"_Sparse_{kind}", (_SparseStandIn,), {"kind": kind})
    for kind in ("csc", "csr", "coo")
}


_NUMPY_ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}


def _latin1_encode(text, encoding="latin1", errors="strict"):
    """What protocol-2 pickles of ``bytes`` call (``_codecs.encode(str, 'latin1')``)."""
    if encoding not in ("latin1", "latin-1", "iso-8859-1") or not isinstance(text, str):
        raise UnsafePickleError(f"pickle calls _codecs.encode with encoding {encoding!r}")
    return text.encode("latin1", errors="strict")


# Constructors of plain data types (chumpy states hold sets, for instance); none can run code.
_SAFE_BUILTINS = {
    t.__name__: t
    for t in (
        object,
        set,
        frozenset,
        list,
        dict,
        tuple,
        slice,
        complex,
        bytearray,
        bool,
        int,
        float,
        str,
    )
}


def _bytearray(*args):
    """``bytearray`` as a pickle may call it: from bytes or text, never ``bytearray(n)`` (n
    zero bytes: a memory bomb)."""
    if args and isinstance(args[0], int) and not isinstance(args[0], bool):
        raise UnsafePickleError(f"pickle calls bytearray({args[0]}), which is not allowed")
    return bytearray(*args)


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) == ("_codecs", "encode"):
            return _latin1_encode
        if (module, name) in _NUMPY_ALLOWED:
            mod = "numpy._core.multiarray" if module.endswith("multiarray") else module
            mod = "numpy._core.numeric" if module.endswith("numeric") else mod
            return getattr(__import__(mod, fromlist=[name]), name)
        if module in ("copy_reg", "copyreg") and name in ("_reconstructor", "__newobj__"):
            return getattr(copyreg, name)
        if module in ("__builtin__", "builtins") and name == "bytearray":
            return _bytearray
        if module in ("__builtin__", "builtins") and name in _SAFE_BUILTINS:
            return _SAFE_BUILTINS[name]
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "chumpy" or module.startswith("chumpy."):
            return _ChumpyStandIn
        is_sparse = name[:3] in _SPARSE_STAND_INS and name[3:] in ("_matrix", "_array")
        if module.startswith("scipy.sparse") and is_sparse:
            return _SPARSE_STAND_INS[name[:3]]
        raise UnsafePickleError(
            f"pickle refers to the global {module}.{name}, which is not allowed"
        )

    def persistent_load(self, pid):
        raise UnsafePickleError("pickle uses persistent ids, which are not allowed")


def _to_plain(obj):
    if isinstance(obj, (_ChumpyStandIn, _SparseStandIn)):
        return obj.to_array()
    if isinstance(obj, dict):
        return {
            (k.decode("latin1") if isinstance(k, bytes) else k): _to_plain(v)
            for k, v in obj.items()
        }
    return obj


def _check_structure(path: Path, data: bytes) -> None:
    """Walk the pickle's opcodes without running any (pickletools.genops): a declared length
    past the file's end, a stack deeper than :data:`MAX_PICKLE_DEPTH` (a 200,000-deep nesting
    would end in a RecursionError or a crash) or a truncated pickle is a BodyFileError before
    anything is built or allocated."""
    import pickletools

    stack, marks, deepest = 0, [], 0
    try:
        for op, _, _ in pickletools.genops(data):
            before, after = op.stack_before, op.stack_after
            if pickletools.markobject in before:
                # items above the mark go, and the ones listed before the mark (APPENDS' list)
                stack = (marks.pop() if marks else 0) - before.index(pickletools.markobject)
            else:
                stack -= len(before)
            if pickletools.markobject in after:
                marks.append(max(stack, 0))
            else:
                stack += len(after)
            deepest = max(deepest, stack + len(marks))
            if deepest > MAX_PICKLE_DEPTH:
                raise BodyFileError(
                    f"{path}: pickle nests deeper than {MAX_PICKLE_DEPTH} levels; refused"
                )
    except ValueError as e:  # genops: a truncated pickle, a declared length past the end
        if isinstance(e, BodyFileError):
            raise
        raise BodyFileError(f"{path}: not a readable pickle ({e})") from None


def _restricted_load(path: Path) -> dict:
    try:
        data = read_bytes(path, what="model file", max_bytes=MAX_MODEL_FILE_BYTES)
    except InputError as e:  # missing, a device (/dev/zero), a FIFO, too large
        raise BodyFileError(str(e)) from None
    _check_structure(path, data)
    try:
        obj = _RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()
    except UnsafePickleError as e:
        raise UnsafePickleError(f"{path}: {e}") from None
    except (pickle.UnpicklingError, EOFError, AttributeError, TypeError, ValueError) as e:
        raise BodyFileError(f"{path}: not a readable pickle ({type(e).__name__}: {e})") from e
    except (RecursionError, MemoryError) as e:
        raise BodyFileError(f"{path}: not a plausible model pickle ({type(e).__name__})") from None
    if not isinstance(obj, dict):
        raise BodyFileError(f"{path}: expected a pickled dict, got {type(obj).__name__}")
    out = {}
    for k, v in obj.items():
        key = k.decode("latin1") if isinstance(k, bytes) else k
        try:
            out[key] = _to_plain(v)
        except BodyFileError as e:
            if key in SMPL_MODEL_KEYS or key in POSE_PRIOR_KEYS:
                raise BodyFileError(f"{path}: key {key!r}: {e}") from e
            # an auxiliary chumpy expression we cannot evaluate: not needed, dropped
    return out


def load_body_model(path) -> dict[str, np.ndarray]:
    """Read SMPL-format parameters from ``.npz`` or an official ``.pkl`` (restricted unpickler).

    Returns a dict of numpy arrays with at least SMPL_MODEL_KEYS (J_regressor dense);
    non-array entries of a pkl (e.g. ``bs_style`` strings) are dropped.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with open_regular(path, what="body model file") as fh:
                params = load_npz(fh)  # each member's size checked before it is read
        except InputError as e:
            raise BodyFileError(str(e)) from None
        except NPZ_ERRORS as e:
            raise BodyFileError(f"{path}: cannot read body model npz ({e})") from e
    elif suffix == ".pkl":
        raw = _restricted_load(path)
        params = {}
        for k, v in raw.items():
            if isinstance(v, np.ndarray):
                params[k] = v
            elif isinstance(v, scipy.sparse.spmatrix):
                params[k] = np.asarray(v.toarray())
    else:
        raise BodyFileError(f"{path}: expected a .npz or .pkl body model file")
    missing = [k for k in SMPL_MODEL_KEYS if k not in params]
    if missing:
        raise BodyFileError(f"{path}: body model lacks keys {missing}; has {sorted(params)}")
    V = params["v_template"].shape[0]
    if params["v_template"].shape != (V, 3) or params["J_regressor"].shape != (24, V):
        raise BodyFileError(
            f"{path}: v_template {params['v_template'].shape} / J_regressor "
            f"{params['J_regressor'].shape} do not match (V, 3) / (24, V)"
        )
    return params


def _refuse_incomplete(path, params: dict) -> Path:
    missing = [k for k in SMPL_MODEL_KEYS if k not in params]
    if missing:
        raise BodyFileError(f"{path}: refusing to write a body model without keys {missing}")
    return Path(path)


def save_body_model_npz(path, params: dict) -> None:
    """Write body model parameters (dict of arrays, SMPL keys) as an uncompressed ``.npz`` with
    deterministic bytes (:mod:`storage.npzio`); writers may race: each renames a whole file."""
    save_npz_deterministic(
        _refuse_incomplete(path, params),
        compressed=False,
        **{k: np.asarray(v) for k, v in params.items()},
    )


def save_body_model_pkl(path, params: dict) -> None:
    """Write body model parameters as a plain-numpy SMPL pickle (official keys; extra array keys
    such as ``coco_vertex_ids`` kept). Deterministic for equal parameters."""
    from storage.plain_pickle import dumps_plain

    atomic_write_bytes(
        _refuse_incomplete(path, params),
        dumps_plain({k: np.array(params[k]) for k in sorted(params)}),
    )


#: the procedural stand-in's "gender": smplx.SMPL finds ``SMPL_<GENDER>.pkl`` in a folder
SMPLX_GENDER = "procedural"


def save_smplx_model(folder, params: dict, gender: str = SMPLX_GENDER) -> Path:
    """Write body model parameters where ``smplx`` finds them: ``<folder>/smpl/SMPL_<GENDER>.pkl``
    (:func:`save_body_model_pkl`). smplx.create reads the model type from the file name's first
    ``_`` part (``smpl``), so both ``smplx.create(that_file)`` and ``smplx.create(folder,
    model_type="smpl", gender=gender)`` load it (pass :func:`smplx_vertex_ids` as
    ``vertex_ids`` for a mesh other than SMPL's). Returns the file's path."""
    path = Path(folder) / "smpl" / f"SMPL_{gender.upper()}.pkl"
    save_body_model_pkl(path, params)
    return path


def smplx_vertex_ids(params: dict) -> dict[str, int]:
    """The ``vertex_ids`` to pass to ``smplx.SMPL`` for a model other than the official SMPL
    (smplx's default indices are SMPL's 6,890-vertex ids): its face keypoints from
    ``coco_vertex_ids`` (nose, l_eye, r_eye, l_ear, r_ear). Pass ``use_hands=False,
    use_feet_keypoints=False`` with it (no finger-tip / toe ids on the stand-in)."""
    if "coco_vertex_ids" not in params:
        raise BodyFileError(
            "body model has no coco_vertex_ids: cannot name its face keypoint vertices"
        )
    nose, leye, reye, lear, rear = (
        int(i) for i in np.asarray(params["coco_vertex_ids"]).reshape(5)
    )
    return {"nose": nose, "leye": leye, "reye": reye, "lear": lear, "rear": rear}


def _check_prior(path: Path, prior: dict) -> dict[str, np.ndarray]:
    missing = [k for k in POSE_PRIOR_KEYS if k not in prior]
    if missing:
        raise BodyFileError(f"{path}: pose prior lacks keys {missing}; has {sorted(prior)}")
    try:
        out = {k: np.asarray(prior[k], dtype=np.float64) for k in POSE_PRIOR_KEYS}
    except (TypeError, ValueError, RecursionError) as e:
        raise BodyFileError(f"{path}: pose prior arrays are not numbers ({e})") from None
    K = out["weights"].reshape(-1).shape[0]
    out["weights"] = out["weights"].reshape(-1)
    m, c = out["means"], out["covars"]
    if m.ndim != 2 or m.shape[0] != K or c.shape != (K, m.shape[1], m.shape[1]):
        raise BodyFileError(
            f"{path}: pose prior shapes means {m.shape}, covars {c.shape}, weights ({K},) "
            f"are not (K, d), (K, d, d), (K,)"
        )
    return out


def save_pose_prior_pkl(path, prior: dict) -> None:
    """Write a pose prior dict (means, covars, weights) as a protocol-2 pickle (gmm_08 layout)."""
    path = Path(path)
    out = _check_prior(path, prior)
    atomic_write_bytes(path, pickle.dumps(out, protocol=2))


def load_pose_prior(path) -> dict[str, np.ndarray]:
    """Read a ``gmm_08.pkl``-layout prior with the restricted unpickler (encoding latin1).

    Returns means (K, d), covars (K, d, d), weights (K,), float64.
    """
    path = Path(path)
    return _check_prior(path, _restricted_load(path))
