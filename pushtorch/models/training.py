"""Training a push model (paper, Fig. pipeline, training; §Contact Models, §Object Position Model,
§Motion Model): the full cloud's surface features, the contact and position models fitted to them, and one
motion model per action from the push records.
"""

from __future__ import annotations

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.models.contact import fit_manipulator_contact_model
from pushtorch.models.model import PushModel
from pushtorch.models.motion import fit_motion_model
from pushtorch.models.position import fit_position_model
from pushtorch.models.settings import ModelSettings, as_generator
from pushtorch.objects import ObjectModel
from pushtorch.perception import capture_full_cloud

__all__ = [
    "fit_object_parts",
    "robot_motions",
    "train_push_model",
    "training_features",
]


def training_features(obj: ObjectModel, settings: ModelSettings) -> tuple[se3.Pose, SurfaceFeatures]:
    """The object's training pose (upright at the origin, yaw 0) and its full-cloud features (world)."""
    pose = obj.resting_pose()
    cloud = capture_full_cloud(obj, pose, voxel_size=settings.voxel_size)
    return pose, compute_surface_features(cloud, radius=settings.feature_radius)


def robot_motions(records) -> torch.Tensor:
    """``(P, 3)`` where the robot ended in each push, in its start frame: ``(x, y, yaw)`` of its last recorded
    pose relative to its start (what its odometry reports)."""
    last = se3.Pose.unchecked(records.robot_trajectory.p[:, -1], records.robot_trajectory.q[:, -1])
    moved = se3.relative(records.robot_start, last)
    return torch.stack([moved.p[:, 0], moved.p[:, 1], se3.yaw_of(moved.q)], -1)


def _in_object_frame(features: SurfaceFeatures, pose: se3.Pose) -> SurfaceFeatures:
    """The same features expressed in the frame of ``pose`` (the training object's ``B^O``)."""
    inv = se3.inverse(pose)
    rotate = se3.Pose.unchecked(torch.zeros_like(inv.p), inv.q)
    frames = se3.compose(inv, features.pose)
    return SurfaceFeatures(
        p=frames.p, q=frames.q, r=features.r, normal=se3.apply(rotate, features.normal),
        k1=se3.apply(rotate, features.k1), k2=se3.apply(rotate, features.k2), index=features.index,
    )


def fit_object_parts(obj: ObjectModel, records, settings: ModelSettings, generator: torch.Generator):
    """The contact model, position model and per-action motion models (kernels that know their pushes) of one
    object's push records, before any bandwidth search: what :func:`train_push_model` and the pooled model
    (:func:`pushtorch.models.pooled.train_pooled_model`) build on.

    Raises:
        InvalidParameterError: no valid record.
    """
    from pushtorch.robot import bumper_mesh
    from pushtorch.sim.push import place_robot_against

    valid = records.take(records.valid)
    if len(valid) == 0:
        raise InvalidParameterError(f"no valid push record of {obj.name} (every push tipped, lifted or missed "
                                    "the object)")
    valid = valid.to(torch.float32)
    pose, features = training_features(obj, settings)
    # the contact model is learnt at the nominal placement; the records' jittered placements only
    # enter the motion model
    robot_pose = place_robot_against(obj.mesh, pose)
    contact = fit_manipulator_contact_model(
        features, pose, robot_pose, bumper_mesh(robot_pose),
        cutoff=settings.contact_cutoff, drop_off=settings.contact_drop_off,
    )
    keep = torch.randperm(len(features), generator=generator)[: settings.position_frames]
    position = fit_position_model(features.select(keep.sort().values), pose)
    features_object = _in_object_frame(features, pose)
    # a push table without mass and ground friction (pushtorch.sim.tables): kernels that do not know their physics
    known = bool(torch.isfinite(valid.ground_friction).all() and torch.isfinite(valid.mass).all())
    motions = []
    for a in torch.unique(valid.action_index).tolist():
        sel = valid.take(valid.action_index == a)
        motions.append(
            fit_motion_model(
                features_object, sel.object_initial, sel.object_final, sel.robot_start, bumper_mesh(se3.identity()),
                sel.action[0], settings.environment_contacts_training, settings.manipulator_kernels_per_push,
                settings.contact_cutoff, settings.contact_drop_off, generator,
                physics=torch.stack([sel.ground_friction, sel.mass], -1) if known else None,
                robot_motion=robot_motions(sel),
            )
        )
    return contact, position, motions


def train_push_model(
    obj: ObjectModel,
    records,
    settings: ModelSettings | None = None,
    name: str | None = None,
    generator: torch.Generator | int | None = None,
    meta: dict | None = None,
    partial_data: dict | None = None,
) -> PushModel:
    """Train a model from an object and its push records (paper, Fig. pipeline, both training stages).

    The manipulator contact model is learnt at the nominal training placement (bumper flat against the
    side facing the robot, centred: :func:`pushtorch.sim.push.place_robot_against`); the records, whose
    placements may be jittered, train the motion models.

    Args:
        obj: the training object.
        records: :class:`pushtorch.sim.records.PushRecords` of this object (invalid pushes are skipped).
        settings: model settings (default: the paper's).
        generator: a seeded ``torch.Generator`` or an int seed (None: seeded with :data:`DEFAULT_SEED`, so
            training is reproducible).
        partial_data: set when the records are only part of their runs (kept in the model file).
    Raises:
        InvalidParameterError: no valid record.
    """
    from pushtorch.models.bandwidth import select_bandwidths

    settings = settings or ModelSettings()
    generator = as_generator(generator)
    contact, position, motions = fit_object_parts(obj, records, settings, generator)
    meta = dict(meta or {})
    if settings.bandwidth_folds >= 2:
        settings, search = select_bandwidths(settings, motions, settings.bandwidth_folds, generator)
        meta["bandwidths"] = search.as_meta()
    return PushModel(name or obj.name, obj.name, settings, contact, position, motions, meta, partial_data)
