"""An experiment's prediction sets: the test poses, the single-shot cloud of each, and every predictor's
prediction of every test condition and action of a group (ours and the baselines, from the same starts and
seeds), cached per group (paper, Experimental Setup, Fig. prediction_accuracy_methodology, prediction).

:func:`predict_set` makes a group's :class:`PredictionSet`; :mod:`pushtorch.experiments.scoring` simulates its
ground truth and scores it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.experiments.context import (
    ExperimentContext,
    LogConditions,
    fingerprint,
    load_arrays,
    save_arrays,
    scores_made_from,
    stable_seed,
)
from pushtorch.experiments.example_files import load_examples, save_examples
from pushtorch.experiments.training import engine_tag, placement_tag
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.models.library import ModelLibrary
from pushtorch.models.model import PushModel
from pushtorch.models.settings import ModelSettings
from pushtorch.objects import ObjectModel
from pushtorch.paths import contained_path
from pushtorch.perception import PointCloud
from pushtorch.sim.plan import Placement

__all__ = [
    "Example",
    "Examples",
    "PREDICTION_VERSION",
    "PredictionSet",
    "cache_name",
    "examples_path",
    "observe",
    "predict_set",
    "sample_test_poses",
    "scores_path",
    "spread_test_start",
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
                "cloud_start", "cloud_final", "ensemble_start", "ensemble_final", "residual_start", "residual_final")


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
        residual_start, residual_final: the residual model's (``pushtorch_residual``) cloud body before the push
            and its density's mode ``(N, A)``, from pushtorch's own robot start, or None.
        backoff: ``(N, A)`` metres each robot start was backed off to clear the observed cloud
            (:attr:`pushtorch.prediction.PushCondition.backoff`).
        selected: ``(N, A)`` index into ``model_names`` of the model that made each prediction.
        model_names: names of the candidate models.
        fingerprint: what the set was computed from (a cached set is reused only if it matches).
        densities: per condition and action, ``{method: PoseDensity}`` of the methods that predict a
            density (``pushtorch``, ``mean_motion``, ``physics_ensemble``), kept in memory for
            :func:`~pushtorch.experiments.scoring.likelihood_scores`; None for a set read from the cache (its
            scores were cached with it).
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
    residual_start: se3.Pose | None = None
    residual_final: se3.Pose | None = None

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
        if self.residual_final is not None:
            out["pushtorch_residual"] = (self.residual_start, self.residual_final)
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
    """One prediction kept in memory for the recording (index of its condition and action), the residual
    model's prediction of the same push where the group has one (``pushtorch_residual``), and the draws of
    their densities where a task made them (:func:`pushtorch.viz.densities.draw_density`; None: drawn when
    logged)."""

    condition: int
    action: int
    prediction: Any
    features: SurfaceFeatures
    residual: Any = None
    drawn: Any = None
    residual_drawn: Any = None


@dataclass
class Examples:
    """The predictions of one group that the recording logs (:func:`pushtorch.experiments.recording.log_examples`).

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


def cache_name(ctx: ExperimentContext, key: str) -> str:
    """A group's cache name: its key, tagged when the test pushes start off-centre (``test_placement``) and
    outside the default pybullet world (``_mujoco``), so both test sets' and both engines' predictions, scores
    and ground truth keep apart in one run folder (:func:`pushtorch.experiments.training.engine_tag`,
    :func:`~pushtorch.experiments.training.placement_tag`)."""
    key += engine_tag(ctx)
    if ctx.test_placement is None:
        return key
    return f"{key}_test_spread{placement_tag(ctx.test_placement)}"


