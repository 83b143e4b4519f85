"""Read the data out of a pickle without unpickling it: the opcode stream, walked as data.

``pickle.load`` runs code: a pickle names functions and classes (``GLOBAL``) and asks for them to
be called (``REDUCE``, ``NEWOBJ``) and their instances updated (``BUILD``). :func:`read_pickle`
walks the opcodes with the standard library's :func:`pickletools.genops` and keeps a stack and a
memo of plain values, but never imports a module or calls anything a pickle names: a ``GLOBAL``
becomes a :class:`GlobalRef` (two strings); a call of a global is looked up in a table of
*reducers* (pure functions of the call's arguments written here, e.g. numpy's array
reconstruction from its raw bytes) or of *classes* whose instances are kept as inert
:class:`PickledObject` records (class name, arguments, ``BUILD`` state) for the caller to take
data from. Anything else is refused with :class:`UnsafePickleError` naming the global, unless
``allow_unknown`` (then it becomes an :class:`Opaque` marker, never resolved, which the caller
must not find in the data it keeps).

Supported: protocols 0-5 except out-of-band buffers and the extension registry; numpy arrays
and dtypes (plain scalar types, either byte order; object and structured dtypes refused), numpy
scalars, ``bytes`` from protocol 0-2 pickles (``_codecs.encode``), sets, ``OrderedDict``.
Python 2 ``str`` (``SHORT_BINSTRING``/``BINSTRING``) comes out as latin-1 text, as
``pickle.load(..., encoding="latin1")`` would give it; array data in it is re-encoded to bytes.
"""

from __future__ import annotations

import dataclasses
import pickletools
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

ARG_OPS = {  # opcodes that push their argument: ints and (Python 2 or 3) strings
    *("INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4"),
    *("STRING", "BINSTRING", "SHORT_BINSTRING"),
    *("UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8"),
}
REFUSED_OPS = {  # opcodes that call or import things by other routes, or need out-of-band data
    "INST": "INST calls a class",
    "OBJ": "OBJ calls a class",
    "EXT1": "the extension registry",
    "EXT2": "the extension registry",
    "EXT4": "the extension registry",
    "NEXT_BUFFER": "out-of-band buffers",
    "READONLY_BUFFER": "out-of-band buffers",
}


class UnsafePickleError(ValueError):
    """A pickle asks for something the reader does not rebuild; the message names it."""


@dataclasses.dataclass(frozen=True)
class GlobalRef:
    """A global a pickle names (``module.name``): two strings, never imported."""

    module: str
    name: str

    def __str__(self) -> str:
        return f"{self.module}.{self.name}"


@dataclasses.dataclass
class PickledObject:
    """An instance of an allowed class, never created: its class, arguments and ``BUILD`` state."""

    cls: GlobalRef
    args: tuple = ()
    state: Any = None


@dataclasses.dataclass
class Opaque:
    """A value made from a global outside the tables (only with ``allow_unknown``)."""

    origin: str


@dataclasses.dataclass
class _PendingArray:
    """numpy's ``_reconstruct`` result before its ``BUILD`` state (shape, dtype, bytes)."""

    array: np.ndarray | None = None


@dataclasses.dataclass
class _PendingDtype:
    """``numpy.dtype(code)`` before its ``BUILD`` state (byte order)."""

    dtype: np.dtype


Reducer = Callable[[tuple], Any]  # a call's arguments -> the value it stands for


def _numpy_reconstruct(args: tuple) -> _PendingArray:
    if not args or args[0] != GlobalRef("numpy", "ndarray"):
        raise UnsafePickleError(f"numpy _reconstruct of {args[:1]!r}, not numpy.ndarray")
    return _PendingArray()


def _numpy_dtype(args: tuple) -> _PendingDtype:
    code = args[0] if args else None
    if not isinstance(code, str):
        raise UnsafePickleError(f"numpy.dtype({code!r}): not a type code")
    dtype = np.dtype(code)
    if dtype.kind not in "biufc" or dtype.fields is not None or dtype.subdtype is not None:
        raise UnsafePickleError(f"numpy.dtype({code!r}): only plain numeric dtypes are read")
    return _PendingDtype(dtype)


