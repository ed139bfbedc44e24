"""An experiment's predictions and ground truth: test poses, single-shot clouds, predictions of every
method, likelihood scores, the pushes simulated from the chosen starts, and the records that compare them
(paper, Experimental Setup, Fig. prediction_accuracy_methodology, prediction and ground truth; Eq. pam).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.evaluation.metrics import Accuracy, accuracy, displaced
from pushtorch.experiments.context import (
    ExperimentContext,
    LogConditions,
    fingerprint,
    load_arrays,
    save_arrays,
    stable_seed,
)
from pushtorch.experiments.training import engine_tag, placement_tag
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.models.library import ModelLibrary, ModelSettings, PushModel
from pushtorch.objects import ObjectModel
from pushtorch.paths import contained_path
from pushtorch.perception import PointCloud
from pushtorch.sim.plan import Placement

__all__ = [
    "Example",
    "Examples",
    "METRICS",
    "PREDICTION_VERSION",
    "PredictionSet",
    "compare",
    "compare_displacement",
    "likelihood_scores",
    "observe",
    "predict_set",
    "sample_test_poses",
    "simulate_truth",
    "spread_test_start",
    "summarise",
    "truth_fingerprint",
]

log = logging.getLogger("pushtorch.experiments")


def sample_test_poses(obj: ObjectModel, count: int, yaw_range_deg: Sequence[float], seed: int) -> se3.Pose:
    """``count`` test poses ``(count,)``: the object upright at the origin, yaw uniform in the range (seeded).

    The robot approaches along +x and the camera looks from -x, so a yaw of 0 shows the object's -x side
    to both (the side the training pushes touched).
    """
    if count < 1:
        raise InvalidParameterError(f"the number of test conditions must be >= 1, got {count}")
    low, high = (math.radians(float(v)) for v in yaw_range_deg)
    if not high >= low:
        raise InvalidParameterError(f"yaw_range_deg must be [low, high], low <= high; got {yaw_range_deg}")
    generator = torch.Generator().manual_seed(seed)
    yaw = low + (high - low) * torch.rand(count, generator=generator, dtype=torch.float64)
    return se3.Pose.stack([obj.resting_pose(0.0, 0.0, float(y)) for y in yaw])


def observe(obj: ObjectModel, pose: se3.Pose, settings: ModelSettings) -> tuple[PointCloud, SurfaceFeatures]:
    """The single-shot cloud of ``obj`` at ``pose`` from the default camera, and its surface features."""
    from pushtorch.perception import capture_partial_cloud

    cloud = capture_partial_cloud(obj, pose, voxel_size=settings.voxel_size)
    return cloud, compute_surface_features(cloud, radius=settings.feature_radius)


_POSE_FIELDS = ("truth_initial", "robot_start", "estimate", "final", "mean_motion", "nearest", "oracle",
                "cloud_start", "cloud_final", "ensemble_start", "ensemble_final")


#: Bump when the predictions a cached set holds would come out differently for the same settings (collision-free
#: starts, new baselines): cached sets of an older version are recomputed.
PREDICTION_VERSION = 4


@dataclass
class PredictionSet:
    """The predictions of one group (one test object, one model or library): N conditions × A actions.

    Attributes:
        truth_initial: true initial object poses ``(N,)``.
        robot_start: predicted robot start poses ``(N, A)``.
        estimate: estimated initial object poses ``B0'`` ``(N, A)`` (the no-motion baseline).
        final: predicted final poses ``(N, A)``.
        mean_motion: the mean-motion baseline's final poses ``(N, A)``.
        nearest: the nearest-push baseline's final poses ``(N, A)`` (from ``estimate``).
        oracle: the oracle-physics baseline's final poses ``(N, A)`` (from ``truth_initial``), or None.
        cloud_start, cloud_final: the physics-from-cloud baseline's reconstructed body before and after the
            push ``(N, A)``, or None.
        ensemble_start, ensemble_final: the physics ensemble's reconstructed body before the push and its
            most probable rollout ``(N, A)`` (the outcome of highest density under the ensemble's own), or None.
        backoff: ``(N, A)`` metres each robot start was backed off to clear the observed cloud
            (:attr:`pushtorch.prediction.PushCondition.backoff`).
        selected: ``(N, A)`` index into ``model_names`` of the model that made each prediction.
        model_names: names of the candidate models.
        fingerprint: what the set was computed from (a cached set is reused only if it matches).
        densities: per condition and action, ``{method: PoseDensity}`` of the methods that predict a
            density (``pushtorch``, ``mean_motion``, ``physics_ensemble``), kept in memory for
            :func:`likelihood_scores`; None for a set read from the cache (its scores were cached with it).
    """

    truth_initial: se3.Pose
    robot_start: se3.Pose
    estimate: se3.Pose
    final: se3.Pose
    mean_motion: se3.Pose
    nearest: se3.Pose
    oracle: se3.Pose | None
    cloud_start: se3.Pose | None
    cloud_final: se3.Pose | None
    backoff: torch.Tensor
    selected: torch.Tensor
    model_names: list[str]
    fingerprint: str
    densities: list[list[dict]] | None = field(default=None, repr=False)
    ensemble_start: se3.Pose | None = None
    ensemble_final: se3.Pose | None = None

    @property
    def invalid_starts(self) -> int:
        """How many robot starts needed more back-off than :data:`pushtorch.prediction.MAX_BACKOFF` (invalid
        conditions, pushed from the cleared start all the same)."""
        from pushtorch.prediction import MAX_BACKOFF

        return int((self.backoff > MAX_BACKOFF).sum())

    def methods(self) -> dict[str, tuple[se3.Pose, se3.Pose]]:
        """``{method: (start, final)}`` of every method in the set, each ``(N, A)``: the displacement from
        start to final is what the method predicts (oracle physics starts at the true pose)."""
        n, a = self.final.batch_shape
        truth = se3.Pose.unchecked(self.truth_initial.p.unsqueeze(1).expand(n, a, 3),
                         self.truth_initial.q.unsqueeze(1).expand(n, a, 4))
        out = {"pushtorch": (self.estimate, self.final), "no_motion": (self.estimate, self.estimate),
               "mean_motion": (self.estimate, self.mean_motion), "nearest_push": (self.estimate, self.nearest)}
        if self.cloud_final is not None:
            out["physics_from_cloud"] = (self.cloud_start, self.cloud_final)
        if self.ensemble_final is not None:
            out["physics_ensemble"] = (self.ensemble_start, self.ensemble_final)
        if self.oracle is not None:
            out["oracle_physics"] = (truth, self.oracle)
        return out

    def save(self, path: Path) -> None:
        """Write atomically as a plain ``.npz`` (no pickle); the densities are not kept."""
        arrays = {"selected": self.selected, "backoff": self.backoff}
        for name in _POSE_FIELDS:
            pose = getattr(self, name)
            if pose is not None:
                arrays[f"{name}_p"], arrays[f"{name}_q"] = pose.p, pose.q
        save_arrays(path, arrays, {"model_names": self.model_names, "fingerprint": self.fingerprint})

    @staticmethod
    def load(path: Path) -> PredictionSet:
        """Read a file written by :meth:`save`.

        Raises:
            RecordFormatError: unreadable or incomplete file.
        """
        arrays, meta = load_arrays(path)
        try:
            poses = {n: se3.Pose.unchecked(arrays[f"{n}_p"], arrays[f"{n}_q"]) if f"{n}_p" in arrays else None
                     for n in _POSE_FIELDS}
            return PredictionSet(**poses, backoff=arrays["backoff"], selected=arrays["selected"],
                                 model_names=list(meta["model_names"]), fingerprint=str(meta["fingerprint"]))
        except (KeyError, TypeError) as exc:
            raise RecordFormatError(f"{path} is not a complete prediction set: missing {exc}") from exc


@dataclass
class Example:
    """One prediction kept in memory for the recording (index of its condition and action)."""

    condition: int
    action: int
    prediction: Any
    features: SurfaceFeatures


@dataclass
class Examples:
    """The predictions of one group that the recording logs (:func:`log_examples`).

    Attributes:
        choice: which conditions (None: the group logs none).
        kept: the chosen conditions' predictions kept while the set was predicted (every action, with their
            annealing history), when the choice was known before the ground truth (``first``, a list).
        again: predicts condition ``i`` again with its own seeds (the same predictions the set holds, with
            their history): ``worst`` and ``best`` choose once the ground truth is known.
    """

    choice: LogConditions | None = None
    kept: list[Example] = field(default_factory=list)
    again: Callable[[int], list[Example]] | None = field(default=None, repr=False)

    def __bool__(self) -> bool:
        return self.choice is not None


def _cache_name(ctx: ExperimentContext, key: str) -> str:
    """A group's cache name: its key, tagged when the test pushes start off-centre (``test_placement``) and
    outside the default pybullet world (``_mujoco``), so both test sets' and both engines' predictions, scores
    and ground truth keep apart in one run folder."""
    key += engine_tag(ctx)
    if ctx.test_placement is None:
        return key
    return f"{key}_test_spread{placement_tag(ctx.test_placement)}"


def _scores_path(ctx: ExperimentContext, key: str) -> Path:
    return contained_path(ctx.run_dir, "scores", f"{_cache_name(ctx, key)}.npz",
                          what="experiment, object or prior name")


def truth_fingerprint(ctx: ExperimentContext, conditions: Sequence[tuple[str, str]], samples: int,
                      seed_key: str) -> str:
    """What a group's ground truth is made from besides its predictions (conditions, priors, samples, seeds,
    simulator): the scores cached with a prediction set are reused only for the same truth."""
    priors = [(repr(ctx.prior("friction", f)), repr(ctx.prior("mass", m))) for f, m in conditions]
    return fingerprint(conditions=list(conditions), priors=priors, samples=samples, seed=ctx.seed,
                       seed_key=seed_key, sim=asdict(ctx.sim), duration=ctx.duration)


def spread_test_start(obj: ObjectModel, pose: se3.Pose, placement: Placement,
                      generator: torch.Generator) -> se3.Pose:
    """A ``placement_spread`` start: the robot heading along the object's own x axis (its yaw in ``pose``)
    plus a uniform ± ``yaw_jitter_deg``, its bumper's centre line a uniform ± ``lateral_jitter`` from the
    object's centre, ``gap`` short of touching (:func:`pushtorch.sim.push.place_robot_against`)."""
    from pushtorch.sim.push import place_robot_against

    u = torch.rand(2, generator=generator, dtype=torch.float64) * 2 - 1
    heading = float(se3.yaw_of(pose.q.double())) + float(u[0]) * math.radians(placement.yaw_jitter_deg)
    return place_robot_against(obj.mesh, pose, heading, float(u[1]) * placement.lateral_jitter, placement.gap)


