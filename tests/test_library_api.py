"""pushtorch as a library: the public face and reproducible results by default.

The README's "Using it from your own code" example is run as written (smaller: 10 pushes per action, its
run folders in a temporary directory) in a fresh process; with the slow checks, in two, which must print identical
numbers.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from pushtorch.errors import PushtorchError

ROOT = Path(__file__).resolve().parents[1]


def _readme_example(folder: Path) -> str:
    """The README's library example, at 10 pushes per action, writing under ``folder``."""
    readme = (ROOT / "README.md").read_text()
    section = readme[readme.index("## Using it from your own code"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "make_actions(3), 100," in code and '"runs/' in code  # what the substitutions below rely on
    assert "from pushtorch." not in code and "import pushtorch." not in code  # the top level alone
    return code.replace("make_actions(3), 100,", "make_actions(3), 10,").replace('"runs/', f'"{folder}/')


def test_the_public_face_is_light_and_complete():
    probe = ("import sys, pushtorch; heavy = [m for m in ('open3d', 'pybullet', 'hydra', 'trimesh') "
             "if m in sys.modules]; print(heavy); "
             "print(all(callable(getattr(pushtorch, n)) for n in pushtorch.__all__ if n != '__version__'))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, check=True)
    assert result.stdout.split() == ["[]", "True"]  # importing pushtorch loads no heavy dependency
    import pushtorch

    assert set(pushtorch._LAZY) <= set(pushtorch.__all__) <= set(pushtorch._LAZY) | {"Pose", "PushtorchError",
                                                                                      "__version__"}
    # the data-generation API the README's example uses, from the top level alone
    from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan

    assert pushtorch.Normal is Normal and pushtorch.make_actions is make_actions
    assert pushtorch.plan_training_pushes is plan_training_pushes and pushtorch.run_plan is run_plan
    assert pushtorch.load_records is load_records and pushtorch.object_spec is object_spec
    assert (ROOT / "pushtorch" / "py.typed").is_file()


def test_predict_is_the_function_of_the_prediction_package():
    """``pushtorch.predict`` is the function :func:`pushtorch.prediction.predict` (no module of that name is left
    to shadow it), and an unknown name is an AttributeError."""
    import pushtorch
    import pushtorch.prediction

    assert pushtorch.predict is pushtorch.prediction.predict
    assert pushtorch.predict_many is pushtorch.prediction.predict_many
    with pytest.raises(AttributeError):
        pushtorch.no_such_thing  # noqa: B018


def _run_readme_example(tmp_path: Path, run: str) -> str:
    """The README's example in a fresh process, its runs under ``tmp_path / run``; returns what it printed."""
    folder = tmp_path / run
    folder.mkdir()
    script = folder / "example.py"
    script.write_text(_readme_example(folder))
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_the_readme_example_runs_as_written(tmp_path):
    assert "Pose" in _run_readme_example(tmp_path, "a")


@pytest.mark.slow
def test_the_readme_example_prints_the_same_numbers_in_two_processes(tmp_path):
    outputs = [_run_readme_example(tmp_path, run) for run in ("a", "b")]
    assert "Pose" in outputs[0] and outputs[0] == outputs[1]


def test_a_model_moves_to_float64_and_a_float64_cloud_predicts_as_a_float32_one(small_model, tmp_path):
    """``PushModel.to`` and ``load_model(dtype=, map_location=)``. A float64 cloud is cast to the model's dtype
    before its features are computed, so it predicts exactly as the float32 cloud. A float64 model draws the
    same random numbers as the float32 one (``se3.DRAW_DTYPE``), so it predicts the same poses up to
    rounding (within 1e-4 m; 5e-5 m at most on the quickstart's model, both methods)."""
    import torch

    from pushtorch import capture_partial_cloud, load_model, load_object, predict

    model = small_model("cube")
    prism = load_object("prism_thin")
    cloud = capture_partial_cloud(prism, prism.resting_pose(yaw=0.3))
    base = predict(model, cloud, model.actions[1], generator=3)
    wide = model.to(dtype=torch.float64)
    assert wide.dtype == torch.float64 and model.dtype == torch.float32 and wide.device == model.device
    moved = predict(wide, cloud.to(torch.float64), model.actions[1], generator=3)
    assert moved.final_pose.p.dtype == torch.float64 and torch.isfinite(moved.final_pose.p).all()
    assert float((moved.final_pose.p - base.final_pose.p.double()).norm()) < 1e-4
    dense = [predict(m, cloud, model.actions[0], generator=5, method="dense").final_pose.p.double()
             for m in (model, wide)]
    assert float((dense[0] - dense[1]).norm()) < 1e-4
    assert torch.equal(predict(wide, cloud, model.actions[1], generator=3).final_pose.p, moved.final_pose.p)
    assert torch.equal(predict(model, cloud.to(torch.float64), model.actions[1], generator=3).final_pose.p,
                       base.final_pose.p)
    loaded = load_model(model.save(tmp_path / "m.npz"), dtype=torch.float64, map_location="cpu")
    assert loaded.dtype == torch.float64 and loaded.device == torch.device("cpu")
    with pytest.raises(PushtorchError, match="floating"):
        model.to(dtype=torch.int32)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs a CUDA device")
def test_a_model_on_the_gpu_predicts_there(small_model):
    import torch

    from pushtorch import capture_partial_cloud, load_object, predict

    prism = load_object("prism_thin")
    cloud = capture_partial_cloud(prism, prism.resting_pose(yaw=0.3))
    model = small_model("cube")
    prediction = predict(model.to(device="cuda"), cloud, model.actions[1])
    assert prediction.final_pose.p.device.type == "cuda" and torch.isfinite(prediction.final_pose.p).all()
