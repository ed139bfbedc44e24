"""pushtorch: transferable forward models for push manipulation (Howard & Zito), batched in torch.

The data flow is mesh → cloud → features → models → prediction → measure; each stage is a module named
for what it holds (see README's map and docs/method.md for the paper equation behind each function).

The main entry points are importable from here; all but :class:`Pose` and :class:`PushtorchError` load on
first use, so ``import pushtorch`` stays light (no open3d, pybullet or Hydra until they are needed).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from pushtorch.errors import PushtorchError
from pushtorch.se3 import Pose

__version__ = "0.1.0"

#: name → the module that defines it, imported on first access (PEP 562). ``predict`` is also the name of
#: a submodule: once that is imported the package attribute is the module, which is callable as the function
#: (``pushtorch.predict._CallableModule``).
_LAZY = {
    "load_object": "pushtorch.objects",
    "capture_partial_cloud": "pushtorch.perception",
    "train_push_model": "pushtorch.models.library",
    "load_model": "pushtorch.models.library",
    "predict": "pushtorch.predict",
    "predict_many": "pushtorch.predict",
    "FinalPoseDistribution": "pushtorch.distribution",
}

__all__ = ["FinalPoseDistribution", "Pose", "PushtorchError", "__version__", "capture_partial_cloud", "load_model",
           "load_object", "predict", "predict_many", "train_push_model"]

if TYPE_CHECKING:  # what type checkers and IDEs see (py.typed ships with the package)
    from pushtorch.distribution import FinalPoseDistribution
    from pushtorch.models.library import load_model, train_push_model
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.predict import predict, predict_many


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'pushtorch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
