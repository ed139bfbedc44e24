"""A model's settings (paper, §TPMM and the lineage's defaults: bandwidths, cut-offs, query kernels,
annealing) and the helpers every model call shares: a seeded generator by default, an action checked.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np
import torch

from pushtorch.errors import InvalidParameterError
from pushtorch.kde import KernelBandwidth

__all__ = [
    "CONTACT_TRIAL_ROUNDS",
    "DEFAULT_SEED",
    "ModelSettings",
    "as_generator",
    "check_action",
]


#: Trial rounds the motion model's contact-frame kernel may take (:attr:`ModelSettings.contact_bandwidth`): 2^-30 scales
#: any distance a float32 holds into reach.
CONTACT_TRIAL_ROUNDS = 30


@dataclass(frozen=True)
class ModelSettings:
    """Every number of training and prediction; defaults are the paper's (tables) or lineage's.

    Lengths in m, angles in rad, curvature stds in the embedded descriptor space
    (:func:`pushtorch.models.frames.embed_descriptors`).
    """

    # surface features (paper: Surface Features; lineage radius 0.005–0.015 m)
    voxel_size: float = 0.004
    feature_radius: float = 0.012
    # manipulator contact model (paper tables: Distance 0.01, Lambda 100)
    contact_cutoff: float = 0.01
    contact_drop_off: float = 100.0
    # motion model training (paper: 10 environment contacts per push)
    environment_contacts_training: int = 10
    manipulator_kernels_per_push: int = 1
    # prediction (paper tables: 5 environment contacts, 100 samples each, 5000 / 500 kernels)
    environment_contacts: int = 5
    environment_samples: int = 100
    environment_kernels: int = 5000
    manipulator_kernels: int = 500
    # query densities (paper, pose estimation table: 3000 kernels, 500 candidates x 100 steps)
    query_kernels: int = 3000
    position_frames: int = 3000  # uniform subset of the training features kept as position frames
    anneal_candidates: int = 500
    anneal_steps: int = 100
    # the fast path (method="fast") anneals for this fraction of anneal_steps, then moves every candidate
    # to its local mode by polish_steps mean-shift steps (docs/method.md: as accurate as the full schedule
    # on tools/bench_predict.py, a little less on the hardest pose); the dense reference runs it in full
    fast_anneal_fraction: float = 0.3
    polish_steps: int = 3
    descriptor_std: float = 0.5
    descriptor_cutoff_std: float = 5.0
    query_p_std: float = 0.01
    query_rot_std: float = 0.1
    # contact-frame kernel K^c over (u, r) and motion kernels over final poses
    contact_p_std: float = 0.02
    contact_rot_std: float = 0.3
    contact_robot_std: float = 0.05  # m, frame position in the robot's start frame (motion model)
    contact_patch_std: float = 0.02  # m, the push's contact patch on the bumper: its lateral extent
    contact_patch_yaw_std: float = 0.05  # rad, ... and its heading (motion model)
    motion_p_std: float = 0.01
    motion_rot_std: float = 0.05
    # the motion kernels of the density a prediction returns (nll, coverage, the evidence of observed pushes):
    # chosen by held-out likelihood without the motion stds' floor (pushtorch.models.bandwidth); 0: the
    # motion stds above (docs/method.md, "Two widths: the mode and the density")
    density_p_std: float = 0.0
    density_rot_std: float = 0.0
    # the evidence's outlier share ε: observed pushes are weighed under kernels (1 − ε) K_density + ε K_motion,
    # so a push the calibrated kernels miss costs nats in proportion, not tens (chosen with the density stds;
    # 0: the density kernels alone; docs/method.md "The evidence's outlier share")
    density_outlier: float = 0.0
    # Σ of the experts' exponents (w^P normalised; 1: a logarithmic opinion pool, docs/method.md)
    pool_sharpness: float = 1.0
    # k of the k-fold search that chooses the motion and contact bandwidths from the training pushes
    # (pushtorch.models.bandwidth); 0 keeps the values above
    bandwidth_folds: int = 5
    # a model pooled over many shapes scales its motion kernels, wider on a contact far from every training one:
    # stds × sqrt(transfer_scale² + transfer_widening · d²), d the manipulator contact's distance to the
    # nearest training contact in contact-kernel stds (chosen by held-out likelihood across training shapes,
    # pushtorch.evaluation.transfer). 1 and 0: unchanged (every single-object model)
    transfer_scale: float = 1.0
    transfer_widening: float = 0.0
    cutoff_std: float = 3.0
    alpha_t: float = 2.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
            zero_ok = f.name in ("polish_steps", "bandwidth_folds", "transfer_widening", "density_p_std",
                                 "density_rot_std", "density_outlier")
            if not (numeric and (value >= 0 if zero_ok else value > 0)):
                kind = "a number >= 0" if zero_ok else "a positive number"
                raise InvalidParameterError(f"model setting {f.name} must be {kind}, got {value!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "int":  # a count: 2.5 kernels would be silently floored
                if int(value) != value:
                    raise InvalidParameterError(f"model setting {f.name} must be an integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))  # 3000.0 from a config is the count 3000
        if self.fast_anneal_fraction > 1:
            raise InvalidParameterError(f"fast_anneal_fraction must be in (0, 1], got {self.fast_anneal_fraction}")
        if self.alpha_t <= 1:
            raise InvalidParameterError(f"alpha_t must be > 1, got {self.alpha_t}")
        if self.density_outlier >= 1:
            raise InvalidParameterError(f"density_outlier must be in [0, 1), got {self.density_outlier}")

    @property
    def fast_anneal_steps(self) -> int:
        """Annealing steps of the fast path: ``fast_anneal_fraction`` of ``anneal_steps`` (at least 1)."""
        return max(1, round(self.anneal_steps * self.fast_anneal_fraction))

    # -- the kernels the settings define: built once per settings object (frozen, so they cannot go stale)

    @cached_property
    def query_bandwidth(self) -> KernelBandwidth:
        """The query densities' kernel (robot and object poses)."""
        c = self.cutoff_std
        return KernelBandwidth(self.query_p_std, self.query_rot_std, cutoff_std=(c, c, c), alpha_t=self.alpha_t)

    @cached_property
    def contact_bandwidth(self) -> KernelBandwidth:
        """The motion model's contact-frame kernel: relation ``u``, embedded curvatures, the frame's position in
        the robot's start frame and the push's contact patch on the bumper.

        It may widen by up to :data:`CONTACT_TRIAL_ROUNDS` trial rounds (the lineage's 10 elsewhere): its patch
        stds are chosen from the training pushes (5 mm, 0.01 rad at the bounds), and an incongruent model's push
        can meet the object with a patch metres or a radian from every training one (measured: 9,600 scaled
        distances in the quickstart's selection part). Widening then lets the nearest training pushes weigh in,
        as trial rounds are meant to, instead of refusing the prediction.
        """
        return self._contact_kernel(True)

    @cached_property
    def environment_contact_bandwidth(self) -> KernelBandwidth:
        """The environment contacts' kernel: relation ``u`` and embedded curvatures (10 trial rounds at most)."""
        return self._contact_kernel(False)

    def _contact_kernel(self, with_robot_position: bool) -> KernelBandwidth:
        c = self.cutoff_std
        stds = (self.descriptor_std,) * 2
        rounds = 10
        if with_robot_position:
            stds += (self.contact_robot_std,) * 3 + (self.contact_patch_std,) * 2 + (self.contact_patch_yaw_std,)
            rounds = CONTACT_TRIAL_ROUNDS
        return KernelBandwidth(self.contact_p_std, self.contact_rot_std, stds,
                               cutoff_std=(c, c, self.descriptor_cutoff_std), alpha_t=self.alpha_t,
                               max_trial_rounds=rounds)

    @cached_property
    def motion_bandwidth(self) -> KernelBandwidth:
        """The motion kernels' bandwidth (final poses)."""
        c = self.cutoff_std
        return KernelBandwidth(self.motion_p_std, self.motion_rot_std, cutoff_std=(c, c, c), alpha_t=self.alpha_t)

    @cached_property
    def density_bandwidth(self) -> KernelBandwidth:
        """The motion kernels of the density a prediction returns and observations are weighed by: the
        calibrated stds (``density_p_std``, ``density_rot_std``; 0 falls back to the motion stds). The annealed
        mode is found with :attr:`motion_bandwidth`."""
        c = self.cutoff_std
        return KernelBandwidth(self.density_p_std or self.motion_p_std, self.density_rot_std or self.motion_rot_std,
                               cutoff_std=(c, c, c), alpha_t=self.alpha_t)

    @staticmethod
    def from_mapping(mapping) -> ModelSettings:
        """Settings from a dict / Hydra node; unknown keys are an error (a typo would be silent)."""
        known = {f.name for f in fields(ModelSettings)}
        if not isinstance(mapping, Mapping):
            raise InvalidParameterError(f"model settings must be a mapping of names to numbers, got {mapping!r}")
        extra = set(mapping) - known
        if extra:
            raise InvalidParameterError(f"unknown model settings: {sorted(extra)}; known: {sorted(known)}")
        return ModelSettings(**dict(mapping))


