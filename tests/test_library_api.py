"""pushtorch as a library (issue 23, first pieces): the public face and reproducible results by default.

The README's "Using it from your own code" example is run as written (smaller: 20 pushes per action, its
run folders in a temporary directory) in two fresh processes, which must print identical numbers.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _readme_example(folder: Path) -> str:
    """The README's library example, at 20 pushes per action, writing under ``folder``."""
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Using it from your own code"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "make_actions(3), 100," in code and '"runs/' in code  # what the substitutions below rely on
    return code.replace("make_actions(3), 100,", "make_actions(3), 20,").replace('"runs/', f'"{folder}/')


def test_the_public_face_is_light_and_complete():
    probe = ("import sys, pushtorch; heavy = [m for m in ('open3d', 'pybullet', 'hydra') if m in sys.modules]; "
             "names = [pushtorch.load_object, pushtorch.capture_partial_cloud, pushtorch.train_push_model, "
             "pushtorch.load_model, pushtorch.predict, pushtorch.predict_many, pushtorch.Pose, "
             "pushtorch.PushtorchError]; print(heavy, all(callable(n) for n in names))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, check=True)
    assert result.stdout.strip() == "[] True"  # importing pushtorch loads no heavy dependency
    import pushtorch

    assert set(pushtorch._LAZY) <= set(pushtorch.__all__)
    assert (ROOT / "pushtorch" / "py.typed").is_file()


def test_predict_is_callable_from_the_package_in_any_import_order():
    import pushtorch
    import pushtorch.predict  # the submodule binds the package attribute to itself

    assert callable(pushtorch.predict) and pushtorch.predict_many is pushtorch.predict.predict_many
    with pytest.raises(AttributeError):
        pushtorch.no_such_thing  # noqa: B018


def test_the_readme_example_prints_the_same_numbers_in_two_processes(tmp_path):
    outputs = []
    for run in ("a", "b"):
        folder = tmp_path / run
        folder.mkdir()
        script = folder / "example.py"
        script.write_text(_readme_example(folder))
        result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path,
                                timeout=600)
        assert result.returncode == 0, result.stderr[-2000:]
        outputs.append(result.stdout)
    assert "Pose" in outputs[0] and outputs[0] == outputs[1]