def predict_set(
    ctx: ExperimentContext,
    key: str,
    obj: ObjectModel,
    candidates: Sequence[PushModel],
    poses: se3.Pose,
    *,
    truth: str,
    adaptive: bool = False,
    choose: Callable[[int], int] | None = None,
    physics: tuple[float, float] | None = None,
    ensemble: tuple[Any, Any, int] | None = None,
    seed_key: str | None = None,
    memo: dict | None = None,
    examples: LogConditions | int | None = None,
    bar=None,
) -> tuple[PredictionSet, Examples]:
    """Predict every test condition and action of one group, with the baselines (cached).

    Paper, Fig. prediction_accuracy_methodology: capture the partial cloud, generate the push condition,
    predict. The prediction of condition ``i`` and action ``j`` is seeded with
    ``stable_seed(seed, seed_key, i, j)``: groups that share a ``seed_key`` use common random numbers,
    so they differ only by the model they apply (a paired comparison), and a model predicting the same
    condition twice gives the same answer (``memo`` then skips the second prediction).

    Args:
        ctx: the experiment context.
        key: the group's name (its cache file ``<run_dir>/predictions/<key>.npz``).
        obj: the test object.
        candidates: the models; with ``adaptive`` the one with the lowest ``H_r`` on each cloud is used
            (paper, Model Selection), else ``candidates[choose(i)]`` for condition ``i`` (default 0).
        poses: true initial poses ``(N,)``.
        truth: :func:`truth_fingerprint` of the ground truth the set will be scored against: a cached set
            is reused only with the likelihood scores of that truth (:func:`likelihood_scores`), since the
            densities they need are not cached.
        physics: (mass kg, ground friction) of the physics baselines (the training prior's means), or None
            to skip them.
        ensemble: (friction prior, mass prior, rollouts) of the ``physics_ensemble`` peer (the model's
            training prior; :func:`pushtorch.evaluation.baselines.physics_ensemble_prediction`), or None.
        seed_key: the name the seeds derive from (default ``key``).
        memo: a dict shared by groups with the same ``seed_key`` and object, keyed by (condition,
            model name, action); holds derived poses and densities, not predictions.
        examples: which conditions' predictions to return whole, with their annealing history, for the
            recording (an int k: the first k; None or no recording: none). Those chosen before the
            ground truth are kept while predicting (recomputed with the same seeds when the set comes
            from the cache); the rest are predicted again, with the same seeds, on demand
            (:class:`Examples`).
        bar: a tqdm bar advanced once per prediction.

    Returns:
        The predictions, and the examples to log.
    """
    from pushtorch.evaluation.baselines import (
        mean_motion_prediction,
        nearest_push_prediction,
        oracle_physics_prediction,
        physics_ensemble_prediction,
        physics_from_cloud_prediction,
    )
    from pushtorch.evaluation.likelihood import ensemble_density, mean_motion_density, motion_product_density
    from pushtorch.prediction import contact_bandwidth, predict

    n, a_count = int(poses.p.shape[0]), int(ctx.actions.shape[0])
    choose = choose or (lambda i: 0)
    seed_key = seed_key or key
    made_from = fingerprint(
        key=key, seed=ctx.seed, seed_key=seed_key, models=[m.name for m in candidates], adaptive=adaptive,
        choice=[choose(i) for i in range(n)], settings=asdict(ctx.settings),
        poses=poses.p.tolist() + poses.q.tolist(), actions=ctx.actions.tolist(),
        physics=physics, samples_per_action=ctx.samples_per_action, version=PREDICTION_VERSION,
        engines=[ctx.sim.engine, ctx.physics.engine],
        **({} if ensemble is None else {"ensemble": [repr(ensemble[0]), repr(ensemble[1]), int(ensemble[2])]}),
    )
    path = contained_path(ctx.run_dir, "predictions", f"{_cache_name(ctx, key)}.npz",
                          what="experiment, object or prior name")
    cached = None
    if path.is_file() and _scores_path(ctx, key).is_file():
        try:
            cached = PredictionSet.load(path)
            _, scores_meta = load_arrays(_scores_path(ctx, key))
        except RecordFormatError as exc:
            log.warning("recomputing %s: %s", key, exc)
            cached = None
        else:
            if cached.fingerprint != made_from or scores_meta.get("made_from") != [made_from, truth]:
                cached = None
    library = ModelLibrary(list(candidates)) if adaptive else None
    if isinstance(examples, int) and not isinstance(examples, bool):
        examples = LogConditions("first", examples)
    choice = examples if ctx.recording is not None else None
    wanted = set(choice.known_before_truth(n)) if choice is not None else set()
    memo = {} if memo is None else memo
    kept: list[Example] = []

    def test_start(i: int, j: int) -> se3.Pose | None:
        """The placement_spread start of condition ``i``, action ``j`` (None: the model's own)."""
        if ctx.test_placement is None:
            return None
        return spread_test_start(obj, poses.take(i), ctx.test_placement,
                                 torch.Generator().manual_seed(stable_seed(ctx.seed, seed_key, i, j, "placement")))

    def predict_condition(i: int, features: SurfaceFeatures, record: bool,
                          into: list[Example] = kept) -> tuple[int, list[dict]]:
        """Model index and, per action, the derived poses of condition ``i`` (with ``record``, its predictions
        go to ``into`` whole)."""
        index = int(library.select(features)[1].argmin()) if library is not None else choose(i)
        model = candidates[index]
        derived = []
        for j in range(a_count):
            memo_key = (i, model.name, j)
            if memo_key in memo and not record:
                derived.append(memo[memo_key])
                continue
            generator = torch.Generator().manual_seed(stable_seed(ctx.seed, seed_key, i, j))
            prediction = predict(model, features, ctx.actions[j], generator, record_history=record,
                                 robot_start=test_start(i, j))
            condition = prediction.condition
            motion = model.motions[model.action_index(ctx.actions[j])]
            start, estimate = condition.robot_start, condition.object_pose
            scoring = torch.Generator().manual_seed(stable_seed(ctx.seed, seed_key, i, j, "likelihood"))
            memo[memo_key] = {
                "robot_start": start, "estimate": estimate, "final": prediction.final_pose,
                "mean_motion": mean_motion_prediction(motion, start, estimate),
                "nearest": nearest_push_prediction(motion, condition.manipulator_frame, start, estimate,
                                                   contact_bandwidth(model.settings), condition.contact_patch),
                "backoff": condition.backoff,
                "densities": {
                    "pushtorch": motion_product_density(prediction.motion_density, scoring, prediction.candidates),
                    "mean_motion": mean_motion_density(motion.manipulator.m, motion.mean_motion, start, estimate),
                },
            }
            derived.append(memo[memo_key])
            if record:
                into.append(Example(i, j, prediction, features))
        return index, derived

    def again(i: int) -> list[Example]:
        """Condition ``i``'s predictions, made again with its seeds (the set's own), whole."""
        if not 0 <= i < n:
            raise InvalidParameterError(f"{key} has test conditions 0..{n - 1}, not {i}")
        _, features = observe(obj, poses.take(i), ctx.settings)
        out: list[Example] = []
        predict_condition(i, features, True, out)
        return out

    chosen = Examples(choice, kept, again) if choice is not None else Examples()
    if cached is not None:
        if bar is not None:
            bar.update(n * a_count)
        for i in sorted(wanted):  # the logged examples only: same seeds, same predictions
            _, features = observe(obj, poses.take(i), ctx.settings)
            predict_condition(i, features, True)
        return cached, chosen

    names = ("robot_start", "estimate", "final", "mean_motion", "nearest", "oracle", "cloud_start", "cloud_final",
             "ensemble_start", "ensemble_final")
    fields: dict[str, list] = {name: [] for name in names}
    selected = torch.zeros(n, a_count, dtype=torch.int64)
    backoff = torch.zeros(n, a_count)
    densities: list[list[dict]] = []
    for i in range(n):
        _, features = observe(obj, poses.take(i), ctx.settings)
        index, derived = predict_condition(i, features, i in wanted)
        selected[i] = index
        densities.append([dict(d["densities"]) for d in derived])  # a copy: memo entries are shared
        for j, poses_ij in enumerate(derived):
            for name in ("robot_start", "estimate", "final", "mean_motion", "nearest"):
                fields[name].append(poses_ij[name])
            backoff[i, j] = poses_ij["backoff"]
            if physics is not None:
                fields["oracle"].append(oracle_physics_prediction(
                    obj, poses_ij["robot_start"], poses.take(i), ctx.actions[j], *physics, settings=ctx.physics))
                cloud_start, cloud_final = physics_from_cloud_prediction(
                    features.p, poses_ij["estimate"], poses_ij["robot_start"], ctx.actions[j], *physics,
                    settings=ctx.physics)
                fields["cloud_start"].append(cloud_start)
                fields["cloud_final"].append(cloud_final)
            if ensemble is not None:
                rollouts = torch.Generator().manual_seed(stable_seed(ctx.seed, seed_key, i, j, "ensemble"))
                start, finals = physics_ensemble_prediction(
                    features.p, poses_ij["estimate"], poses_ij["robot_start"], ctx.actions[j], ensemble[0],
                    ensemble[1], int(ensemble[2]), rollouts, settings=ctx.physics)
                density = ensemble_density(finals, candidates[index].settings.motion_p_std,
                                           candidates[index].settings.motion_rot_std)
                best = int(density.log_prob(finals.vector().double()).argmax())
                fields["ensemble_start"].append(start)
                fields["ensemble_final"].append(finals.take(best))
                densities[-1][j]["physics_ensemble"] = density
            if bar is not None:
                bar.update(1)

    def stacked(items: list[se3.Pose]) -> se3.Pose | None:
        if not items:
            return None
        flat = [se3.Pose.unchecked(p.p.reshape(3).float().cpu(), p.q.reshape(4).float().cpu()) for p in items]
        return se3.Pose.stack(flat).reshape(n, a_count)

    result = PredictionSet(
        truth_initial=se3.Pose.unchecked(poses.p.float(), poses.q.float()),
        **{name: stacked(fields[name]) for name in names},
        backoff=backoff,
        selected=selected,
        model_names=[m.name for m in candidates],
        fingerprint=made_from,
        densities=densities,
    )
    result.save(path)
    stale = _scores_path(ctx, key)
    stale.unlink(missing_ok=True)  # scores of an older set must not pass for this one's
    return result, chosen


