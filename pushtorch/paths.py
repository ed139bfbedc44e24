"""Names that become file names, checked in one place, so nothing is written outside its folder.

No paper section: the experiments cache pushes, models and predictions under the run folder by names made
from configuration values (object, prior and experiment names). A name such as ``a/../../outside/p`` would
otherwise place a file outside the run folder; :func:`safe_name` refuses it and :func:`contained_path`
joins only checked names and verifies the result stays inside its base folder.
"""

from __future__ import annotations

import re
from pathlib import Path

from pushtorch.errors import UnsafeNameError

__all__ = ["SAFE_NAME", "contained_path", "safe_name", "sanitised_name"]

#: A plain file-name part: starts with a letter or digit, then letters, digits, ``_``, ``.`` and ``-``.
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: Longest name accepted (file systems allow 255 bytes; suffixes are added to names).
MAX_NAME_LENGTH = 128


def safe_name(name: object, what: str = "name") -> str:
    """``name`` if it is a plain file-name part (:data:`SAFE_NAME`, no ``..``, at most 128 characters).

    Raises:
        UnsafeNameError: anything else, naming ``what`` the name is for.
    """
    if not isinstance(name, str):
        raise UnsafeNameError(f"{what} must be a string, got {type(name).__name__} {name!r}")
    if not SAFE_NAME.match(name) or ".." in name or len(name) > MAX_NAME_LENGTH:
        raise UnsafeNameError(
            f"{what} {name!r} cannot be part of a file name: use letters, digits, '_', '.' and '-' only, "
            f"starting with a letter or digit, no '..', at most {MAX_NAME_LENGTH} characters"
        )
    return name


def sanitised_name(text: str, fallback: str = "object") -> str:
    """A safe name made from free text (e.g. a mesh file's stem): every run of other characters becomes
    ``_``; leading separators are dropped; ``fallback`` if nothing is left."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", text).replace("..", "_").lstrip("_.-")[:MAX_NAME_LENGTH]
    return name or fallback


def contained_path(base: str | Path, *parts: str, what: str = "name") -> Path:
    """``base / part / ...`` after checking every part with :func:`safe_name` (a final suffix such as
    ``.npz`` may be part of the last one); the result is verified to lie inside ``base``.

    Raises:
        UnsafeNameError: a part that is not a plain name, or a result outside ``base``.
    """
    base = Path(base)
    path = base.joinpath(*(safe_name(part, what) for part in parts))
    resolved_base = base.resolve()
    if not path.resolve().is_relative_to(resolved_base):  # e.g. a symlink inside base pointing out
        raise UnsafeNameError(f"{path} lies outside {resolved_base}")
    return path