def check_action(action) -> torch.Tensor:
    """``action`` as a float64 ``(2,)`` tensor (ẋ m/s, θ̇ rad/s), or a clear error.

    Raises:
        InvalidParameterError: not numeric, not exactly two numbers, or NaN/infinite.
    """
    try:
        a = torch.as_tensor(action, dtype=torch.float64) if not isinstance(action, torch.Tensor) else action
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InvalidParameterError(f"an action must be two numbers (ẋ m/s, θ̇ rad/s), got {action!r}") from exc
    if a.is_complex() or a.dtype == torch.bool or a.numel() != 2:
        raise InvalidParameterError(
            f"an action must be two real numbers (ẋ m/s, θ̇ rad/s), got shape {tuple(a.shape)} of {a.dtype}"
        )
    a = a.detach().reshape(2).to(torch.float64)
    if not torch.isfinite(a).all():
        raise InvalidParameterError(f"an action must be finite, got {a.tolist()}")
    return a


#: The seed of the generator a function that draws random numbers uses when given none: results never depend
#: on torch's global random state (issue 23, "reproducible by default").
DEFAULT_SEED = 0


def as_generator(generator: torch.Generator | int | None, device: torch.device | str | None = None
                 ) -> torch.Generator:
    """A ``torch.Generator`` as given, a new one seeded with an int, or (None) a new one seeded with
    :data:`DEFAULT_SEED`: never torch's global stream, so a call without a generator is reproducible. New
    generators are made for ``device`` (default the CPU).

    Raises:
        InvalidParameterError: anything else (a float, a string, a negative or too large seed).
    """
    if generator is None:
        return torch.Generator(device=device or "cpu").manual_seed(DEFAULT_SEED)
    if isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, int | np.integer) and not isinstance(generator, bool):
        if not 0 <= int(generator) < 2**64:
            raise InvalidParameterError(f"a seed must be an integer in [0, 2**64), got {generator}")
        return torch.Generator(device=device or "cpu").manual_seed(int(generator))
    raise InvalidParameterError(
        f"generator must be a torch.Generator or an integer seed, got {type(generator).__name__} {generator!r}"
    )
