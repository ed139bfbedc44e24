"""pushtorch: transferable forward models for push manipulation (Howard & Zito), batched in torch.

The data flow is mesh → cloud → features → models → prediction → measure; each stage is a module named
for what it holds (docs/architecture.md has the map, docs/method.md the paper equation behind each function).

The main entry points are importable from here: objects and clouds, simulated pushes (plan, run, load),
training and prediction. All but :class:`Pose` and :class:`PushtorchError` load on first use, so
``import pushtorch`` stays light (no open3d, pybullet or Hydra until they are needed).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from pushtorch.errors import PushtorchError
from pushtorch.se3 import Pose

__version__ = "0.1.0"

#: name → the module that defines it, imported on first access (PEP 562).
_LAZY = {
    # objects and what a camera sees of them
    "load_object": "pushtorch.objects",
    "capture_partial_cloud": "pushtorch.perception",
    # simulated pushes: actions, priors over mass and friction, plans, the parallel runner, records
    "make_actions": "pushtorch.sim.push",
    "Fixed": "pushtorch.sim.priors",
    "Normal": "pushtorch.sim.priors",
    "Uniform": "pushtorch.sim.priors",
    "plan_training_pushes": "pushtorch.sim.plan",
    "object_spec": "pushtorch.sim.settings",
    "run_plan": "pushtorch.sim.runner",
    "simulate_pushes": "pushtorch.sim.runner",
    "load_records": "pushtorch.sim.records",
    "read_push_table": "pushtorch.sim.tables",
    # models and predictions
    "train_push_model": "pushtorch.models.training",
    "train_pooled_model": "pushtorch.models.pooled",
    "load_model": "pushtorch.models.model",
    "train_residual_model": "pushtorch.models.residual",
    "load_residual_model": "pushtorch.models.residual_file",
    "ModelLibrary": "pushtorch.models.library",
    "Observation": "pushtorch.models.conditioning",
    "predict": "pushtorch.prediction",
    "predict_many": "pushtorch.prediction",
    "FinalPoseDistribution": "pushtorch.distribution",
}

__all__ = ["Fixed", "FinalPoseDistribution", "ModelLibrary", "Normal", "Observation", "Pose", "PushtorchError",
           "Uniform", "__version__", "capture_partial_cloud", "load_model", "load_object", "load_records",
           "load_residual_model",
           "make_actions", "object_spec", "plan_training_pushes", "predict", "predict_many", "read_push_table",
           "run_plan", "simulate_pushes", "train_pooled_model", "train_push_model",
           "train_residual_model"]

if TYPE_CHECKING:  # what type checkers and IDEs see (py.typed ships with the package)
    from pushtorch.distribution import FinalPoseDistribution
    from pushtorch.models.conditioning import Observation
    from pushtorch.models.library import ModelLibrary
    from pushtorch.models.model import load_model
    from pushtorch.models.pooled import train_pooled_model
    from pushtorch.models.residual import train_residual_model
    from pushtorch.models.residual_file import load_residual_model
    from pushtorch.models.training import train_push_model
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.prediction import predict, predict_many
    from pushtorch.sim.plan import plan_training_pushes
    from pushtorch.sim.priors import Fixed, Normal, Uniform
    from pushtorch.sim.push import make_actions
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan, simulate_pushes
    from pushtorch.sim.settings import object_spec
    from pushtorch.sim.tables import read_push_table


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'pushtorch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
