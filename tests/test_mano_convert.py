"""MANO .pkl -> safetensors without unpickling, on pickles that mimic the official file."""

from __future__ import annotations

import pickle
import struct
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse

torch = pytest.importorskip("torch")

from egosim.stages.hands.convert_mano import convert_mano_pickle, read_mano_pickle  # noqa: E402
from egosim.stages.hands.convert_pickle import UnsafePickleError, read_pickle  # noqa: E402
from egosim.stages.hands.mano import ManoFileError, load_mano_arrays, load_mano_layer  # noqa: E402
from tests.test_mano import numpy_mano, tiny_mano  # noqa: E402

CALLS: list[str] = []  # what the stub classes saw called


class Ch:
    """Stands in for ``chumpy.ch.Ch`` when writing: pickled by class name with its ``__dict__``."""


def _refusing_chumpy_module() -> types.ModuleType:
    """A ``chumpy.ch`` whose ``Ch`` records and refuses being created or given state."""

    class RefusingCh:
        def __new__(cls, *args, **kwargs):
            CALLS.append("Ch.__new__")
            raise AssertionError("the converter created a chumpy object")

        def __setstate__(self, state):
            CALLS.append("Ch.__setstate__")
            raise AssertionError("the converter set a chumpy object's state")

    module = types.ModuleType("chumpy.ch")
    RefusingCh.__module__, RefusingCh.__qualname__ = "chumpy.ch", "Ch"
    module.Ch = RefusingCh
    return module


class Py2Pickler(pickle._Pickler):
    """Writes bytes as Python 2 ``str`` opcodes (SHORT_BINSTRING / BINSTRING), as the official
    Python 2 file stores array data."""

    dispatch = pickle._Pickler.dispatch.copy()

    def save_bytes(self, obj: bytes) -> None:
        if len(obj) < 256:
            self.write(pickle.SHORT_BINSTRING + bytes([len(obj)]) + obj)
        else:
            self.write(pickle.BINSTRING + struct.pack("<i", len(obj)) + obj)
        self.memoize(obj)

    dispatch[bytes] = save_bytes


def official_like(arrays: dict[str, np.ndarray], monkeypatch, py2: bool = False) -> bytes:
    """A pickle of ``arrays`` in the official layout: ``J_regressor`` a scipy CSC matrix,
    ``shapedirs`` a ``chumpy.ch.Ch`` with its array as ``x``, the two blend-skinning strings."""
    package = types.ModuleType("chumpy")
    module = types.ModuleType("chumpy.ch")
    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    module.Ch = Ch
    monkeypatch.setitem(sys.modules, "chumpy", package)
    monkeypatch.setitem(sys.modules, "chumpy.ch", module)
    shapedirs = Ch()
    shapedirs.__dict__.update(
        {
            "x": arrays["shapedirs"],
            "_dirty_vars": {"x"},
            "_itr": None,
            "_depends_on_deps": {},
            "_make_dense": False,
            "_make_sparse": False,
        }
    )
    tree = {
        **arrays,
        "J_regressor": scipy.sparse.csc_matrix(arrays["J_regressor"]),
        "shapedirs": shapedirs,
        "bs_style": "lbs",
        "bs_type": "lrotmin",
        "f": np.array([[0, 1, 2], [2, 1, 3]], dtype=np.uint32),
    }
    if not py2:
        data = pickle.dumps(tree, protocol=2)
    else:
        import io

        buffer = io.BytesIO()
        Py2Pickler(buffer, protocol=2).dump(tree)
        data = buffer.getvalue()
    # From here on chumpy.ch is a module that refuses: the converter must not import or call it.
    monkeypatch.setitem(sys.modules, "chumpy.ch", _refusing_chumpy_module())
    return data


@pytest.mark.parametrize("py2", [False, True])
def test_official_like_pickle_converts_without_unpickling(tmp_path: Path, monkeypatch, py2) -> None:
    arrays = tiny_mano()
    pkl = tmp_path / "MANO_RIGHT.pkl"
    pkl.write_bytes(official_like(arrays, monkeypatch, py2=py2))
    CALLS.clear()
    with pytest.raises(AssertionError):  # the stub bites: unpickling would have called it
        pickle.loads(pkl.read_bytes(), encoding="latin1")  # as MANO loaders do
    assert CALLS
    CALLS.clear()
    out = convert_mano_pickle(pkl, tmp_path / "weights")
    assert CALLS == []  # nothing in the file was called
    converted = load_mano_arrays(out)
    for key in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights"):
        np.testing.assert_array_equal(converted[key], arrays[key])
    np.testing.assert_array_equal(converted["kintree_table"], arrays["kintree_table"])
    assert "bs_style" not in converted and converted["f"].shape == (2, 3)
    # The converted model runs and equals the reference on the original arrays.
    rng = np.random.default_rng(4)
    pose, betas = rng.normal(0.0, 0.5, (16, 3)), rng.normal(0.0, 1.0, 4)
    layer = load_mano_layer(out, torch.float64)
    from egosim.stages.hands.mano import axis_angle_to_matrix

    rot = axis_angle_to_matrix(torch.as_tensor(pose))[None]
    _, joints = layer(rot, torch.as_tensor(betas)[None])
    np.testing.assert_allclose(joints[0].numpy(), numpy_mano(arrays, pose, betas), atol=1e-12)


