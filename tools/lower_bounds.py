"""Print a pip constraints file pinning every dependency of pyproject.toml to its declared lower bound.

`make check-install` installs the wheel with these constraints, so a declared lower bound is always a version
that CI has run (README, "Set-up"). Requirements whose environment marker does not hold here are left out.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

from packaging.requirements import Requirement


def lower_bound_pins(pyproject: Path, extras: tuple[str, ...] = ()) -> list[str]:
    """``name==X`` for every requirement (and those of ``extras``) that declares ``>=X`` and applies here."""
    project = tomllib.loads(pyproject.read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in extras:
        requirements += project["optional-dependencies"][extra]
    pins = []
    for text in requirements:
        requirement = Requirement(text)
        if requirement.marker is not None and not requirement.marker.evaluate():
            continue
        lower = [spec.version for spec in requirement.specifier if spec.operator == ">="]
        if not lower:
            sys.exit(f"{requirement.name} declares no lower bound (>=) in {pyproject}")
        pins.append(f"{requirement.name}=={lower[0]}")
    return pins


if __name__ == "__main__":
    print("\n".join(lower_bound_pins(Path(__file__).resolve().parents[1] / "pyproject.toml", tuple(sys.argv[1:]))))