def _to_bytes(raw: Any) -> bytes:
    """Array or scalar data as bytes (a Python 2 ``str`` arrives as latin-1 text)."""
    if isinstance(raw, bytes | bytearray):
        return bytes(raw)
    if isinstance(raw, str):
        return raw.encode("latin-1")
    raise UnsafePickleError(f"array data must be bytes, got {type(raw).__name__}")


def _numpy_scalar(args: tuple) -> Any:
    dtype = resolve(args[0])
    if not isinstance(dtype, np.dtype) or len(args) < 2:
        raise UnsafePickleError("numpy scalar needs a dtype and its bytes")
    return np.frombuffer(_to_bytes(args[1]), dtype=dtype, count=1)[0]


def _numpy_frombuffer(args: tuple) -> np.ndarray:
    """numpy's protocol-5 ``_frombuffer(buffer, dtype, shape, order)`` (in-band buffers)."""
    if len(args) != 4:
        raise UnsafePickleError(f"numpy _frombuffer with {len(args)} arguments")
    raw, dtype, shape, order = args
    pending = _PendingArray()
    _build_array(pending, (shape, dtype, order == "F", raw))
    return pending.array


def _codecs_encode(args: tuple) -> bytes:
    if len(args) != 2 or not isinstance(args[0], str) or args[1] not in ("latin1", "latin-1"):
        raise UnsafePickleError(f"_codecs.encode{args!r}: only latin-1 bytes are read")
    return args[0].encode("latin-1")


def _make_set(args: tuple) -> set:
    return set(args[0]) if args else set()


def _ordered_dict(args: tuple) -> dict:
    return dict(args[0]) if args else {}


BASE_REDUCERS: dict[tuple[str, str], Reducer] = {
    ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy", "dtype"): _numpy_dtype,
    ("numpy.core.numeric", "_frombuffer"): _numpy_frombuffer,
    ("numpy._core.numeric", "_frombuffer"): _numpy_frombuffer,
    ("numpy.core.multiarray", "scalar"): _numpy_scalar,
    ("numpy._core.multiarray", "scalar"): _numpy_scalar,
    ("_codecs", "encode"): _codecs_encode,
    ("__builtin__", "set"): _make_set,
    ("builtins", "set"): _make_set,
    ("__builtin__", "frozenset"): lambda a: frozenset(_make_set(a)),
    ("builtins", "frozenset"): lambda a: frozenset(_make_set(a)),
    ("collections", "OrderedDict"): _ordered_dict,
}
RECONSTRUCTORS = {("copy_reg", "_reconstructor"), ("copyreg", "_reconstructor")}


def _build_array(pending: _PendingArray, state: Any) -> None:
    """numpy's ``ndarray.__setstate__``: ``(version, shape, dtype, is_fortran, raw)``."""
    if not isinstance(state, tuple) or len(state) not in (4, 5):
        raise UnsafePickleError("numpy array state is not (version, shape, dtype, fortran, data)")
    shape, dtype, fortran, raw = state[-4:]
    dtype = resolve(dtype)
    if not isinstance(dtype, np.dtype):
        raise UnsafePickleError(f"numpy array of dtype {dtype!r} (object arrays are not read)")
    shape = tuple(int(s) for s in shape)
    data = _to_bytes(raw)
    count = int(np.prod(shape, dtype=np.int64))
    if len(data) != count * dtype.itemsize:
        raise UnsafePickleError(
            f"numpy array {shape} {dtype} needs {count * dtype.itemsize} bytes, has {len(data)}"
        )
    flat = np.frombuffer(data, dtype=dtype, count=count)
    pending.array = flat.reshape(shape, order="F" if fortran else "C").copy()


def _build_dtype(pending: _PendingDtype, state: Any) -> None:
    """numpy's ``dtype.__setstate__``: only the byte order of a plain dtype is taken."""
    if not isinstance(state, tuple) or len(state) < 5:
        raise UnsafePickleError(f"numpy dtype state {state!r} not understood")
    order, subarray, names, fields = state[1], state[2], state[3], state[4]
    if subarray is not None or names is not None or fields is not None:
        raise UnsafePickleError("structured numpy dtypes are not read")
    if order == ">":
        pending.dtype = pending.dtype.newbyteorder(">")
    elif order == "<":
        pending.dtype = pending.dtype.newbyteorder("<")


