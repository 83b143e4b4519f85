"""Convert the official ``MANO_RIGHT.pkl`` to a safetensors file of arrays, without unpickling.

The official MANO model file (licence-gated: users download it themselves from
https://mano.is.tue.mpg.de) is a Python 2 pickle of a dict: numpy arrays (``v_template``,
``posedirs``, ``weights``, ``kintree_table``, ``f``, ``hands_components``, ``hands_mean``, ...),
``J_regressor`` as a ``scipy.sparse`` CSC matrix, ``shapedirs`` as a chumpy ``Ch`` (whose array
is its ``x`` attribute) and two strings (``bs_style = "lbs"``, ``bs_type = "lrotmin"``).
:func:`read_mano_pickle` rebuilds these from the pickle's opcodes
(:func:`~egosim.stages.hands.convert_pickle.read_pickle`): neither scipy nor chumpy is imported
and nothing named in the file is called; the sparse matrix is densified from its ``data``,
``indices`` and ``indptr`` arrays, the ``Ch`` replaced by its array. Any other object in the
file is refused. :func:`convert_mano_pickle` writes the arrays as ``mano.safetensors``, the file
:mod:`egosim.stages.hands.mano` reads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from egosim.stages.hands.convert_pickle import PickledObject, UnsafePickleError, read_pickle
from egosim.stages.hands.mano import MANO_FILE, ManoFileError, save_mano_arrays

SPARSE_CLASSES = {  # scipy.sparse classes as old and new scipy name them
    (module, f"{fmt}_{kind}"): fmt
    for fmt in ("csc", "csr")
    for module in (f"scipy.sparse.{fmt}", f"scipy.sparse._{fmt}")
    for kind in ("matrix", "array")
}
CHUMPY_CLASS = ("chumpy.ch", "Ch")  # chumpy's array wrapper
EXPECTED_STRINGS = {"bs_style": "lbs", "bs_type": "lrotmin"}  # what the MANO layer implements


def dense_from_sparse(obj: PickledObject, fmt: str) -> np.ndarray:
    """The dense array of a pickled scipy CSC/CSR matrix's state (``data``, ``indices``,
    ``indptr``, ``_shape``)."""
    state = obj.state
    if isinstance(state, tuple) and len(state) == 2:  # (dict, slots)
        state = state[0]
    if not isinstance(state, dict):
        raise UnsafePickleError(f"{obj.cls}: state is not a dict")
    shape = state.get("_shape", state.get("shape"))
    arrays = [state.get(k) for k in ("data", "indices", "indptr")]
    if shape is None or not all(isinstance(a, np.ndarray) for a in arrays):
        raise UnsafePickleError(f"{obj.cls}: needs _shape, data, indices and indptr")
    data, indices, indptr = arrays
    rows, cols = (int(s) for s in shape)
    major = cols if fmt == "csc" else rows  # CSC: indptr runs over columns
    minor = rows if fmt == "csc" else cols
    if (
        indptr.shape != (major + 1,)
        or indptr[0] != 0
        or indptr[-1] != len(data)
        or np.any(np.diff(indptr) < 0)
        or len(indices) != len(data)
        or (len(indices) and (indices.min() < 0 or indices.max() >= minor))
    ):
        raise UnsafePickleError(f"{obj.cls}: inconsistent sparse arrays for shape {shape}")
    dense = np.zeros((major, minor), dtype=np.float64)
    owner = np.repeat(np.arange(major), np.diff(indptr))  # (nnz,) column (CSC) of each value
    np.add.at(dense, (owner, indices.astype(np.int64)), data.astype(np.float64))
    return dense.T.copy() if fmt == "csc" else dense


def array_from_value(key: str, value: Any) -> np.ndarray | None:
    """The array a MANO dict entry holds (None for a string), or :class:`UnsafePickleError`."""
    if isinstance(value, np.ndarray):
        return value
    if isinstance(value, PickledObject):
        cls = (value.cls.module, value.cls.name)
        if cls in SPARSE_CLASSES:
            return dense_from_sparse(value, SPARSE_CLASSES[cls])
        if cls == CHUMPY_CLASS:
            state = value.state[0] if isinstance(value.state, tuple) else value.state
            inner = state.get("x") if isinstance(state, dict) else None
            if not isinstance(inner, np.ndarray):
                raise UnsafePickleError(f"{key}: chumpy Ch without an array 'x' in its state")
            return inner
    if isinstance(value, str):
        return None
    raise UnsafePickleError(f"{key}: a {type(value).__name__}, not an array")


def read_mano_pickle(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of an official MANO ``.pkl`` (layout in the module docstring), read from its
    opcodes; :class:`ManoFileError` names the file and what is wrong."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ManoFileError(f"{path}: cannot read MANO pickle ({exc})") from exc
    try:
        tree = read_pickle(data, classes={*SPARSE_CLASSES, CHUMPY_CLASS})
        if not isinstance(tree, dict):
            raise UnsafePickleError(f"holds a {type(tree).__name__}, not MANO's dict")
        arrays = {}
        for key, value in tree.items():
            array = array_from_value(str(key), value)
            if array is None:
                expected = EXPECTED_STRINGS.get(str(key))
                if expected is not None and value != expected:
                    raise UnsafePickleError(f"{key} = {value!r}; this MANO layer needs {expected}")
                continue
            arrays[str(key)] = array
    except UnsafePickleError as exc:
        raise ManoFileError(f"{path}: {exc}") from exc
    return arrays


def convert_mano_pickle(path: str | Path, out_dir: str | Path) -> Path:
    """Convert the MANO pickle ``path`` to ``out_dir/mano.safetensors`` (checked); its path."""
    arrays = read_mano_pickle(path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target = out / MANO_FILE
    try:
        save_mano_arrays(arrays, target)
    except ManoFileError as exc:
        raise ManoFileError(f"{path}: not a MANO model ({exc})") from exc
    return target
