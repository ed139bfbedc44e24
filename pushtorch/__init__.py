"""pushtorch: transferable forward models for push manipulation (Howard & Zito), batched in torch.

The data flow is mesh → cloud → features → models → prediction → measure; each stage is a module named
for what it holds (see README's map and docs/method.md for the paper equation behind each function).
"""

from pushtorch.errors import PushtorchError
from pushtorch.se3 import Pose

__version__ = "0.1.0"
__all__ = ["Pose", "PushtorchError", "__version__"]