def test_sparse_matrices_are_densified_exactly(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    dense = rng.normal(size=(5, 7)) * (rng.uniform(size=(5, 7)) < 0.3)
    for matrix in (scipy.sparse.csc_matrix(dense), scipy.sparse.csr_matrix(dense)):
        pkl = tmp_path / "m.pkl"
        pkl.write_bytes(pickle.dumps({"J_regressor": matrix}, protocol=4))
        np.testing.assert_array_equal(read_mano_pickle(pkl)["J_regressor"], dense)


def test_code_in_a_pickle_is_refused_and_never_run(tmp_path: Path) -> None:
    class Payload:
        def __reduce__(self):
            return (CALLS.append, ("payload ran",))

    CALLS.clear()
    pkl = tmp_path / "MANO_RIGHT.pkl"
    pkl.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3)), "x": Payload()}, protocol=2))
    with pytest.raises(ManoFileError, match=r"MANO_RIGHT\.pkl.*getattr"):
        read_mano_pickle(pkl)
    assert CALLS == []
    evil = b"cos\nsystem\n(S'echo hi'\ntR."  # protocol 0: os.system('echo hi')
    with pytest.raises(UnsafePickleError, match=r"os\.system"):
        read_pickle(evil)
    with pytest.raises(UnsafePickleError, match="INST"):
        read_pickle(b"(S'echo hi'\nios\nsystem\n.")
    objects = pickle.dumps({"a": np.array([object()], dtype=object)}, protocol=2)
    with pytest.raises(UnsafePickleError):
        read_pickle(objects)


def test_plain_values_and_dtypes_round_trip() -> None:
    value = {
        "f32": np.arange(6, dtype="<f4").reshape(2, 3),
        "big": np.arange(4, dtype=">i8"),
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "scalar": np.float64(2.5),
        "items": [1, 2.0, "s", b"b", None, True, (1, 2)],
        "set": {1, 2},
    }
    for protocol in range(6):
        out = read_pickle(pickle.dumps(value, protocol=protocol))
        for key in ("f32", "big", "fortran"):
            np.testing.assert_array_equal(out[key], value[key])
            assert out[key].dtype == value[key].dtype
        assert out["scalar"] == 2.5 and out["items"] == value["items"] and out["set"] == {1, 2}


def test_bad_mano_files_name_the_file(tmp_path: Path) -> None:
    pkl = tmp_path / "MANO_RIGHT.pkl"
    pkl.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(ManoFileError, match=r"MANO_RIGHT\.pkl.*not MANO's dict"):
        read_mano_pickle(pkl)
    pkl.write_bytes(pickle.dumps({"bs_style": "dqs"}))
    with pytest.raises(ManoFileError, match="bs_style"):
        read_mano_pickle(pkl)
    pkl.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3))}))
    with pytest.raises(ManoFileError, match=r"not a MANO model.*missing arrays"):
        convert_mano_pickle(pkl, tmp_path / "out")
    pkl.write_bytes(b"\x80\x02}q\x00")  # truncated
    with pytest.raises(ManoFileError, match="malformed"):
        read_mano_pickle(pkl)
    with pytest.raises(ManoFileError, match="cannot read"):
        read_mano_pickle(tmp_path / "absent.pkl")


def test_cli_converts_mano(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from egosim.pipeline.cli import app

    pkl = tmp_path / "MANO_RIGHT.pkl"
    pkl.write_bytes(official_like(tiny_mano(), monkeypatch))
    result = CliRunner().invoke(app, ["hands", "convert-mano", str(pkl), "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "mano.safetensors").is_file()
    pkl.write_bytes(pickle.dumps({"v_template": np.zeros((3, 3))}))
    result = CliRunner().invoke(app, ["hands", "convert-mano", str(pkl), "--out", str(tmp_path)])
    assert result.exit_code == 2 and "missing arrays" in result.output
