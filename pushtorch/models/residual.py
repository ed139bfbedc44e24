"""The residual model, ``pushtorch_residual``: physics on the body the observed cloud builds, corrected by how
the world's outcomes differed from the simulator's in the training pushes (beyond the paper: its §Conclusions
and future work ask for models that transfer to unlike shapes; a simulator with a learned stochastic residual
follows Ajay et al. 2018, "Augmenting physical simulators with stochastic neural networks").

Local contact decides where a learned model transfers (paper, §Contact Models), and it cannot tell an object
that spins against the bumper from one that sticks to it; a simulator on the observed shape can, but its
contact and friction are not the world's. The residual model keeps both:

* **Training** (:func:`train_residual_model`). Every training push is rolled out again in the model's
  simulator (``sim.engine``), with the push's own robot start, action, friction and mass, on the body that a
  single-shot cloud of the object at that push's start builds (:func:`pushtorch.sim.bodies.cloud_body`). The
  residual is how the world's outcome of the body's reference pose differs from the rollout's, in the robot's
  start frame about the rollout's centre (:func:`residual_of`): a lateral slide or an extra turn of the
  object, whatever its shape or heading. Each manipulator kernel of the underlying :class:`PushModel` carries
  its push's residual, so residuals are weighed by local contact as the paper's motion kernels are.
* **Prediction** (:func:`pushtorch.prediction.residual.predict_residual`). The push condition is the
  model's own (or a given robot start); the cloud's body is rolled out for an ensemble of ``(μ, m)`` drawn from
  the training pushes' physics, in one call; each rollout is corrected by every residual kernel, weighted by
  its contact weight, and the density is the mixture of these kernels (:data:`RESIDUAL_LADDER` widths chosen
  by leave-one-push-out likelihood).

Decisions are in docs/method.md, "The residual model".
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, ModelError, RecordFormatError
from pushtorch.kde import KernelBandwidth
from pushtorch.kde.normaliser import log_rotation_normaliser
from pushtorch.models.model import PushModel, load_model, model_from_parts, read_model_file, write_model_file
from pushtorch.objects import ObjectModel
from pushtorch.perception import capture_partial_cloud
from pushtorch.sim.bodies import cloud_body, rollout_ensemble
from pushtorch.sim.settings import SimSettings

Tensor = torch.Tensor

__all__ = ["DEFAULT_ENSEMBLE", "RESIDUAL_LADDER", "ResidualModel", "choose_bandwidth", "corrected", "engine_version",
           "load_any_model", "load_residual_model", "residual_of", "train_residual_model", "with_ensemble"]

#: Rollouts per prediction unless the model says otherwise: the largest power of two whose prediction stays within
#: 3× a pushtorch prediction (tools/bench_residual.py on an Intel Xeon, 2 cores: 0.38 s at 4 rollouts against
#: pushtorch's 0.16 s; 1.11 s at 16). Not yet chosen by held-out likelihood.
DEFAULT_ENSEMBLE = 4
#: The residual kernels' stds tried, position (m) × rotation (rad): the pair of highest leave-one-push-out
#: likelihood of the training residuals is kept.
RESIDUAL_LADDER = ((0.0025, 0.005, 0.01, 0.02, 0.04, 0.08), (0.005, 0.01, 0.02, 0.04, 0.08, 0.16))

_IDENTITY_Q = torch.tensor([1.0, 0.0, 0.0, 0.0])


def _centre(pose: se3.Pose) -> se3.Pose:
    """The pure translation to ``pose``'s position (same batch)."""
    return se3.Pose.unchecked(pose.p, _IDENTITY_Q.to(pose.q).expand_as(pose.q))


def residual_of(robot_start: se3.Pose, simulated: se3.Pose, world: se3.Pose) -> se3.Pose:
    """The correction ``D`` that carries a rollout's final pose to the world's (batch dims broadcast): in the
    robot's start frame ``R0``, with ``s = R0⁻¹ ∘ simulated``, ``y = R0⁻¹ ∘ world`` and ``C`` the translation to
    ``s``'s position, ``y = C ∘ D ∘ C⁻¹ ∘ s``: ``D``'s translation is the world's extra slide, its rotation the
    extra turn about the object's centre."""
    s, y = se3.relative(robot_start, simulated), se3.relative(robot_start, world)
    c = _centre(s)
    return se3.compose(se3.inverse(c), se3.compose(y, se3.compose(se3.inverse(s), c)))


