"""Perception demo: the catalogue's objects, their clouds and surface features in one Rerun recording.

Paper, Experimental Setup (full multi-view cloud for training, single shot for prediction) and
Surface Features. Objects stand in a row along x; each gets its mesh, both clouds coloured by the
curvature r1, and its surface-feature frames (a subsample, so the viewer stays responsive). The recording's
blueprint (:func:`pushtorch.viz.blueprint.perception_blueprint`) shows all objects, then a tab per object.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
from tqdm import tqdm

from pushtorch import viz
from pushtorch.features import compute_surface_features
from pushtorch.objects import load_object
from pushtorch.perception import capture_full_cloud, capture_partial_cloud

__all__ = ["log_object_perception", "run"]


def log_object_perception(
    rec,
    name: str,
    x: float,
    voxel_size: float,
    feature_radius: float,
    depth_noise: float,
    generator: torch.Generator,
    frames_shown: int = 400,
) -> dict[str, int]:
    """Capture, featurise and log one catalogue object standing at ``(x, 0)``; return point counts."""
    from pushtorch.perception import DepthCamera

    obj = load_object(name)
    pose = obj.resting_pose(x=x)
    camera = DepthCamera(noise_std=depth_noise)
    full = capture_full_cloud(obj, pose, camera=camera, voxel_size=voxel_size, generator=generator)
    partial = capture_partial_cloud(obj, pose, camera=camera, voxel_size=voxel_size, generator=generator)
    features = compute_surface_features(full, radius=feature_radius)
    partial_features = compute_surface_features(partial, radius=feature_radius)
    root = f"{viz.WORLD}/objects/{name}"
    viz.log_pose(rec, root, pose, static=True)
    viz.log_mesh(rec, f"{root}/mesh", obj.mesh, static=True)
    # clouds are in the world frame: log them beside the object, not under its transform
    viz.log_points(rec, f"{viz.WORLD}/clouds/{name}/full_cloud", features.p,
                   colors=viz.curvature_colors(features.r[:, 0]), static=True)
    viz.log_points(rec, f"{viz.WORLD}/clouds/{name}/partial_cloud", partial_features.p,
                   colors=viz.curvature_colors(partial_features.r[:, 0]), static=True)
    shown = torch.randperm(len(features), generator=generator)[:frames_shown]
    viz.log_frames(rec, f"{viz.WORLD}/clouds/{name}/features", features.pose.take(shown), static=True)
    return {"full_points": len(features), "partial_points": len(partial_features)}


def run(cfg, out_dir: Path, overrides: Sequence[str] = ()) -> dict:
    """Log every configured object; returns where the recording is and the cloud sizes (``overrides``: unused,
    as every experiment's ``run`` takes them)."""
    exp = cfg.experiment
    generator = torch.Generator().manual_seed(int(cfg.seed))
    recording = out_dir / "recording.rrd"
    from pushtorch.viz.blueprint import perception_blueprint

    rec = viz.open_recording(recording, "pushtorch-perception")
    names = [str(name) for name in exp.objects]
    counts = {}
    try:
        for i, name in enumerate(tqdm(names, desc="objects", unit="obj")):
            counts[name] = log_object_perception(
                rec, name, i * float(exp.spacing), float(exp.voxel_size), float(exp.feature_radius),
                float(exp.depth_noise), generator,
            )
    finally:
        rec.send_blueprint(perception_blueprint(names))
        rec.disconnect()  # completes the file (flush alone leaves it without its footer)
    return {"recording": str(recording), "points": counts}
