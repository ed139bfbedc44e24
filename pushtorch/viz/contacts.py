"""Rerun logging of a trained push model: its manipulator contact frames, training placement and position frames.

Paper, §TPMM (Manipulator Contact Model, Object Position Model): the frames a model learnt from its training
pushes, drawn on the training object, and the robot where the contact frames put it. Everything is in the
world frame (z up, metres); point sets are subsampled with a fixed seed (:mod:`~pushtorch.viz.helpers`).

Entity paths (:func:`log_contact_model`), root ``world/model/training/<name>``
(``<name>`` defaults to the model's name; ``/`` separates levels of the hierarchy, and within a level
characters outside ``[A-Za-z0-9_.-]`` become ``_``):

=================================  ==============================================================
``<root>/object``                  training pose ``B^O`` of the object (transform, static)
``<root>/object/mesh``             the training object's mesh
``<root>/contact/points``          manipulator contact frames ``c^m``: positions ``v``, coloured by ``w^c``
                                   (over its range: with λ_c = 100 it spans only 0.99–1)
``<root>/contact/frames``          the same frames as axis triads (x red, y green, z blue)
``<root>/contact/implied_robot``   robot base positions ``v ∘ u^m`` implied by each frame (colour: ``w^c``)
``<root>/robot``                   training robot base pose (transform; mean of ``v ∘ u^m`` on the ground)
``<root>/robot/chassis``           the robot's chassis box (base frame)
``<root>/bumper``                  the bumper at the training pose (world-frame mesh)
``<root>/position/points``         position frames ``c^p``: positions, coloured by saliency weight
``<root>/position/frames``         position frames as axis triads
=================================  ==============================================================
"""

from __future__ import annotations

import rerun as rr
import torch

from pushtorch import se3
from pushtorch.models.query import planar
from pushtorch.viz.bodies import log_posed_mesh, log_robot, mesh_of
from pushtorch.viz.core import entity_name, log_points
from pushtorch.viz.helpers import MODEL, check_limits, log_frames_and_points, range_colors, subsample, weight_colors

__all__ = ["TRAINING", "log_contact_model"]

#: Root of trained models' frames (:func:`log_contact_model`).
TRAINING = f"{MODEL}/training"

_OBJECT_COLOUR = (70, 130, 220, 255)


def log_contact_model(
    rec: rr.RecordingStream,
    model,
    obj=None,
    object_pose: se3.Pose | None = None,
    label: str | None = None,
    max_points: int = 3000,
    max_frames: int = 300,
) -> str:
    """Log a trained model's manipulator contact frames, training placement and position frames.

    The frames are stored relative to the training object's origin ``B^O``; they are drawn on the
    object at ``object_pose`` (default: its training pose, upright at the origin), and the robot where
    the frames put it: ``object_pose ∘ v ∘ u^m`` (their mean, on the ground). Entity paths: see the
    module docstring.

    Args:
        rec: an open recording (:func:`pushtorch.viz.open_recording`).
        model: a :class:`~pushtorch.models.library.PushModel`.
        obj: the training :class:`~pushtorch.objects.ObjectModel` or its mesh (object frame); default
            the catalogue object named ``model.object_name``.
        object_pose: where to draw the object, Pose ``()``; default its resting pose at the origin
            (the pose the model was trained at).
        label: entity name under ``world/model/training`` (default the model's name).
        max_points: points shown per point set; max_frames: axis triads shown per frame set.
    Returns:
        The model's root entity path.
    Raises:
        InvalidParameterError: a limit below 1, an empty label, or ``obj`` of the wrong type.
        PushtorchError: ``obj`` is None and ``model.object_name`` is not a catalogue object.
    """
    from pushtorch.objects import load_object

    check_limits(max_points, max_frames)
    if obj is None:
        obj = load_object(model.object_name)
    mesh = mesh_of(obj)
    if object_pose is None:
        # ObjectModel.resting_pose's definition, which a bare mesh lacks
        object_pose = se3.from_xy_yaw(0.0, 0.0, 0.0, z=float(-mesh.bounds[0, 2]))
    object_pose = se3.Pose.unchecked(object_pose.p.reshape(3).float(), object_pose.q.reshape(4).float())
    root = f"{TRAINING}/{entity_name(label if label is not None else model.name)}"
    log_posed_mesh(rec, f"{root}/object", object_pose, mesh, _OBJECT_COLOUR, axis_length=0.1)

    contact = model.contact.frames.to(torch.float32).transformed(object_pose)
    # w^c = exp(-λ_c d²) spans a narrow band (0.99–1 with the paper's λ_c, δ_c): show its range
    contact_colors = range_colors(contact.weight)
    log_frames_and_points(rec, f"{root}/contact", contact, contact_colors, max_points, max_frames)
    implied = contact.entity  # (N,): the robot base pose each frame implies
    shown = subsample(len(contact), max_points, implied.p.device)
    log_points(rec, f"{root}/contact/implied_robot", implied.p[shown],
               colors=contact_colors[shown.cpu().numpy()], radii=0.004, static=True)
    log_robot(rec, root, planar(se3.mean_pose(implied)))

    position = model.position.frames.to(torch.float32).transformed(object_pose)
    log_frames_and_points(rec, f"{root}/position", position, weight_colors(position.weight),
                           max_points, max_frames)
    return root