def likelihood_scores(ctx: ExperimentContext, key: str, obj: ObjectModel, predictions: PredictionSet,
                      truth_final: se3.Pose, truth: str) -> dict[str, torch.Tensor]:
    """Negative log-likelihoods (nats) of the ground truths ``(C, N, A, S)`` under every method's predicted
    density, in the displacement sense (:func:`pushtorch.evaluation.likelihood.nll`): ``{method: (C, N, A, S)}``;
    and for every method with a density of its own, ``{"coverage:<method>": (C, N, A, S, L)}``, 1 where the
    truth lies inside the density's highest-density region of each level of
    :data:`~pushtorch.evaluation.likelihood.COVERAGE_LEVELS` (:func:`~pushtorch.evaluation.likelihood.hdr_thresholds`).

    ``pushtorch``, ``mean_motion`` and ``physics_ensemble`` are scored under their own densities; the point
    predictions under one kernel of the model's motion bandwidth
    (:func:`pushtorch.evaluation.likelihood.point_density`), without coverage. Cached as
    ``<run_dir>/scores/<key>.npz`` with the set's and the truth's fingerprints (``truth``:
    :func:`truth_fingerprint`).

    Raises:
        RecordFormatError: the set came from the cache but its scores did not (they are written together).
    """
    from pushtorch.evaluation.likelihood import COVERAGE_LEVELS, covered, hdr_thresholds, nll, point_density

    path = _scores_path(ctx, key)
    made_from = [predictions.fingerprint, truth]
    if predictions.densities is None:
        arrays, meta = load_arrays(path)
        if meta.get("made_from") != made_from:
            raise RecordFormatError(f"{path} holds the scores of another prediction set or ground truth")
        return arrays
    c_count, n, a_count, samples = truth_final.batch_shape
    p_std, rot_std = ctx.settings.motion_p_std, ctx.settings.motion_rot_std
    scores: dict[str, torch.Tensor] = {}
    for method, (start, final) in predictions.methods().items():
        out = torch.empty(c_count, n, a_count, samples)
        inside = torch.zeros(c_count, n, a_count, samples, len(COVERAGE_LEVELS))
        has_density = True
        for i in range(n):
            for j in range(a_count):
                own = predictions.densities[i][j].get(method)
                has_density = has_density and own is not None
                density = own or point_density(final.take((i, j)), p_std, rot_std)
                truths = se3.Pose.unchecked(truth_final.p[:, i, j].reshape(-1, 3),
                                            truth_final.q[:, i, j].reshape(-1, 4))
                values = nll(density, truths, predictions.truth_initial.take(i), start.take((i, j)),
                             obj.symmetry)
                out[:, i, j] = values.reshape(c_count, samples).float()
                if own is not None:
                    draws = torch.Generator().manual_seed(stable_seed(ctx.seed, key, method, i, j, "coverage"))
                    thresholds = hdr_thresholds(own, COVERAGE_LEVELS, generator=draws)
                    inside[:, i, j] = covered(values, thresholds).reshape(c_count, samples, -1).float()
        scores[method] = out
        if has_density:
            scores[f"coverage:{method}"] = inside
    save_arrays(path, scores, {"made_from": made_from})
    return scores


