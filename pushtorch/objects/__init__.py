"""Objects: the paper's catalogue, user meshes, their symmetries, and generated shapes.

Paper, Test Set and Pose Estimation Accuracy: the catalogue's six objects and the modified cube
(:mod:`~pushtorch.objects.catalogue`); Prediction Accuracy Measure (Eq. pam): each object's dimensions D_S and
visually identical orientations Q_gt (:mod:`~pushtorch.objects.symmetry`), detected from its mesh
(:mod:`~pushtorch.objects.symmetry_detection`) with the arithmetic of rotation groups
(:mod:`~pushtorch.objects.rotation_groups`). Beyond the paper: user meshes as the engine pushes them
(:mod:`~pushtorch.objects.meshes`), the object as the library holds it (:mod:`~pushtorch.objects.object_model`),
and random convex shapes for training and held-out tests (:mod:`~pushtorch.objects.shapes`).
"""

from pushtorch.objects.catalogue import CATALOGUE, catalogue_names, load_object
from pushtorch.objects.meshes import (
    BODY_GAP,
    CONVEX_VOLUME_FRACTION,
    SIZE_RANGE,
    UP_AXES,
    VHACD_SETTINGS,
    convex_decomposition,
    load_mesh_file,
    save_mesh_file,
)
from pushtorch.objects.object_model import ObjectModel
from pushtorch.objects.symmetry import Symmetry
from pushtorch.objects.symmetry_detection import detect_symmetry

__all__ = [
    "BODY_GAP",
    "CATALOGUE",
    "CONVEX_VOLUME_FRACTION",
    "ObjectModel",
    "SIZE_RANGE",
    "Symmetry",
    "UP_AXES",
    "VHACD_SETTINGS",
    "catalogue_names",
    "convex_decomposition",
    "detect_symmetry",
    "load_mesh_file",
    "load_object",
    "save_mesh_file",
]
