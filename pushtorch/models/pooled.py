"""One model from many training shapes: every shape's kernels pooled, with the contact frames they came from
(paper, §Conclusion and future work: transfer to novel objects by *local* contact models; beyond the paper's
two training objects).

The paper trains one model per object and picks one for a new cloud by ``H_r`` (:class:`ModelLibrary`). Its
thesis is that contact and motion models are local: a kernel's weight in an expert is ``K^c``, how much its
training contact resembles the new one (Eq. contact_frame_probability). A pooled model tests that thesis at
scale: the kernels of every shape's pushes sit in one model, and the product of experts weighs them by local
contact, so the pushes of whichever shapes touched the bumper as this object does decide the prediction.

Decisions (docs/method.md, "Many shapes"):

* **Motion kernels**: every shape's, concatenated per action (pushes renumbered so the bandwidth search's
  folds hold out whole pushes). The bandwidths are then chosen on the pool, as for one object
  (:func:`pushtorch.models.bandwidth.select_bandwidths`). A prediction evaluates at most
  :data:`POOLED_BUDGET` kernels, the nearest in contact (:func:`pushtorch.models.motion.nearest_in_contact`):
  every one of them is within reach of the contact, where most of a single object's 5,000 environment kernels
  are cut off, so the same count would cost 2–3 × the time.
* **Manipulator contact model**: every shape's frames (where the robot stood against it), at most an equal
  share of ``position_frames`` per shape (drawn by weight), each shape's weights normalised to the same total,
  so a shape with a large face does not outvote the rest; the robot's query density then costs what one
  object's does (57,322 frames of 40 shapes made a prediction 3.6 × slower).
* **Position model**: an equal share of every shape's position frames, ``position_frames`` in all. The pose
  estimate of a new object then leans on features of all shapes; it matters little for the displacement
  score (the motion is carried in the robot's start frame), and the frame score says what it costs.
* **Mean motion**: the mean over every pushed shape's motions (the ``mean_motion`` baseline of the pool).

The widening of the density on contacts far from every training contact is chosen on the training shapes
by held-out likelihood, one shape held out at a time (:func:`pushtorch.evaluation.transfer.choose_widening`).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.models.contact import ManipulatorContactModel
from pushtorch.models.frames import ContactFrames, embed_descriptors
from pushtorch.models.model import PushModel
from pushtorch.models.motion import MotionKernels, MotionModel
from pushtorch.models.position import PositionModel
from pushtorch.models.settings import ModelSettings, as_generator
from pushtorch.models.training import fit_object_parts
from pushtorch.objects import ObjectModel

__all__ = ["POOLED_BUDGET", "ShapeParts", "fit_shape_parts", "pool_parts", "train_pooled_model"]

#: The pooled model's kernel budget per prediction and action (at most the settings' own): the manipulator and
#: environment kernels nearest in contact. Chosen with tools/bench_shapes.py so that a pool of 40 shapes and the
#: paper's 24,000 pushes predicts within 1.25 × the one-object model's time (the paper's 500 / 5,000: 3.65 ×;
#: 200 / 2,000: 1.41 ×), at no measured cost in likelihood (docs/method.md, "Many shapes").
POOLED_BUDGET = {"manipulator_kernels": 100, "environment_kernels": 1000}

#: One shape's fitted parts: (name, contact model, position model, motion models per action).
ShapeParts = tuple[str, ManipulatorContactModel, PositionModel, list[MotionModel]]


def fit_shape_parts(objects: list[ObjectModel], records: list, settings: ModelSettings,
                    generator: torch.Generator | int | None = None) -> list[ShapeParts]:
    """Every shape's contact, position and motion models (:func:`~pushtorch.models.training.fit_object_parts`).

    Raises:
        InvalidParameterError: no shape, a records list of another length, or repeated shape names.
    """
    if not objects:
        raise InvalidParameterError("a pooled model needs at least one training shape")
    if len(records) != len(objects):
        raise InvalidParameterError(f"{len(objects)} training shapes but {len(records)} sets of push records")
    names = [o.name for o in objects]
    if len(set(names)) != len(names):
        raise InvalidParameterError(f"training shapes must have distinct names, got {names}")
    generator = as_generator(generator)
    return [(o.name, *fit_object_parts(o, r, settings, generator)) for o, r in zip(objects, records, strict=True)]


def _cat_frames(frames: list[ContactFrames]) -> ContactFrames:
    return ContactFrames(se3.Pose.cat([f.v for f in frames]), torch.cat([f.r for f in frames]),
                         se3.Pose.cat([f.u for f in frames]), torch.cat([f.weight for f in frames]))


def _cat_kernels(kernels: list[MotionKernels], offsets: list[int]) -> MotionKernels:
    def cat(name: str) -> torch.Tensor | None:
        values = [getattr(k, name) for k in kernels]
        return None if any(v is None for v in values) else torch.cat(values)

    push = None
    if all(k.push is not None for k in kernels):
        push = torch.cat([k.push + o for k, o in zip(kernels, offsets, strict=True)])
    return MotionKernels(cat("r"), se3.Pose.cat([k.u for k in kernels]), se3.Pose.cat([k.m for k in kernels]),
                         cat("g"), cat("patch"), push, cat("physics"), cat("robot_motion"), cat("log_weight"))


def _pushes(motion: MotionModel) -> int:
    """How many pushes an action's kernels came from (their largest push index + 1; 0 if unknown)."""
    known = [k.push for k in (motion.manipulator, motion.environment) if k.push is not None and len(k)]
    return int(max(int(p.max()) for p in known)) + 1 if known else 0