def scores_path(ctx: ExperimentContext, key: str) -> Path:
    """Where a group's likelihood scores are cached: ``<run_dir>/scores/<cache name>.npz`` (written with its
    prediction set's fingerprint; a set is reused from the cache only with its scores)."""
    return contained_path(ctx.run_dir, "scores", f"{cache_name(ctx, key)}.npz",
                          what="experiment, object or prior name")


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
    residual: Mapping[str, Any] | None = None,
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
        truth: :func:`~pushtorch.experiments.scoring.truth_fingerprint` of the ground truth the set will be
            scored against: a cached set is reused only with the likelihood scores of that truth
            (:func:`~pushtorch.experiments.scoring.likelihood_scores`), since the densities they need are not
            cached.
        physics: (mass kg, ground friction) of the physics baselines (the training prior's means), or None
            to skip them.
        ensemble: (friction prior, mass prior, rollouts) of the ``physics_ensemble`` peer (the model's
            training prior; :func:`pushtorch.evaluation.baselines.physics_ensemble_prediction`), or None.
        residual: the :class:`~pushtorch.models.residual.ResidualModel` of each candidate model, by the model's
            name (``pushtorch_residual``, from the same robot start as the candidate's prediction), or None.
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
    n = int(poses.p.shape[0])
    choose = choose or (lambda i: 0)
    seed_key = seed_key or key
    made_from = _set_fingerprint(ctx, key, candidates, poses, adaptive, choose, physics, ensemble, seed_key,
                                 residual)
    path = contained_path(ctx.run_dir, "predictions", f"{cache_name(ctx, key)}.npz",
                          what="experiment, object or prior name")
    cached = _cached_set(ctx, key, path, made_from, truth)
    group = _GroupPredictor(ctx, key, obj, candidates, poses, choose, seed_key,
                            library=ModelLibrary(list(candidates)) if adaptive else None,
                            memo={} if memo is None else memo, residual=residual)
    choice = _logged_choice(ctx, examples)
    wanted = set(choice.known_before_truth(n)) if choice is not None else set()
    chosen = Examples(choice, group.kept, group.again) if choice is not None else Examples()
    kept_path = examples_path(ctx, key)
    if cached is not None:
        if bar is not None:
            bar.update(n * int(ctx.actions.shape[0]))
        kept = load_examples(kept_path, made_from, wanted) if wanted else None
        if kept is not None:  # kept by the task that predicted the set: nothing to predict (or compile) here
            group.kept.extend(kept)
        elif wanted:
            for i in sorted(wanted):  # the logged examples only: same seeds, same predictions
                _, features = observe(obj, poses.take(i), ctx.settings)
                group.predict_condition(i, features, True)
            if ctx.keep_examples:  # a task of a resumed run: for the submitting process to log
                save_examples(kept_path, made_from, wanted, group.kept)
        if ctx.recording is not None:
            kept_path.unlink(missing_ok=True)  # logged from memory now; a rerun predicts them again
        return cached, chosen
    result = _predict_conditions(group, wanted, physics, ensemble, made_from, bar, residual)
    if ctx.keep_examples and wanted:  # before the set: a set on disk finds its examples there too
        save_examples(kept_path, made_from, wanted, group.kept)
    result.save(path)
    scores_path(ctx, key).unlink(missing_ok=True)  # scores of an older set must not pass for this one's
    return result, chosen


def examples_path(ctx: ExperimentContext, key: str) -> Path:
    """Where a task keeps a group's logged examples for the submitting process: ``<run_dir>/examples/<cache
    name>.pt`` (every action's prediction whole, with its history and cloud; about 3.5 MB each at the quickstart's
    sizes). The submitting process reads it when it logs them, then removes it."""
    return contained_path(ctx.run_dir, "examples", f"{cache_name(ctx, key)}.pt",
                          what="experiment, object or prior name")


def _set_fingerprint(ctx: ExperimentContext, key: str, candidates: Sequence[PushModel], poses: se3.Pose,
                     adaptive: bool, choose: Callable[[int], int], physics: tuple[float, float] | None,
                     ensemble: tuple[Any, Any, int] | None, seed_key: str,
                     residual: Mapping[str, Any] | None = None) -> str:
    """What a group's prediction set is made from (a cached set is reused only if it matches)."""
    return fingerprint(
        key=key, seed=ctx.seed, seed_key=seed_key, models=[m.name for m in candidates], adaptive=adaptive,
        choice=[choose(i) for i in range(int(poses.p.shape[0]))], settings=asdict(ctx.settings),
        poses=poses.p.tolist() + poses.q.tolist(), actions=ctx.actions.tolist(),
        physics=physics, samples_per_action=ctx.samples_per_action, version=PREDICTION_VERSION,
        engines=[ctx.sim.engine, ctx.physics.engine],
        **({} if ensemble is None else {"ensemble": [repr(ensemble[0]), repr(ensemble[1]), int(ensemble[2])]}),
        **({} if residual is None else {"residual": {name: [r.ensemble, r.engine_version, r.meta]
                                                     for name, r in sorted(residual.items())}}),
    )


def _cached_set(ctx: ExperimentContext, key: str, path: Path, made_from: str, truth: str) -> PredictionSet | None:
    """The group's cached set at ``path`` if it was made from ``made_from`` and its cached scores from it and
    ``truth``; None otherwise (an unreadable file is recomputed, with a warning)."""
    if not (path.is_file() and scores_path(ctx, key).is_file()):
        return None
    try:
        cached = PredictionSet.load(path)
        _, scores_meta = load_arrays(scores_path(ctx, key))
    except RecordFormatError as exc:
        log.warning("recomputing %s: %s", key, exc)
        return None
    if cached.fingerprint != made_from or scores_meta.get("made_from") != scores_made_from(made_from, truth):
        return None
    return cached


def _logged_choice(ctx: ExperimentContext, examples: LogConditions | int | None) -> LogConditions | None:
    """Which conditions the recording logs (an int k: the first k); None without a recording (a task of a run that
    records keeps them: ``keep_examples``)."""
    if isinstance(examples, int) and not isinstance(examples, bool):
        examples = LogConditions("first", examples)
    return examples if ctx.recording is not None or ctx.keep_examples else None


@dataclass
class _GroupPredictor:
    """How one group predicts a test condition: its models (one chosen per condition by ``choose``, or by the
    ``library``'s ``H_r`` on each cloud), its seeds, the memo it shares with the groups of its ``seed_key``, and
    the examples it keeps whole for the recording."""

    ctx: ExperimentContext
    key: str
    obj: ObjectModel
    candidates: Sequence[PushModel]
    poses: se3.Pose
    choose: Callable[[int], int]
    seed_key: str
    library: ModelLibrary | None
    memo: dict
    kept: list[Example] = field(default_factory=list)
    residual: Mapping[str, Any] | None = None

    def test_start(self, i: int, j: int) -> se3.Pose | None:
        """The placement_spread start of condition ``i``, action ``j`` (None: the model's own)."""
        ctx = self.ctx
        if ctx.test_placement is None:
            return None
        return spread_test_start(self.obj, self.poses.take(i), ctx.test_placement,
                                 torch.Generator().manual_seed(stable_seed(ctx.seed, self.seed_key, i, j,
                                                                           "placement")))

    def predict_condition(self, i: int, features: SurfaceFeatures, record: bool,
                          into: list[Example] | None = None) -> tuple[int, list[dict]]:
        """Model index and, per action, the derived poses of condition ``i`` (with ``record``, its predictions
        go to ``into`` whole, by default :attr:`kept`)."""
        into = self.kept if into is None else into
        index = int(self.library.select(features)[1].argmin()) if self.library is not None else self.choose(i)
        model = self.candidates[index]
        derived = []
        for j in range(int(self.ctx.actions.shape[0])):
            memo_key = (i, model.name, j)
            if memo_key in self.memo and not record:
                derived.append(self.memo[memo_key])
                continue
            self.memo[memo_key], prediction = self._derive(model, i, j, features, record)
            derived.append(self.memo[memo_key])
            if record:
                peer = None if self.residual is None else _residual_peer(
                    self.ctx, features, self.memo[memo_key], j, self.residual[model.name],
                    stable_seed(self.ctx.seed, self.seed_key, i, j, "residual"))
                into.append(Example(i, j, prediction, features, peer))
        return index, derived

    def _derive(self, model: PushModel, i: int, j: int, features: SurfaceFeatures, record: bool) -> tuple[dict, Any]:
        """``model``'s prediction of condition ``i``, action ``j``, and the poses and densities derived from it:
        the start, estimate and final pose, the mean-motion and nearest-push baselines from the same start, the
        back-off and the densities of ``pushtorch`` and ``mean_motion``."""
        from pushtorch.evaluation.baselines import mean_motion_prediction, nearest_push_prediction
        from pushtorch.evaluation.likelihood import mean_motion_density, motion_product_density
        from pushtorch.prediction import contact_bandwidth, predict

        ctx = self.ctx
        generator = torch.Generator().manual_seed(stable_seed(ctx.seed, self.seed_key, i, j))
        prediction = predict(model, features, ctx.actions[j], generator, record_history=record,
                             robot_start=self.test_start(i, j))
        condition = prediction.condition
        motion = model.motions[model.action_index(ctx.actions[j])]
        start, estimate = condition.robot_start, condition.object_pose
        scoring = torch.Generator().manual_seed(stable_seed(ctx.seed, self.seed_key, i, j, "likelihood"))
        derived = {
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
        return derived, prediction

    def again(self, i: int) -> list[Example]:
        """Condition ``i``'s predictions, made again with its seeds (the set's own), whole."""
        n = int(self.poses.p.shape[0])
        if not 0 <= i < n:
            raise InvalidParameterError(f"{self.key} has test conditions 0..{n - 1}, not {i}")
        _, features = observe(self.obj, self.poses.take(i), self.ctx.settings)
        out: list[Example] = []
        self.predict_condition(i, features, True, out)
        return out


#: The pose fields a set predicts per condition and action, in :class:`PredictionSet`'s order.
_PREDICTED = ("robot_start", "estimate", "final", "mean_motion", "nearest", "oracle", "cloud_start", "cloud_final",
              "ensemble_start", "ensemble_final", "residual_start", "residual_final")


def _predict_conditions(group: _GroupPredictor, wanted: set[int], physics: tuple[float, float] | None,
                        ensemble: tuple[Any, Any, int] | None, made_from: str, bar,
                        residual: Mapping[str, Any] | None = None) -> PredictionSet:
    """Predict every condition and action of ``group`` with its baselines (the physics ones with ``physics``,
    the ensemble with ``ensemble``, the residual model with ``residual``); the conditions in ``wanted`` are kept
    whole for the recording."""
    ctx, obj, poses = group.ctx, group.obj, group.poses
    n, a_count = int(poses.p.shape[0]), int(ctx.actions.shape[0])
    fields: dict[str, list] = {name: [] for name in _PREDICTED}
    selected = torch.zeros(n, a_count, dtype=torch.int64)
    backoff = torch.zeros(n, a_count)
    densities: list[list[dict]] = []
    for i in range(n):
        _, features = observe(obj, poses.take(i), ctx.settings)
        index, derived = group.predict_condition(i, features, i in wanted)
        selected[i] = index
        densities.append([dict(d["densities"]) for d in derived])  # a copy: memo entries are shared
        for j, poses_ij in enumerate(derived):
            for name in ("robot_start", "estimate", "final", "mean_motion", "nearest"):
                fields[name].append(poses_ij[name])
            backoff[i, j] = poses_ij["backoff"]
            if physics is not None:
                for name, pose in zip(("oracle", "cloud_start", "cloud_final"),
                                      _physics_peers(ctx, obj, features, poses_ij, poses.take(i), j, physics),
                                      strict=True):
                    fields[name].append(pose)
            if ensemble is not None:
                rollouts = torch.Generator().manual_seed(stable_seed(ctx.seed, group.seed_key, i, j, "ensemble"))
                start, final, density = _ensemble_peer(ctx, features, poses_ij, j, ensemble,
                                                       group.candidates[index], rollouts)
                fields["ensemble_start"].append(start)
                fields["ensemble_final"].append(final)
                densities[-1][j]["physics_ensemble"] = density
            if residual is not None:  # a kept example's is the same prediction (same seed): not made twice
                made = next((e.residual for e in group.kept if (e.condition, e.action) == (i, j)), None)
                if made is None:
                    made = _residual_peer(ctx, features, poses_ij, j, residual[group.candidates[index].name],
                                          stable_seed(ctx.seed, group.seed_key, i, j, "residual"))
                fields["residual_start"].append(made.start)
                fields["residual_final"].append(made.final_pose)
                densities[-1][j]["pushtorch_residual"] = made.density
            if bar is not None:
                bar.update(1)
    return PredictionSet(
        truth_initial=se3.Pose.unchecked(poses.p.float(), poses.q.float()),
        **{name: _stacked(fields[name], n, a_count) for name in _PREDICTED},
        backoff=backoff,
        selected=selected,
        model_names=[m.name for m in group.candidates],
        fingerprint=made_from,
        densities=densities,
    )


def _physics_peers(ctx: ExperimentContext, obj: ObjectModel, features: SurfaceFeatures, derived: dict,
                   truth_initial: se3.Pose, j: int,
                   physics: tuple[float, float]) -> tuple[se3.Pose, se3.Pose, se3.Pose]:
    """The physics baselines of one prediction, pushed from its robot start with ``physics`` (mass, friction):
    ``oracle_physics``'s final pose (the true mesh from the true pose) and ``physics_from_cloud``'s start and
    final pose (the body the cloud reconstructs, from the estimate)."""
    from pushtorch.evaluation.baselines import oracle_physics_prediction, physics_from_cloud_prediction

    oracle = oracle_physics_prediction(obj, derived["robot_start"], truth_initial, ctx.actions[j], *physics,
                                       settings=ctx.physics)
    cloud_start, cloud_final = physics_from_cloud_prediction(
        features.p, derived["estimate"], derived["robot_start"], ctx.actions[j], *physics, settings=ctx.physics)
    return oracle, cloud_start, cloud_final


def _ensemble_peer(ctx: ExperimentContext, features: SurfaceFeatures, derived: dict, j: int,
                   ensemble: tuple[Any, Any, int], model: PushModel,
                   rollouts: torch.Generator) -> tuple[se3.Pose, se3.Pose, Any]:
    """The ``physics_ensemble`` peer of one prediction: the cloud's body before the push, its most probable
    rollout (the outcome of highest density under the ensemble's own) and that density (kernels of ``model``'s
    motion bandwidth)."""
    from pushtorch.evaluation.baselines import physics_ensemble_prediction
    from pushtorch.evaluation.likelihood import ensemble_density

    start, finals = physics_ensemble_prediction(
        features.p, derived["estimate"], derived["robot_start"], ctx.actions[j], ensemble[0], ensemble[1],
        int(ensemble[2]), rollouts, settings=ctx.physics)
    density = ensemble_density(finals, model.settings.motion_p_std, model.settings.motion_rot_std)
    best = int(density.log_prob(finals.vector().double()).argmax())
    return start, finals.take(best), density


def _residual_peer(ctx: ExperimentContext, features: SurfaceFeatures, derived: dict, j: int, residual,
                   seed: int):
    """The ``pushtorch_residual`` prediction of one condition and action, from pushtorch's own robot start
    (:func:`pushtorch.prediction.residual.predict_residual`; its start, point and density are the set's; a model
    whose point is learned reports pushtorch's prediction of the same push, made already)."""
    from pushtorch.prediction.residual import predict_residual

    return predict_residual(residual, features, ctx.actions[j], seed, robot_start=derived["robot_start"],
                            learned=(derived["estimate"], derived["final"]))


def _stacked(items: list[se3.Pose], n: int, a_count: int) -> se3.Pose | None:
    """One field's poses of every condition and action as ``(N, A)`` float32 on the CPU (None: not predicted)."""
    if not items:
        return None
    flat = [se3.Pose.unchecked(p.p.reshape(3).float().cpu(), p.q.reshape(4).float().cpu()) for p in items]
    return se3.Pose.stack(flat).reshape(n, a_count)
