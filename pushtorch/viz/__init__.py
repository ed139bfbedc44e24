"""Rerun recordings of every stage, under stable entity paths (one place for all logging).

Entity paths (world frame, z up, metres):
    world/objects/<name>/mesh          object mesh (its transform on world/objects/<name>)
    world/clouds/<name>/full_cloud     training cloud (world frame), coloured by curvature r1
    world/clouds/<name>/partial_cloud  single-shot cloud (world frame), coloured by curvature r1
    world/clouds/<name>/features       surface-feature frames (k1 red, k2 green, normal blue)
    world/sim/<label>/...              a simulated push on the ``sim_time`` timeline (see viz.sim)
    world/model/training/<model>/...   a trained model's contact and position frames (see viz.contacts)
    world/model/prediction/<part>/<object>/<model>/c<i>a<j>/...
                                       an experiment's logged prediction of test condition i, action j
                                       (<model> is the method in model selection; see viz.predictions): its
                                       ground-truth push plays on ``sim_time`` at .../truth_push, its
                                       annealing series are .../robot_query/best_log_prob,
                                       .../pose_query/best_log_prob and .../motion/best_log_prob on
                                       ``anneal_step``, its predicted density is .../density/...
                                       (draws, 90 % region, mode, truth), its accuracy and nll are
                                       the text .../summary
    world/model/prediction/action_<j>/...
                                       the predict app's prediction of action j (the same entities)
    world/experiments/pose_estimation/<object>/...
                                       a pose-estimation example (true pose, cloud, estimates)
    metrics/<part>/hacc/<object>[/<model>][/<condition>]/<method>
                                       a group's mean H_acc: a scalar on the ``group`` timeline at the
                                       group's index in results.json (see viz.scores)
    metrics/<part>/summary             a part's markdown summary (its groups' table, its logged predictions)
    metrics/summary                    the predict app's markdown summary

Timelines: ``sim_time`` (duration, seconds since a push started), ``anneal_step`` (sequence; 0 = initial
candidates), ``group`` (sequence). Every recording ships a blueprint (viz.blueprint) that opens it with a
3D view per experiment part (or predicted action), its text and plots, and the time panel on ``sim_time``.
"""

from pushtorch.viz.core import (
    WORLD,
    curvature_colors,
    entity_name,
    log_arrows,
    log_frames,
    log_line_strip,
    log_mesh,
    log_points,
    log_pose,
    open_recording,
    read_entity_paths,
    transform_columns,
)

__all__ = [
    "WORLD",
    "curvature_colors",
    "entity_name",
    "log_arrows",
    "log_frames",
    "log_line_strip",
    "log_mesh",
    "log_points",
    "log_pose",
    "open_recording",
    "read_entity_paths",
    "transform_columns",
]