def corrected(robot_start: se3.Pose, simulated: se3.Pose, residual: se3.Pose) -> se3.Pose:
    """A rollout's final pose with a residual applied (world; the inverse of :func:`residual_of`; batch dims
    broadcast)."""
    s = se3.relative(robot_start, simulated)
    c = _centre(s)
    return se3.compose(robot_start, se3.compose(c, se3.compose(residual, se3.compose(se3.inverse(c), s))))


@dataclass
class ResidualModel:
    """A push model's contact kernels, each with its training push's residual, and the simulator to roll out in.

    Attributes:
        model: the :class:`PushModel` whose push conditions place the robot and whose manipulator contact kernels
            weigh the residuals.
        residuals: per action, ``(J,)`` the residual of each manipulator kernel's push (:func:`residual_of`).
        bandwidth: the residual kernels' stds (no cut-off: the density is a plain mixture).
        sim: the rollout engine and its settings; engine_version: that engine's version string at training.
        ensemble: rollouts per prediction.
        meta: how the residuals and widths were chosen (scores, rollouts that failed).
    """

    model: PushModel
    residuals: list[se3.Pose]
    bandwidth: KernelBandwidth
    sim: SimSettings
    engine_version: str
    ensemble: int = DEFAULT_ENSEMBLE
    meta: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.model.name}_residual"

    @property
    def actions(self) -> Tensor:
        return self.model.actions

    def action_index(self, action) -> int:
        return self.model.action_index(action)

    # what a prediction and a library read of a model: the push model's own (selection by H_r, the cloud's
    # features, conditioning's evidence), so residual models sit in a ModelLibrary as push models do
    @property
    def settings(self):
        return self.model.settings

    @property
    def position(self):
        return self.model.position

    @property
    def contact(self):
        return self.model.contact

    @property
    def motions(self):
        return self.model.motions

    @property
    def motion_kernels(self):
        return self.model.motion_kernels

    @property
    def physics_posterior(self):
        return self.model.physics_posterior

    @property
    def dtype(self) -> torch.dtype:
        return self.model.dtype

    @property
    def device(self) -> torch.device:
        return self.model.device

    def condition_on(self, observations, seed: int | None = None, prior: tuple | None = None,
                     bandwidth=None) -> ResidualModel:
        """This model with its push model conditioned on observed pushes
        (:meth:`PushModel.condition_on <pushtorch.models.model.PushModel.condition_on>`): the ensemble's
        friction and mass are then drawn from the posterior, and each residual kernel weighs by it too."""
        return dataclasses.replace(self, model=self.model.condition_on(observations, seed, prior, bandwidth))

    def save(self, path) -> Path:
        """Write the model atomically to ``path``: the push model's sealed file, with the residuals' arrays and a
        ``residual`` header (the rollout engine, its version and settings, the ensemble and the kernels' stds).
        :func:`~pushtorch.models.model.load_model` reads the push model back from it;
        :func:`load_residual_model` the whole."""
        arrays = {}
        for a, r in enumerate(self.residuals):
            arrays[f"residual{a}.p"], arrays[f"residual{a}.q"] = r.p, r.q
        header = {"residual": {"engine": self.sim.engine, "engine_version": self.engine_version,
                               "sim": dataclasses.asdict(self.sim), "ensemble": self.ensemble,
                               "p_std": self.bandwidth.p_std, "rot_std": self.bandwidth.rot_std,
                               "meta": self.meta}}
        return write_model_file(path, *self.model.file_parts(arrays, header))


def engine_version(engine: str) -> str:
    """The installed version of ``engine`` (``pybullet`` or ``mujoco``): what a model file records."""
    if engine == "mujoco":
        import mujoco

        return f"mujoco {mujoco.__version__}"
    import importlib.metadata

    return f"pybullet {importlib.metadata.version('pybullet')}"


def _log_kernels(residuals: se3.Pose, p_std: float, rot_std: float) -> Tensor:
    """``(J, J)`` each normalised, uncut residual kernel's log density at every residual (float64)."""
    p = residuals.p.double()
    q = residuals.q.double()
    d2 = ((p.unsqueeze(1) - p.unsqueeze(0)) ** 2).sum(-1)
    dq = (1 - (q.unsqueeze(1) * q.unsqueeze(0)).sum(-1).abs()).clamp_min(0)
    sigma_q = rot_std**2 / 4
    log_norm = 1.5 * math.log(2 * math.pi * p_std**2) + float(log_rotation_normaliser(torch.tensor(1 / sigma_q)))
    return -d2 / (2 * p_std**2) - dq / sigma_q - log_norm


