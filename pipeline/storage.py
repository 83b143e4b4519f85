"""Where shards and run records live: local folders or fsspec URLs (``s3://``, ``gs://``, ...).

A *location* is a local :class:`~pathlib.Path` or a URL string. :func:`location` turns what a
user typed into one: a plain path or a ``file://`` URL becomes a ``Path`` (so local runs behave
exactly as before), any other URL stays a string and is reached through the fsspec filesystem
of its protocol (:func:`filesystem`). Every other function here takes either kind.

Commits (see docs/design.md, "Remote storage"). A writer never writes under the final name:

- local paths: a temporary file ``NAME.tmp-XXXXXXXX`` in the same folder, renamed into place
  (``os.replace`` is atomic), as shards always were;
- other filesystems (object stores have no atomic rename): a temporary key
  ``NAME.tmp-XXXXXXXX``, then (1) the completion marker ``NAME.complete`` of an older version is
  deleted, (2) the temporary key is moved to ``NAME`` (a server-side copy on S3 and GCS), (3) the
  marker is written, holding the size of ``NAME``, (4) the temporary key is gone with the move.

A remote file counts as committed (:func:`is_committed`) only when its marker exists and names
its size: a write killed at any step leaves a temporary key or a key without a matching marker,
and listings (:func:`list_files`), resume and ``egosim check`` on a folder ignore both. A file
named explicitly (``egosim check s3://b/x.parquet``) is read whatever its marker says; shards
carry content hashes that catch a damaged one.

Options of a filesystem (endpoint, credentials) come from fsspec's own configuration: the
``FSSPEC_<PROTOCOL>_<OPTION>`` environment variables (``FSSPEC_S3_ENDPOINT_URL=http://...``)
or a JSON file in ``~/.config/fsspec/``. Dask workers inherit them from the environment.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path, PurePosixPath
from typing import IO, Any

TMP_MARKER = ".tmp-"  # infix of temporary files and keys: NAME.tmp-XXXXXXXX
COMPLETE_SUFFIX = ".complete"  # completion marker of a remote file: NAME.complete
CACHE_ENV = "EGOSIM_CACHE"  # folder of local copies of remote inputs (default ~/.cache/egosim)

Location = Path | str  # a local path, or a URL with a protocol other than file://
# Protocols of object stores (fsspec names): no folders to create, no atomic rename.
OBJECT_STORES = frozenset({"s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "oss"})


class StorageError(OSError):
    """A location cannot be used (bad URL, unknown protocol, a part that escapes its root)."""


def is_url(value: str | Path) -> bool:
    """True for a URL with a protocol other than ``file`` (``s3://b/k``, ``memory://x``)."""
    if isinstance(value, Path):
        return False
    scheme, sep, _ = str(value).partition("://")
    return bool(sep) and scheme.isidentifier() and scheme.lower() != "file"


def location(value: str | Path) -> Location:
    """The location a user gave: a ``Path`` for plain paths and ``file://``, else the URL.

    Raises :class:`StorageError` for a URL whose protocol fsspec does not know (or whose
    filesystem package is not installed), naming the URL.
    """
    if isinstance(value, Path):
        return value
    text = str(value)
    if text.startswith("file://"):
        return Path(text[len("file://") :])
    if not is_url(text):
        return Path(text)
    filesystem(text)  # fail now, not in the middle of a run
    scheme, _, rest = text.partition("://")
    return f"{scheme}://{rest.rstrip('/')}"


def filesystem(loc: Location) -> tuple[Any, str]:
    """``(fsspec filesystem, path inside it)`` of a location."""
    import fsspec.core

    try:
        fs, path = fsspec.core.url_to_fs(str(loc))
    except (ImportError, ValueError) as exc:  # unknown protocol, or its package missing
        raise StorageError(f"{loc}: no usable fsspec filesystem ({exc})") from exc
    # Other processes (Dask workers) write here too: never answer from a cached listing.
    fs.invalidate_cache()
    return fs, path


def is_local(loc: Location) -> bool:
    """True when ``loc`` is a local path (atomic rename, no completion markers)."""
    return isinstance(loc, Path)


def _check_part(part: str, base: Location) -> str:
    if not part or part in (".", "..") or "/" in part or "\\" in part or "\0" in part:
        raise StorageError(
            f"path part {part!r} under {base} is empty, '.', '..' or has a separator"
        )
    return part


def join(base: Location, *parts: str) -> Location:
    """``base`` / ``parts``; each part is one name (no separator, not ``..``), so the result
    stays under ``base`` (:class:`StorageError` otherwise)."""
    for part in parts:
        _check_part(part, base)
    if isinstance(base, Path):
        return base.joinpath(*parts)
    return "/".join([base.rstrip("/"), *parts])


def name(loc: Location) -> str:
    """The last part of a location (``shard-00000.parquet``)."""
    return loc.name if isinstance(loc, Path) else PurePosixPath(loc.partition("://")[2]).name


def parent(loc: Location) -> Location:
    """The folder that holds ``loc``."""
    if isinstance(loc, Path):
        return loc.parent
    scheme, _, rest = loc.partition("://")
    return f"{scheme}://{PurePosixPath(rest).parent}"


def with_name(loc: Location, new_name: str) -> Location:
    """``loc`` with its last part replaced by ``new_name`` (one name, checked)."""
    return join(parent(loc), _check_part(new_name, loc))


def marker_of(loc: Location) -> Location:
    """The completion marker of a remote file (``NAME.complete``)."""
    return with_name(loc, name(loc) + COMPLETE_SUFFIX)


def exists(loc: Location) -> bool:
    """True when a file is stored at ``loc``, committed or not (see :func:`is_committed`)."""
    if isinstance(loc, Path):
        return loc.is_file()
    fs, path = filesystem(loc)
    return bool(fs.isfile(path))


def is_dir(loc: Location) -> bool:
    """True when ``loc`` is a folder (on object stores: a prefix with keys under it)."""
    if isinstance(loc, Path):
        return loc.is_dir()
    fs, path = filesystem(loc)
    return bool(fs.isdir(path))


def size(loc: Location) -> int:
    """Size in bytes of the file at ``loc``."""
    if isinstance(loc, Path):
        return loc.stat().st_size
    fs, path = filesystem(loc)
    return int(fs.size(path))


def is_committed(loc: Location) -> bool:
    """True when a complete write is stored at ``loc`` (see the module doc).

    Local: the file exists (renames are atomic). Remote: the file exists and its completion
    marker names its size.
    """
    if isinstance(loc, Path):
        return loc.is_file()
    fs, path = filesystem(loc)
    _, marker = filesystem(marker_of(loc))
    try:
        recorded = json.loads(fs.cat_file(marker))["size"]
        return int(fs.size(path)) == int(recorded)
    except (FileNotFoundError, ValueError, KeyError, TypeError):
        return False


def is_object_store(loc: Location) -> bool:
    """True for a URL of an object store (keys, no folders: nothing to create before a write)."""
    return is_url(loc) and str(loc).partition("://")[0].lower() in OBJECT_STORES


def makedirs(loc: Location) -> None:
    """Create the folder ``loc`` and its parents.

    A no-op on object stores: they have no folders, and creating one there would create a
    bucket; a missing bucket fails at the first write instead, with the store's message.
    """
    if isinstance(loc, Path):
        loc.mkdir(parents=True, exist_ok=True)
    elif not is_object_store(loc):
        fs, path = filesystem(loc)
        fs.makedirs(path, exist_ok=True)


def remove(loc: Location) -> None:
    """Delete the file at ``loc`` (and its completion marker, first); absent files are fine."""
    if isinstance(loc, Path):
        loc.unlink(missing_ok=True)
        return
    fs, path = filesystem(loc)
    for target in (filesystem(marker_of(loc))[1], path):
        with contextlib.suppress(FileNotFoundError):
            fs.rm_file(target)


def open_read(loc: Location) -> IO[bytes]:
    """A binary file object reading ``loc`` (seekable: pyarrow reads Parquet footers from it)."""
    if isinstance(loc, Path):
        import pyarrow as pa

        return pa.OSFile(str(loc), "rb")  # pyarrow's native file: 2x faster Parquet reads
    fs, path = filesystem(loc)
    return fs.open(path, "rb")


def read_text(loc: Location) -> str:
    """The text (UTF-8) stored at ``loc``."""
    with open_read(loc) as f:
        return f.read().decode("utf-8")


def _temporary(loc: Location) -> Location:
    return with_name(loc, f"{name(loc)}{TMP_MARKER}{uuid.uuid4().hex[:8]}")


@contextlib.contextmanager
def atomic_write(loc: Location) -> Iterator[IO[bytes]]:
    """Yield a binary file whose bytes appear at ``loc`` only when the block ends without error.

    See the module doc for how each kind of location commits. On an error the temporary file
    or key is deleted and ``loc`` keeps what it held before.
    """
    tmp = _temporary(loc)
    makedirs(parent(loc))
    if isinstance(loc, Path):
        assert isinstance(tmp, Path)  # same kind as loc
        import pyarrow as pa

        try:
            with pa.OSFile(str(tmp), "wb") as f:
                yield f
            os.replace(tmp, loc)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return
    fs, tmp_path = filesystem(tmp)
    body_done = False  # errors after the caller's block are the store's: name the location
    try:
        with fs.open(tmp_path, "wb") as f:
            yield f
            body_done = True
        commit(tmp, loc)
    except BaseException as exc:
        with contextlib.suppress(Exception):
            fs.rm_file(tmp_path)
        if body_done and isinstance(exc, OSError) and not isinstance(exc, StorageError):
            raise StorageError(f"{loc}: cannot write ({exc})") from exc
        raise


def commit(tmp: Location, loc: Location) -> None:
    """Move the written temporary ``tmp`` to ``loc`` on a remote store, marker last.

    The steps are spelled out in the module doc; a crash between any two of them leaves
    ``loc`` uncommitted (no marker, or a marker of another size), never a wrong committed file.
    """
    fs, path = filesystem(loc)
    _, tmp_path = filesystem(tmp)
    _, marker = filesystem(marker_of(loc))
    with contextlib.suppress(FileNotFoundError):
        fs.rm_file(marker)
    fs.mv(tmp_path, path)
    write_marker(fs, marker, int(fs.size(path)))


def write_marker(fs: Any, marker: str, nbytes: int) -> None:
    """Write the completion marker ``marker`` naming a committed file of ``nbytes`` bytes."""
    fs.pipe_file(marker, json.dumps({"size": nbytes}).encode())


def write_text_atomic(loc: Location, text: str) -> None:
    """Write ``text`` (UTF-8) to ``loc`` through :func:`atomic_write`."""
    with atomic_write(loc) as f:
        f.write(text.encode("utf-8"))


def _walk(folder: Location, recursive: bool) -> list[Location]:
    """Every file under ``folder`` (only its own files unless ``recursive``), sorted."""
    if isinstance(folder, Path):
        found = folder.rglob("*") if recursive else folder.iterdir()
        return sorted(p for p in found if p.is_file())
    fs, path = filesystem(folder)
    if recursive:
        keys = fs.find(path)
    else:
        keys = [e["name"] for e in fs.ls(path, detail=True) if e.get("type") == "file"]
    return [fs.unstrip_protocol(key) for key in sorted(keys)]


def list_files(folder: Location, pattern: str = "*", recursive: bool = False) -> list[Location]:
    """Committed files under ``folder`` whose name matches ``pattern`` (fnmatch), sorted.

    Temporary files and keys, completion markers and (remote) files without a matching marker
    are left out: an interrupted write is never listed.
    """
    from fnmatch import fnmatchcase

    out = []
    for loc in _walk(folder, recursive):
        file_name = name(loc)
        if TMP_MARKER in file_name or file_name.endswith(COMPLETE_SUFFIX):
            continue
        if fnmatchcase(file_name, pattern) and (is_local(loc) or is_committed(loc)):
            out.append(loc)
    return out


def remove_temporaries(folder: Location) -> list[Location]:
    """Delete every temporary file or key (``*.tmp-*``) under ``folder``; returns them.

    Call only while no other writer uses ``folder`` (the runner holds its run lock).
    """
    if not is_dir(folder):
        return []
    removed = [
        loc
        for loc in _walk(folder, recursive=True)
        if TMP_MARKER in name(loc) and not (isinstance(loc, Path) and loc.is_symlink())
    ]
    for loc in removed:
        if isinstance(loc, Path):
            loc.unlink(missing_ok=True)
        else:
            fs, path = filesystem(loc)
            with contextlib.suppress(FileNotFoundError):
                fs.rm_file(path)
    return removed


def cache_dir() -> Path:
    """Local folder for copies of remote inputs and run locks of remote outputs.

    ``$EGOSIM_CACHE`` when set, else ``$XDG_CACHE_HOME/egosim`` or ``~/.cache/egosim``.
    """
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "egosim"


def url_key(url: str) -> str:
    """A short stable folder name for a URL (first 16 hex digits of its SHA-256)."""
    return hashlib.sha256(url.encode()).hexdigest()[:16]


def scratch_dir(out: Location) -> Path:
    """The local folder of a run's own files (its lock, its log) for run folder ``out``.

    ``out`` itself when it is local; for a remote run ``CACHE/runs/<url key>`` on this machine.
    """
    if isinstance(out, Path):
        return out
    return cache_dir() / "runs" / url_key(str(out))


def upload(local: Path, loc: Location) -> None:
    """Copy the local file ``local`` to ``loc`` through :func:`atomic_write` (no-op if equal)."""
    if isinstance(loc, Path) and loc.resolve() == local.resolve():
        return
    with local.open("rb") as src, atomic_write(loc) as dst:
        while chunk := src.read(1 << 20):
            dst.write(chunk)


def local_copy(url: str, cache: Path | None = None) -> Path:
    """Download the file or folder at ``url`` into the local cache; returns the local copy.

    For readers that need a local file (PyAV, OpenCV, pycolmap, h5py). The copy lives in
    ``CACHE/inputs/<url key>/<name>``; a file already there with the remote size (and, when the
    store reports one, modification time) is kept, so a re-run downloads nothing and its input
    fingerprints (path, size, time) stay the same. Every file is downloaded to a temporary name
    and renamed. Raises :class:`FileNotFoundError` naming the URL when nothing is there.
    """
    fs, root = filesystem(url)
    dest = (cache or cache_dir()) / "inputs" / url_key(url) / _check_part(name(url), url)
    if fs.isfile(root):
        pairs = [(root, dest)]
    elif fs.isdir(root):
        pairs = []
        for key in sorted(fs.find(root)):
            rel = PurePosixPath(str(key)).relative_to(PurePosixPath(root.rstrip("/")))
            pairs.append((key, join(dest, *rel.parts)))
    else:
        raise FileNotFoundError(f"{url}: no file or folder there")
    for key, target in pairs:
        assert isinstance(target, Path)  # joined under a local Path
        info = fs.info(key)
        mtime = _modified(fs, key)
        same_size = target.is_file() and target.stat().st_size == info["size"]
        if same_size and (mtime is None or abs(target.stat().st_mtime - mtime) < 1e-3):
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f"{target.name}{TMP_MARKER}{uuid.uuid4().hex[:8]}")
        try:
            fs.get_file(key, str(tmp))
            if mtime is not None:
                os.utime(tmp, (mtime, mtime))
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    return dest


def _modified(fs: Any, key: str) -> float | None:
    """The store's modification time of ``key`` (POSIX seconds), or None when it has none."""
    try:
        return float(fs.modified(key).timestamp())
    except (NotImplementedError, AttributeError, FileNotFoundError, TypeError, ValueError):
        return None
