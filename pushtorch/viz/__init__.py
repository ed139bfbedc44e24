"""Rerun recordings of every stage, under stable entity paths (one place for all logging).

Entity paths (world frame, z up, metres):
    world/objects/<name>/mesh          object mesh (its transform on world/objects/<name>)
    world/clouds/<name>/full_cloud     training cloud (world frame), coloured by curvature r1
    world/clouds/<name>/partial_cloud  single-shot cloud (world frame), coloured by curvature r1
    world/clouds/<name>/features       surface-feature frames (k1 red, k2 green, normal blue)
    world/sim/...                      a simulated push on the ``sim_time`` timeline (see viz.sim)
"""

from pushtorch.viz.core import (
    WORLD,
    curvature_colors,
    log_arrows,
    log_frames,
    log_line_strip,
    log_mesh,
    log_points,
    log_pose,
    open_recording,
    read_entity_paths,
)

__all__ = [
    "WORLD",
    "curvature_colors",
    "log_arrows",
    "log_frames",
    "log_line_strip",
    "log_mesh",
    "log_points",
    "log_pose",
    "open_recording",
    "read_entity_paths",
]
