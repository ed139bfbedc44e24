"""Old module paths kept importable for one release: each warns once with a ``DeprecationWarning`` naming
the new path, then stands for the new module (the same module object: every name, private ones too).

No paper section: the package was laid out anew to mirror the pipeline (``docs/architecture.md``).
"""

from __future__ import annotations

import importlib
import sys
import warnings

__all__ = ["alias_module"]


def alias_module(old: str, new: str) -> None:
    """Make the module ``old`` (being imported) stand for ``new``, warning at the importer's line.

    Call it at the top level of the old module's file. The warning is attributed to the importer's line, so
    Python's default filters show it where a user's script imports the old path.
    """
    # 1: this function, 2: the old module, 3: its importer (warnings skips the import machinery's frames)
    warnings.warn(f"{old} has moved to {new}: import it from there (the old path goes in the next release)",
                  DeprecationWarning, stacklevel=3)
    sys.modules[old] = importlib.import_module(new)