def choose_bandwidth(residuals: list[se3.Pose], push: list[Tensor], settings) -> tuple[KernelBandwidth, dict]:
    """The residual kernels' stds of highest leave-one-push-out likelihood: each training push's residual
    scored under the other pushes' kernels, equally weighted, summed over actions (nats per push)."""
    best, scores = None, {}
    for p_std in RESIDUAL_LADDER[0]:
        for rot_std in RESIDUAL_LADDER[1]:
            total, count = 0.0, 0
            for r, k in zip(residuals, push, strict=True):
                if len(r.p) < 2:
                    continue
                log_k = _log_kernels(r, p_std, rot_std)
                log_k = log_k.masked_fill(k.unsqueeze(1) == k.unsqueeze(0), -math.inf)  # its own push held out
                held = torch.logsumexp(log_k, 1) - torch.log(torch.isfinite(log_k).sum(1).clamp_min(1).double())
                keep = torch.isfinite(held)
                total += float(held[keep].sum())
                count += int(keep.sum())
            if count:
                scores[(p_std, rot_std)] = total / count
                if best is None or scores[(p_std, rot_std)] > scores[best]:
                    best = (p_std, rot_std)
    if best is None:
        raise ModelError("too few training pushes to choose the residual kernels' width (two per action at least)")
    bandwidth = KernelBandwidth(best[0], best[1], cutoff_std=(math.inf, math.inf, math.inf),
                                alpha_t=settings.alpha_t)
    return bandwidth, {"p_std": best[0], "rot_std": best[1], "score": round(scores[best], 3)}


def _training_body(obj: ObjectModel, pose: se3.Pose, voxel_size: float) -> tuple[ObjectModel, se3.Pose]:
    """The body a single-shot cloud of ``obj`` at ``pose`` builds, as a prediction would build it."""
    cloud = capture_partial_cloud(obj, pose, voxel_size=voxel_size)
    return cloud_body(cloud.points, pose)


def train_residual_model(model: PushModel, obj: ObjectModel, records, sim: SimSettings | None = None,
                         ensemble: int = DEFAULT_ENSEMBLE,
                         body_of: Callable[[ObjectModel, se3.Pose], tuple[ObjectModel, se3.Pose]] | None = None
                         ) -> ResidualModel:
    """The residual model of ``model``, trained on the same push ``records`` of ``obj`` (module docstring).

    Args:
        model: trained on ``records`` by this pushtorch (its kernels know their pushes).
        records: the :class:`~pushtorch.sim.records.PushRecords` the model was trained on.
        sim: the simulator the residual is taken against (default pybullet's settings).
        ensemble: rollouts per prediction.
        body_of: ``(object, pose) → (body, body pose)``, the body each push is rolled out on; default the
            body a single-shot cloud at the push's start builds (the true mesh: ``lambda o, p: (o, p)``).

    Raises:
        InvalidParameterError: an ensemble < 1, kernels that do not know their pushes (a loaded model), or
            records without friction and mass.
    """
    sim = sim or SimSettings()
    if isinstance(ensemble, bool) or int(ensemble) != ensemble or ensemble < 1:
        raise InvalidParameterError(f"the ensemble needs at least one rollout, got {ensemble!r}")
    body_of = body_of or (lambda o, pose: _training_body(o, pose, model.settings.voxel_size))
    valid = records.take(records.valid)
    if not bool(torch.isfinite(valid.ground_friction).all() and torch.isfinite(valid.mass).all()):
        raise InvalidParameterError("the residual model rolls each training push out at its own friction and mass, "
                                    "and these records have none (a push table without 'mass' and "
                                    "'ground_friction' columns)")
    indices = torch.unique(valid.action_index).tolist()  # the model's actions, in its order (fit_object_parts)
    if len(indices) != len(model.motions):
        raise InvalidParameterError(f"the records have {len(indices)} actions with valid pushes, the model "
                                    f"{len(model.motions)}: train the residual on the model's own records")
    residuals, pushes, rollouts = [], [], 0
    for a, motion in zip(indices, model.motions, strict=True):
        push = motion.manipulator.push
        if push is None:
            raise InvalidParameterError("a residual model needs a model trained in this session (its kernels know "
                                        "their pushes), not a loaded one")
        sel = valid.take(valid.action_index == a)
        action = sel.action[0].double()
        per_push = []
        for i in range(len(sel)):  # each push has its own body: one rollout each
            b0, b1 = sel.object_initial.take(i), sel.object_final.take(i)
            r0 = sel.robot_start.take(i)
            body, start = body_of(obj, b0)
            final = rollout_ensemble(body, start, r0, action, sel.ground_friction[i:i + 1],
                                     sel.mass[i:i + 1], sim).object_final.take(0)
            world = se3.compose(se3.compose(b1, se3.inverse(b0)), se3.Pose.unchecked(start.p.double(),
                                                                                     start.q.double()))
            per_push.append(residual_of(r0, final, world))
            rollouts += 1
        stacked = se3.Pose.stack(per_push)
        kernels = stacked.take(push.cpu())
        residuals.append(se3.Pose.unchecked(kernels.p.to(model.dtype), kernels.q.to(model.dtype)))
        pushes.append(push.cpu())
    bandwidth, chosen = choose_bandwidth(residuals, pushes, model.settings)
    return ResidualModel(model, residuals, bandwidth, sim, engine_version(sim.engine), int(ensemble),
                         {"bandwidth": chosen, "training_rollouts": rollouts})