def pool_parts(parts: list[ShapeParts], settings: ModelSettings, generator: torch.Generator | int | None = None
               ) -> tuple[ManipulatorContactModel, PositionModel, list[MotionModel]]:
    """The pooled contact, position and motion models of several shapes (module docstring).

    Raises:
        InvalidParameterError: no parts, or a shape pushed with an action no other shape was.
    """
    if not parts:
        raise InvalidParameterError("a pooled model needs at least one training shape")
    generator = as_generator(generator)
    # the actions in the order of the shape that has the most; a shape whose every push of an action was invalid
    # (tipped, missed) adds nothing to that action
    known = max((torch.stack([m.action for m in p[3]]) for p in parts), key=len)
    for name, *_, motions in parts:
        for m in motions:
            if not (known - m.action.to(known)).abs().amax(-1).le(1e-6).any():
                raise InvalidParameterError(f"shape {name} was pushed with action {m.action.tolist()}, which the "
                                            f"other shapes were not ({known.tolist()}): a pooled model needs one set "
                                            "of actions")
    contacts = []
    share = max(1, settings.position_frames // len(parts))
    for _, contact, _, _ in parts:
        frames = contact.frames
        if len(frames) > share:  # drawn by weight: the frames that would weigh most in the robot's query density
            keep = torch.multinomial(frames.weight.double().clamp_min(0) + 1e-12, share, replacement=False,
                                     generator=generator)
            frames = frames.select(keep.sort().values)
        weight = frames.weight / frames.weight.sum().clamp_min(1e-30)
        contacts.append(ContactFrames(frames.v, frames.r, frames.u, weight))
    first = parts[0][1]
    contact = ManipulatorContactModel(_cat_frames(contacts), first.cutoff, first.drop_off)
    positions = []
    for _, _, position, _ in parts:
        keep = torch.randperm(len(position.frames), generator=generator)[:share].sort().values
        positions.append(position.frames.select(keep))
    pooled_frames = _cat_frames(positions)
    std = embed_descriptors(pooled_frames.r).std(0).clamp_min(1e-6)
    position = PositionModel(pooled_frames, std)
    motions = []
    for action in known:
        per_shape = [m for p in parts for m in p[3] if (m.action.to(action) - action).abs().max() <= 1e-6]
        counts = [_pushes(m) for m in per_shape]
        offsets = [sum(counts[:i]) for i in range(len(counts))]
        manipulator = _cat_kernels([m.manipulator for m in per_shape], offsets)
        environment = _cat_kernels([m.environment for m in per_shape], offsets)
        # one manipulator kernel per push and kernel: the pool's mean motion weighs every push alike
        motions.append(MotionModel(per_shape[0].action, manipulator, environment, se3.mean_pose(manipulator.m, 0)))
    return contact, position, motions


def train_pooled_model(objects: list[ObjectModel], records: list, settings: ModelSettings | None = None,
                       name: str = "shapes", generator: torch.Generator | int | None = None,
                       meta: dict | None = None, parts: list[ShapeParts] | None = None) -> PushModel:
    """One model trained on the pushes of many shapes (module docstring).

    Args:
        objects: the training shapes; records: each one's :class:`~pushtorch.sim.records.PushRecords`.
        settings: model settings (default: the paper's); their bandwidths are searched on the pool when
            ``bandwidth_folds >= 2``.
        parts: the shapes' fitted parts when the caller has them (:func:`fit_shape_parts`), else fitted here.

    Raises:
        InvalidParameterError: no shape, mismatched records, a shape without a valid push, different actions.
    """
    from pushtorch.models.bandwidth import select_bandwidths

    settings = settings or ModelSettings()
    generator = as_generator(generator)
    parts = parts if parts is not None else fit_shape_parts(objects, records, settings, generator)
    contact, position, motions = pool_parts(parts, settings, generator)
    meta = dict(meta or {})
    meta["pooled"] = [p[0] for p in parts]
    budget = {k: min(int(getattr(settings, k)), v) for k, v in POOLED_BUDGET.items()}
    if any(budget[k] != getattr(settings, k) for k in budget):
        meta["budget"] = {"start": {k: getattr(settings, k) for k in budget}, "chosen": budget}
        settings = replace(settings, **budget)
    if settings.bandwidth_folds >= 2:
        settings, search = select_bandwidths(settings, motions, settings.bandwidth_folds, generator)
        meta["bandwidths"] = search.as_meta()
    return PushModel(name, name, settings, contact, position, motions, meta)
