"""Identifiers that may become file names (clip ids, step names), and paths built from data.

One rule for every identifier that data supplies and code may turn into a path:

- characters ``A-Z a-z 0-9 . _ -`` only (no path separator, no space, no ``:``);
- the first character is a letter, a digit or ``_`` (never ``.``, so no hidden files and no
  ``.``/``..``; never ``-``, so an id is never read as a command-line flag);
- no ``..`` anywhere;
- at most :data:`MAX_ID_LENGTH` characters.

:func:`id_problems` lists what is wrong with a value (for row validators), :func:`validate_id`
raises :class:`InvalidIdError`, :func:`sanitize_id` turns any text (a file stem) into a valid id.
:func:`path_under` is the one helper that builds a path from data: it resolves the result and
raises :class:`PathEscapeError` unless it lies under its root.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from egosim.schemas.base import SchemaError

MAX_ID_LENGTH = 128  # longest identifier (well under every filesystem's 255-byte name limit)
_ID_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]*")
_BAD_CHARS_RE = re.compile(r"[^A-Za-z0-9._-]+")


class InvalidIdError(SchemaError, ValueError):
    """A clip id or step name breaks the identifier rule; the message quotes it."""


class PathEscapeError(SchemaError, ValueError):
    """A path built from data would lie outside the folder it must stay under."""


def id_problems(value: object, kind: str = "clip id") -> list[str]:
    """Every way ``value`` breaks the identifier rule (empty when it is a valid id)."""
    if not isinstance(value, str):
        return [f"{kind} must be a string, got {type(value).__name__}"]
    problems = []
    if not value:
        problems.append(f"{kind} is empty")
    elif not _ID_RE.fullmatch(value):
        problems.append(
            f"{kind} {value[:80]!r} must use only A-Z a-z 0-9 . _ - and start with a letter, "
            "digit or _"
        )
    if ".." in value:
        problems.append(f"{kind} {value[:80]!r} contains '..'")
    if len(value) > MAX_ID_LENGTH:
        problems.append(f"{kind} is {len(value)} characters long, at most {MAX_ID_LENGTH}")
    return problems


def validate_id(value: object, kind: str = "clip id") -> str:
    """Return ``value`` if it is a valid identifier, else raise :class:`InvalidIdError`."""
    problems = id_problems(value, kind)
    if problems:
        raise InvalidIdError("; ".join(problems))
    return value  # type: ignore[return-value]  (a str: checked above)


def short_hash(text: str, length: int = 8) -> str:
    """The first ``length`` hex digits of the SHA-256 of ``text`` (to make names unique)."""
    return hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:length]


def sanitize_id(text: str, suffix: str = "") -> str:
    """A valid identifier made from ``text`` (e.g. a file stem), ending with ``suffix``.

    Runs of other characters become ``_``, ``..`` becomes ``_``, a leading ``.`` or ``-`` gets a
    ``_`` in front; the text is cut so that the id with ``suffix`` fits :data:`MAX_ID_LENGTH`.
    A text with nothing usable becomes ``clip``. ``suffix`` must itself be id characters.
    """
    cleaned = _BAD_CHARS_RE.sub("_", text)
    while ".." in cleaned:
        cleaned = cleaned.replace("..", "_")
    if not cleaned.strip("_"):
        cleaned = "clip"
    if not _ID_RE.fullmatch(cleaned[0]):
        cleaned = "_" + cleaned
    cleaned = cleaned[: MAX_ID_LENGTH - len(suffix)]
    if cleaned.endswith(".") and suffix.startswith("."):
        cleaned = cleaned[:-1] + "_"
    return validate_id(cleaned + suffix, "sanitized id")


def path_under(root: str | Path, *parts: str) -> Path:
    """``root / parts...``, refused with :class:`PathEscapeError` if it resolves outside ``root``.

    Use for every path whose name comes from data (clip ids, step names). Symbolic links are
    followed, so a link under ``root`` that points elsewhere counts as outside.
    """
    for part in parts:
        if not part or Path(part).is_absolute():
            raise PathEscapeError(f"path part {part!r} under {root} is empty or absolute")
    joined = Path(root).joinpath(*parts)
    base = Path(root).resolve()
    target = joined.resolve()
    if target != base and not target.is_relative_to(base):
        raise PathEscapeError(f"{joined} resolves outside {root}")
    return joined
