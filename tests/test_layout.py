"""The package's layout: old module paths keep importing for one release, each warning with the new path.

Every module path the README or docs named before the package mirrored the pipeline still imports, as the new
module itself (every name, private ones too), and warns once with a ``DeprecationWarning`` that names the new
path, attributed to the importing line (so Python's default filters show it in a user's script).
"""

from __future__ import annotations

import subprocess
import sys

import pytest

#: Old path → new path.
MOVED = {
    "pushtorch.shapes": "pushtorch.objects.shapes",
    "pushtorch.metrics": "pushtorch.evaluation.metrics",
    "pushtorch.likelihood": "pushtorch.evaluation.likelihood",
    "pushtorch.baselines": "pushtorch.evaluation.baselines",
    "pushtorch.cli": "pushtorch.apps.cli",
    "pushtorch.config_check": "pushtorch.apps.config_check",
    "pushtorch.simulate": "pushtorch.apps.simulate",
    "pushtorch.train": "pushtorch.apps.train",
    "pushtorch.predict_cli": "pushtorch.apps.predict",
    "pushtorch.collect": "pushtorch.apps.collect",
    "pushtorch.predict": "pushtorch.prediction",
}


@pytest.mark.parametrize("old, new", list(MOVED.items()))
def test_an_old_module_path_imports_the_new_module_and_warns_where_it_is_imported(tmp_path, old, new):
    script = tmp_path / "user_script.py"
    script.write_text(f"import importlib, {old}\n"
                      f"import sys\n"
                      f"print(sys.modules['{old}'] is importlib.import_module('{new}'))\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "True"
    assert f"user_script.py:1: DeprecationWarning: {old} has moved to {new}" in result.stderr


def test_the_library_itself_imports_no_old_path():
    probe = ("import warnings; warnings.simplefilter('error', DeprecationWarning); "
             "import pushtorch.objects, pushtorch.evaluation.metrics, pushtorch.evaluation.likelihood, "
             "pushtorch.evaluation.baselines, pushtorch.objects.shapes, pushtorch.distribution, "
             "pushtorch.models.motion, pushtorch.prediction, pushtorch.apps.cli, pushtorch.experiments.common")
    subprocess.run([sys.executable, "-c", probe], check=True)


@pytest.mark.parametrize("app", ["pushtorch", "pushtorch.simulate", "pushtorch.train", "pushtorch.predict",
                                 "pushtorch.predict_cli"])
def test_the_documented_commands_run_the_apps_without_a_warning(app):
    result = subprocess.run([sys.executable, "-W", "default", "-m", app, "--help"], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0 and "Configuration groups" in result.stdout, result.stderr[-2000:]
    assert "DeprecationWarning" not in result.stderr


def _imported_private_names() -> list[str]:
    """``module: from X import _name`` for every import of a private name from another package or top-level
    module (a package may use its own privates: ``pushtorch.kde.*`` importing ``pushtorch.kde.fused._x``)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "pushtorch"
    found = []
    for path in root.rglob("*.py"):
        module = ".".join(("pushtorch", *path.relative_to(root).with_suffix("").parts)).removesuffix(".__init__")
        package = module.rsplit(".", 1)[0] if path.name != "__init__.py" else module
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pushtorch"):
                source_package = node.module if (root / Path(*node.module.split(".")[1:]) / "__init__.py").exists() \
                    else node.module.rsplit(".", 1)[0]
                same = source_package == package and package != "pushtorch"
                found += [f"{module}: from {node.module} import {a.name}" for a in node.names
                          if a.name.startswith("_") and not a.name.startswith("__") and not same]
    return found


def test_no_module_imports_another_packages_private_names():
    assert _imported_private_names() == []