def resolve(value: Any) -> Any:
    """``value`` with numpy placeholders replaced by their arrays and dtypes (containers copied)."""
    if isinstance(value, _PendingArray):
        if value.array is None:
            raise UnsafePickleError("a numpy array without its data")
        return value.array
    if isinstance(value, _PendingDtype):
        return value.dtype
    if isinstance(value, list):
        return [resolve(v) for v in value]
    if isinstance(value, tuple):
        return tuple(resolve(v) for v in value)
    if isinstance(value, dict):
        return {resolve(k): resolve(v) for k, v in value.items()}
    if isinstance(value, PickledObject):
        return PickledObject(value.cls, resolve(value.args), resolve(value.state))
    return value


class _Reader:
    """The pickle machine's stack, mark stack and memo over inert values."""

    def __init__(
        self,
        reducers: Mapping[tuple[str, str], Reducer],
        classes: set[tuple[str, str]],
        persistent_load: Callable[[Any], Any] | None,
        allow_unknown: bool,
    ) -> None:
        self.reducers = {**BASE_REDUCERS, **reducers}
        self.classes = classes
        self.persistent_load = persistent_load
        self.allow_unknown = allow_unknown
        self.stack: list[Any] = []
        self.marks: list[list[Any]] = []
        self.memo: dict[int, Any] = {}

    def pop_mark(self) -> list[Any]:
        items, self.stack = self.stack, self.marks.pop()
        return items

    def refuse(self, what: str) -> Opaque:
        if self.allow_unknown:
            return Opaque(what)
        raise UnsafePickleError(
            f"the pickle asks for {what}, which is not data this reader rebuilds (it never "
            "imports or calls what a pickle names)"
        )

    def call(self, func: Any, args: Any) -> Any:
        """``REDUCE``/``NEWOBJ``: a reducer's value, an inert object, or a refusal."""
        if isinstance(func, Opaque):
            return func
        if not isinstance(func, GlobalRef):
            return self.refuse(f"a call of {type(func).__name__}")
        if not isinstance(args, tuple):
            return self.refuse(f"{func} called with {type(args).__name__} arguments")
        key = (func.module, func.name)
        if key in self.reducers:
            return self.reducers[key](args)
        if key in RECONSTRUCTORS and args and isinstance(args[0], GlobalRef | Opaque):
            return self.call(args[0], ())  # copy_reg._reconstructor(cls, object, None)
        if key in self.classes:
            return PickledObject(func, args)
        return self.refuse(str(func))

    def build(self, obj: Any, state: Any) -> None:
        """``BUILD``: set the state of an array, dtype or inert object."""
        if isinstance(obj, _PendingArray):
            _build_array(obj, state)
        elif isinstance(obj, _PendingDtype):
            _build_dtype(obj, state)
        elif isinstance(obj, PickledObject):
            obj.state = state
        elif isinstance(obj, dict) and isinstance(state, dict):
            pass  # an OrderedDict's attributes (torch's _metadata): not data
        elif not isinstance(obj, Opaque):
            self.refuse(f"BUILD of a {type(obj).__name__}")

    def step(self, name: str, arg: Any) -> None:
        """Apply one opcode."""
        s = self.stack
        if name in REFUSED_OPS:
            raise UnsafePickleError(f"opcode {name} ({REFUSED_OPS[name]}) is not read")
        if name in ("PROTO", "FRAME", "STOP"):
            return
        if name == "MARK":
            self.marks.append(s)
            self.stack = []
        elif name == "POP":
            s.pop()
        elif name == "POP_MARK":
            self.pop_mark()
        elif name == "DUP":
            s.append(s[-1])
        elif name in ("PUT", "BINPUT", "LONG_BINPUT"):
            self.memo[int(arg)] = s[-1]
        elif name == "MEMOIZE":
            self.memo[len(self.memo)] = s[-1]
        elif name in ("GET", "BINGET", "LONG_BINGET"):
            s.append(self.memo[int(arg)])
        elif name == "NONE":
            s.append(None)
        elif name in ("NEWTRUE", "NEWFALSE"):
            s.append(name == "NEWTRUE")
        elif name in ARG_OPS:
            s.append(arg)
        elif name in ("FLOAT", "BINFLOAT"):
            s.append(float(arg))
        elif name in ("BINBYTES", "SHORT_BINBYTES", "BINBYTES8"):
            s.append(bytes(arg))
        elif name == "BYTEARRAY8":
            s.append(bytearray(arg))
        elif name == "EMPTY_LIST":
            s.append([])
        elif name == "APPEND":
            value = s.pop()
            s[-1].append(value)
        elif name == "APPENDS":
            items = self.pop_mark()
            self.stack[-1].extend(items)
        elif name == "LIST":
            items = self.pop_mark()
            self.stack.append(items)
        elif name == "EMPTY_TUPLE":
            s.append(())
        elif name == "TUPLE":
            items = self.pop_mark()
            self.stack.append(tuple(items))
        elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
            n = int(name[-1])
            items = tuple(s[-n:])
            del s[-n:]
            s.append(items)
        elif name == "EMPTY_DICT":
            s.append({})
        elif name == "DICT":
            items = self.pop_mark()
            self.stack.append(dict(zip(items[::2], items[1::2], strict=True)))
        elif name == "SETITEM":
            value, key = s.pop(), s.pop()
            s[-1][_hashable(key)] = value
        elif name == "SETITEMS":
            items = self.pop_mark()
            target = self.stack[-1]
            for k, v in zip(items[::2], items[1::2], strict=True):
                target[_hashable(k)] = v
        elif name == "EMPTY_SET":
            s.append(set())
        elif name == "ADDITEMS":
            items = self.pop_mark()
            self.stack[-1].update(_hashable(i) for i in items)
        elif name == "FROZENSET":
            items = self.pop_mark()
            self.stack.append(frozenset(_hashable(i) for i in items))
        elif name == "GLOBAL":
            module, _, attr = arg.partition(" ")
            s.append(GlobalRef(module, attr))
        elif name == "STACK_GLOBAL":
            attr, module = s.pop(), s.pop()
            if not (isinstance(module, str) and isinstance(attr, str)):
                raise UnsafePickleError("STACK_GLOBAL with non-string names")
            s.append(GlobalRef(module, attr))
        elif name in ("REDUCE", "NEWOBJ"):
            args = s.pop()
            s.append(self.call(s.pop(), args))
        elif name == "NEWOBJ_EX":
            kwargs, args = s.pop(), s.pop()
            if kwargs:
                s.pop()
                s.append(self.refuse("NEWOBJ_EX with keyword arguments"))
            else:
                s.append(self.call(s.pop(), args))
        elif name == "BUILD":
            state = s.pop()
            self.build(s[-1], state)
        elif name in ("PERSID", "BINPERSID"):
            pid = arg if name == "PERSID" else s.pop()
            if self.persistent_load is None:
                raise UnsafePickleError("a persistent id, which this file type does not use")
            s.append(self.persistent_load(resolve(pid)))
        else:
            raise UnsafePickleError(f"opcode {name} is not read")