def with_ensemble(model: ResidualModel, ensemble: int) -> ResidualModel:
    """``model`` with another ensemble size."""
    if isinstance(ensemble, bool) or int(ensemble) != ensemble or ensemble < 1:
        raise InvalidParameterError(f"the ensemble needs at least one rollout, got {ensemble!r}")
    return dataclasses.replace(model, ensemble=int(ensemble))


def load_residual_model(path, dtype: torch.dtype = torch.float32, other_engine: bool = False) -> ResidualModel:
    """Read a residual model file (:meth:`ResidualModel.save`).

    Args:
        other_engine: load it even where the installed rollout engine's version is not the one it was trained
            against (its residuals correct that version's outcomes).

    Raises:
        RecordFormatError: as :func:`~pushtorch.models.model.load_model`; a push model's file without residuals;
            a file of another engine version, unless ``other_engine``.
    """
    header, arrays = read_model_file(path)
    if not isinstance(header.get("residual"), dict):
        raise RecordFormatError(f"{path} is a push model without residuals: load it with load_model")
    return _residual_from_parts(path, header, arrays, dtype, other_engine)


def load_any_model(path, dtype: torch.dtype = torch.float32, other_engine: bool = False) -> PushModel | ResidualModel:
    """A model file as what it holds: a :class:`ResidualModel` where it has residuals
    (:func:`load_residual_model`), else the :class:`PushModel` (:func:`~pushtorch.models.model.load_model`).
    What the predict app reads its ``models`` with."""
    header, arrays = read_model_file(path)
    if isinstance(header.get("residual"), dict):
        return _residual_from_parts(path, header, arrays, dtype, other_engine)
    return load_model(path, dtype)  # its own checks and messages


def _residual_from_parts(path, header: dict, arrays: dict, dtype: torch.dtype, other_engine: bool) -> ResidualModel:
    spec = header["residual"]
    try:
        sim = SimSettings(**spec["sim"])
        installed = engine_version(sim.engine)
        if installed != spec["engine_version"] and not other_engine:
            raise RecordFormatError(f"{path} was trained against {spec['engine_version']}, this machine has "
                                    f"{installed}: its residuals correct the other's outcomes (other_engine=True "
                                    "loads it anyway)")
        model = model_from_parts(header, {k: v for k, v in arrays.items() if not k.startswith("residual")}, dtype)
        residuals = [se3.Pose.unchecked(torch.from_numpy(arrays[f"residual{a}.p"]).to(dtype),
                                        torch.from_numpy(arrays[f"residual{a}.q"]).to(dtype))
                     for a in range(len(model.motions))]
        for r, m in zip(residuals, model.motions, strict=True):
            if r.p.shape != (len(m.manipulator), 3) or r.q.shape != (len(m.manipulator), 4):
                raise ValueError("the residuals do not match the manipulator kernels")
        bandwidth = KernelBandwidth(float(spec["p_std"]), float(spec["rot_std"]),
                                    cutoff_std=(math.inf, math.inf, math.inf), alpha_t=model.settings.alpha_t)
        return ResidualModel(model, residuals, bandwidth, sim, str(spec["engine_version"]), int(spec["ensemble"]),
                             dict(spec.get("meta") or {}))
    except RecordFormatError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError, InvalidParameterError) as exc:
        raise RecordFormatError(f"{path} has a malformed residual model ({type(exc).__name__}: {exc})") from exc
