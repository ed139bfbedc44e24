"""Online adaptation in Rerun (paper, §Conclusions and future work; :mod:`pushtorch.models.conditioning`): the
posterior over friction and mass on a timeline of observed pushes, with each observed push.

On the ``observed_push`` timeline, at step ``k`` (``k`` pushes observed), under ``root``:

* ``posterior/samples``: draws of ``(μ, log m)`` from the posterior (2-D points: μ across, log m up);
* ``posterior/mu_mean``, ``posterior/log_mass_mean``: the posterior means as scalar series;
* ``observed/cloud``, ``observed/initial``, ``observed/final``, ``observed/path``: the ``k``-th observed push
  (its cloud before the push, the object's observed poses before and after, and the line between them).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun as rr

from pushtorch.viz.core import log_line_strip, log_points, log_pose

__all__ = ["OBSERVED_TIMELINE", "log_online_adaptation"]

#: The timeline of observed pushes: step k holds the posterior after k of them.
OBSERVED_TIMELINE = "observed_push"


def log_online_adaptation(rec: rr.RecordingStream, root: str, posteriors: Sequence, observations: Sequence,
                          samples: int = 200) -> None:
    """Log ``posteriors[k]`` (what ``condition_on`` gave after ``k`` observations: a conditioned model or library,
    anything with ``posterior(n, generator)``) and ``observations[k - 1]`` at step ``k`` of
    :data:`OBSERVED_TIMELINE`, under ``root``."""
    for k, conditioned in enumerate(posteriors):
        rec.set_time(OBSERVED_TIMELINE, sequence=k)
        summary = conditioned.posterior(samples, generator=k)
        draws = summary.samples.double().numpy()
        points = np.stack([draws[:, 0], np.log(draws[:, 1])], -1).astype(np.float32)
        rec.log(f"{root}/posterior/samples", rr.Points2D(points, radii=0.004, colors=(230, 120, 40)))
        rec.log(f"{root}/posterior/mu_mean", rr.Scalars(summary.mu_mean))
        rec.log(f"{root}/posterior/log_mass_mean", rr.Scalars(summary.log_mass_mean))
        if k == 0 or k > len(observations):
            continue
        o = observations[k - 1]
        cloud = o.cloud.points if hasattr(o.cloud, "points") else o.cloud.p
        log_points(rec, f"{root}/observed/cloud", cloud, colors=(120, 160, 220))
        log_pose(rec, f"{root}/observed/initial", o.initial_pose)
        log_pose(rec, f"{root}/observed/final", o.final_pose)
        path = np.stack([o.initial_pose.p.reshape(3).double().numpy(), o.final_pose.p.reshape(3).double().numpy()])
        log_line_strip(rec, f"{root}/observed/path", path, color=(230, 120, 40))