def _hashable(key: Any) -> Any:
    if isinstance(key, _PendingArray | _PendingDtype | PickledObject | list | dict | set):
        raise UnsafePickleError(f"a {type(key).__name__} used as a dict key or set item")
    return key


def read_pickle(
    data: bytes,
    *,
    reducers: Mapping[tuple[str, str], Reducer] | None = None,
    classes: set[tuple[str, str]] | None = None,
    persistent_load: Callable[[Any], Any] | None = None,
    allow_unknown: bool = False,
) -> Any:
    """The value a pickle ``data`` describes, rebuilt from its opcodes without unpickling.

    ``reducers`` adds pure functions for calls of named globals, ``classes`` the globals whose
    instances come back as :class:`PickledObject`; ``persistent_load`` maps a persistent id
    (torch's storages) to a value. Raises :class:`UnsafePickleError` for anything else (with
    ``allow_unknown``: an :class:`Opaque` marker) and for malformed streams.
    """
    reader = _Reader(reducers or {}, classes or set(), persistent_load, allow_unknown)
    try:
        for opcode, arg, _ in pickletools.genops(data):
            reader.step(opcode.name, arg)
    except UnsafePickleError:
        raise
    except (ValueError, IndexError, KeyError, TypeError, AttributeError) as exc:
        raise UnsafePickleError(f"malformed pickle ({type(exc).__name__}: {exc})") from exc
    if len(reader.stack) != 1 or reader.marks:
        raise UnsafePickleError("malformed pickle (the stack does not end with one value)")
    return resolve(reader.stack[0])