def simulate_truth(
    ctx: ExperimentContext,
    key: str,
    obj: ObjectModel,
    predictions: PredictionSet,
    conditions: Sequence[tuple[str, str]],
    samples: int,
    seed_key: str | None = None,
) -> tuple[se3.Pose, torch.Tensor]:
    """Ground-truth final poses ``(C, N, A, S)`` of every condition, test pose, action and sample (cached).

    Each push starts from the robot start pose the model chose and the true initial pose; mass and
    friction are drawn from the test condition's priors (``conditions``: (friction name, mass name)),
    seeded by ``seed_key`` (default ``key``) and condition, so groups sharing a ``seed_key`` face the
    same physical parameters. Pushes run in parallel into ``<run_dir>/truth/<key>/``.

    Returns:
        The final poses, and ``(C, N, A, S)`` flags of pushes in which the object tipped or left the
        ground (in practice: the chosen robot start pose overlapped the object and the engine threw it).
    """
    from pushtorch.sim.plan import PushPlan
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import object_spec

    if samples < 1:
        raise InvalidParameterError(f"truth_samples must be >= 1, got {samples}")
    n, a_count = predictions.final.batch_shape
    c_count = len(conditions)
    shape = (c_count, n, a_count, samples)
    masses, frictions = [], []
    for friction, mass in conditions:
        seed = stable_seed(ctx.seed, "truth", seed_key or key, friction, mass)
        generator = torch.Generator().manual_seed(seed)
        masses.append(ctx.prior("mass", mass).sample((n, a_count, samples), generator))
        frictions.append(ctx.prior("friction", friction).sample((n, a_count, samples), generator))

    def spread(pose: se3.Pose, dims: tuple[int, ...]) -> se3.Pose:
        return se3.Pose.unchecked(pose.p.double().reshape(*dims, 3).expand(*shape, 3).reshape(-1, 3),
                        pose.q.double().reshape(*dims, 4).expand(*shape, 4).reshape(-1, 4))

    action_index = torch.arange(a_count).reshape(1, 1, a_count, 1).expand(shape).reshape(-1)
    plan = PushPlan(
        object_name=obj.name,
        robot_start=spread(predictions.robot_start, (1, n, a_count, 1)),
        object_initial=spread(predictions.truth_initial, (1, n, 1, 1)),
        action=ctx.actions.double()[action_index],
        mass=torch.stack(masses).reshape(-1),
        ground_friction=torch.stack(frictions).reshape(-1),
        action_index=action_index,
        seed=stable_seed(ctx.seed, "truth", key),
        duration=ctx.duration,
    )
    if ctx.recording is not None:
        ctx._truth_plan = (predictions.fingerprint, plan, shape)
    folder = contained_path(ctx.run_dir, "truth", _cache_name(ctx, key), what="experiment, object or prior name")
    # small plans run in this process: a worker pool costs more than it saves
    small = len(plan) < 4 * ctx.shard_size
    run_plan(object_spec(obj), plan, folder, ctx.sim, workers=1 if small else ctx.workers, shard_size=ctx.shard_size,
             progress=False, executor=None if small else ctx.executor)
    records = load_records(folder)
    final = se3.Pose.unchecked(records.object_final.p.reshape(*shape, 3), records.object_final.q.reshape(*shape, 4))
    return final, (records.tipped | records.left_ground).reshape(shape)


#: The scores of a prediction record, primary first (see :func:`summarise`).
METRICS = ("displacement", "frame")


def compare_displacement(initial_estimate: se3.Pose, final_estimate: se3.Pose, truth_initial: se3.Pose,
                         truth_final: se3.Pose, obj: ObjectModel) -> Accuracy:
    """Accuracy of predicted displacements ``(N, A)`` (from ``initial_estimate`` to ``final_estimate``)
    applied to the true start poses ``(N,)``, against ground truths ``(N, A, S)``."""
    return compare(displaced(initial_estimate, final_estimate, truth_initial.unsqueeze(-1)), truth_final, obj)


def compare(estimate: se3.Pose, truth: se3.Pose, obj: ObjectModel) -> Accuracy:
    """Accuracy of estimates ``(...)`` against ground truths ``(..., S)`` (each estimate vs each sample)."""
    shape = truth.batch_shape
    est = se3.Pose.unchecked(estimate.p.unsqueeze(-2).expand(*shape, 3), estimate.q.unsqueeze(-2).expand(*shape, 4))
    flat = int(np.prod(shape))
    return accuracy(est.reshape(flat), truth.reshape(flat), obj)


def summarise(
    task: str,
    obj: str,
    method: str,
    acc: Accuracy,
    model: str | None = None,
    condition: str | None = None,
    selection_rate: float | None = None,
    metric: str | None = None,
    nll: torch.Tensor | None = None,
    coverage: torch.Tensor | None = None,
) -> dict[str, Any]:
    """One results.json record: a group's H_acc mean and std, and mean raw errors, over ``n`` comparisons.

    ``metric`` (prediction and selection records): ``displacement``, the predicted motion applied to the
    true start pose (:func:`pushtorch.evaluation.metrics.displaced`, the primary score), or ``frame``, the predicted
    final pose as it is (the estimated frame against the test object's own); pose records carry none.
    ``nll`` (displacement records): the per-comparison negative log-likelihoods of the truth under the
    method's density (:func:`likelihood_scores`), summarised as ``nll_mean`` and ``nll_median`` (nats);
    ``coverage`` (displacement records of a method with a density): ``(..., 2)`` inside flags of the 50 % and
    90 % regions, summarised as ``coverage_50`` and ``coverage_90`` (None for a point prediction)."""
    h = acc.hacc.reshape(-1).double()
    record = {
        "task": task,
        "object": obj,
        "method": method,
        "model": model,
        "condition": condition,
        "n": int(h.numel()),
        "hacc_mean": float(h.mean()),
        "hacc_std": float(h.std(unbiased=False)) if h.numel() > 1 else 0.0,
        "linear_cm": float(acc.linear_cm.reshape(-1).double().mean()),
        "angular_deg": float(acc.angular_deg.reshape(-1).double().mean()),
    }
    if task == "selection":
        record["selection_rate"] = None if selection_rate is None else float(selection_rate)
    if metric is not None:
        if metric not in METRICS:
            raise InvalidParameterError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
        record["metric"] = metric
        # the likelihood is scored in the displacement sense only; frame records carry the key, empty
        record["nll_mean"] = None if nll is None else float(nll.double().mean())
        record["nll_median"] = None if nll is None else float(nll.double().median())
        flags = None if coverage is None else coverage.double().reshape(-1, coverage.shape[-1]).mean(0)
        record["coverage_50"] = None if flags is None else float(flags[0])
        record["coverage_90"] = None if flags is None else float(flags[1])
    return record
