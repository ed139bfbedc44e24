"""Shared steps of the paper's experiments: training, test conditions, predictions, ground truth, records.

Paper, Experimental Setup (Fig. prediction_accuracy_methodology): *training* — full cloud, contact models,
simulated pushes (PDRs) under a training prior; *prediction* — a single-shot cloud of the test object,
a push condition chosen by the model (robot start pose, contact frames, initial-pose estimate), a
predicted final pose; *ground truth* — the same push simulated from the chosen robot start pose with
mass and friction drawn from the test condition's prior, ``truth_samples`` times per condition and
action. Everything here composes library calls; an experiment module only decides *what* to compare.

Caching (a re-run with the same run directory resumes): training pushes are resumable shards under
``<run_dir>/data/<object>_<friction>_<mass>/``, trained models ``<run_dir>/models/<same>.npz``, each
group's predictions ``<run_dir>/predictions/<key>.npz`` and its ground-truth pushes
``<run_dir>/truth/<key>/``. A cached file is reused only if it was made with the same settings.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.evaluation.metrics import Accuracy, accuracy, displaced
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.models.library import ModelLibrary, ModelSettings, PushModel, load_model, train_push_model
from pushtorch.objects import ObjectModel, load_object
from pushtorch.paths import contained_path
from pushtorch.perception import PointCloud
from pushtorch.sim.plan import Placement
from pushtorch.sim.priors import Prior, prior_from_config
from pushtorch.sim.world import SimSettings

__all__ = [
    "Example",
    "Examples",
    "ExperimentContext",
    "LOG_RULES",
    "LogConditions",
    "PredictionSet",
    "as_names",
    "compare",
    "context_from_config",
    "entity_label",
    "fingerprint",
    "load_arrays",
    "likelihood_scores",
    "load_test_objects",
    "log_examples",
    "merged_model_config",
    "observe",
    "plain",
    "predict_set",
    "progress_bar",
    "sample_test_poses",
    "save_arrays",
    "simulate_truth",
    "stable_seed",
    "summarise",
    "train_model",
    "training_records",
    "truth_fingerprint",
]

log = logging.getLogger("pushtorch.experiments")


def plain(cfg: Any) -> Any:
    """A Hydra/OmegaConf node as plain Python containers (resolved); anything else unchanged.

    Raises:
        InvalidParameterError: a mandatory value (``???`` in the config) was not given; the message names
            the key (otherwise the string ``???`` would travel on and be reported as a file name).
    """
    if isinstance(cfg, DictConfig) or OmegaConf.is_config(cfg):
        from omegaconf.errors import MissingMandatoryValue

        try:
            return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        except MissingMandatoryValue as exc:
            key = getattr(exc, "full_key", None) or "a mandatory value"
            raise InvalidParameterError(f"{key} is not set (it is mandatory): give it, e.g. {key}=<value>") from exc
    return cfg


def stable_seed(*parts: Any) -> int:
    """A 63-bit seed that is a pure function of ``parts`` (their ``str``), stable across runs and machines.

    Every random quantity of an experiment gets its own seed from the run seed and a name, so results
    do not depend on the order in which groups run or on which groups a run skips (resumption).
    """
    digest = hashlib.sha256("|".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def as_names(value: str | Sequence[str] | None) -> list[str]:
    """One name or a list of names (a Hydra sweep gives one, an experiment's default a list)."""
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


#: The rules of ``recording.conditions`` written ``<rule>:<k>`` (a list of indices is the fourth form).
LOG_RULES = ("first", "worst", "best")
#: Most test conditions one group logs (each logs every action: a recording grows by ~1 MB per prediction).
MAX_LOGGED_CONDITIONS = 100


@dataclass(frozen=True)
class LogConditions:
    """Which test conditions of a group the recording logs (config ``recording.conditions``).

    ``first:k``: conditions ``0 .. k-1``; ``worst:k`` / ``best:k``: the k with the highest / lowest H_acc
    (the group's primary score, :func:`compare_displacement`, against test condition 0's ground truth,
    averaged over actions and truth samples; ties to the lower index); a list: those indices, in that order.
    A group with fewer conditions logs those it has (an index it lacks is skipped, with a warning).

    Attributes:
        rule: ``first``, ``worst``, ``best`` or ``list``.
        count: k of the first three rules.
        indices: the listed indices (rule ``list``).
    """

    rule: str = "first"
    count: int = 1
    indices: tuple[int, ...] = ()

    @staticmethod
    def parse(value: Any, default_count: int = 1, key: str = "recording.conditions") -> LogConditions:
        """The choice a config value names; None: ``first:<default_count>`` (``experiment.log_examples``).

        Raises:
            InvalidParameterError: anything but ``first:k``, ``worst:k``, ``best:k`` (0 <= k <= 100) or a
                list of distinct integer indices >= 0 (at most 100), in one line naming ``key``.
        """
        usage = (f"{key} must be first:k, worst:k or best:k (0 <= k <= {MAX_LOGGED_CONDITIONS}) or a list of "
                 "test-condition indices such as [0, 2]")
        if value is None:
            value = f"first:{default_count}"
        if isinstance(value, str):
            rule, colon, count = value.strip().partition(":")
            if not colon or rule not in LOG_RULES or not count.strip().isdigit():
                raise InvalidParameterError(f"{usage}, got {value!r}")
            k = int(count)
            if k > MAX_LOGGED_CONDITIONS:
                raise InvalidParameterError(f"{usage}, got {value!r}")
            return LogConditions(rule, k)
        if isinstance(value, Sequence) and not isinstance(value, bytes):
            items = list(value)
            if len(items) > MAX_LOGGED_CONDITIONS or not all(
                    isinstance(i, int | np.integer) and not isinstance(i, bool) and i >= 0 for i in items):
                raise InvalidParameterError(f"{usage}, got {items!r}")
            if len(set(items)) != len(items):
                raise InvalidParameterError(f"{key} lists a test condition twice: {items!r}")
            return LogConditions("list", len(items), tuple(int(i) for i in items))
        hint = (f": for the first {value} write first:{value}, for condition {value} alone [{value}]"
                if isinstance(value, int) and not isinstance(value, bool) else "")
        raise InvalidParameterError(f"{usage}, got {value!r} ({type(value).__name__}){hint}")

    @property
    def by_hacc(self) -> bool:
        """Whether the choice needs the group's ground truth (``worst`` and ``best``)."""
        return self.rule in ("worst", "best")

    def __str__(self) -> str:
        return repr(list(self.indices)) if self.rule == "list" else f"{self.rule}:{self.count}"

    def known_before_truth(self, n: int) -> list[int]:
        """The conditions of a group of ``n`` chosen before its ground truth exists (none for worst and best)."""
        if self.rule == "first":
            return list(range(min(self.count, n)))
        if self.rule == "list":
            return [i for i in self.indices if i < n]
        return []

    def choose(self, hacc: torch.Tensor) -> list[int]:
        """The conditions chosen, given each condition's H_acc ``(N,)`` (used by worst and best only; NaN
        counts as the worst)."""
        n = int(hacc.shape[0])
        if not self.by_hacc:
            return self.known_before_truth(n)
        score = torch.nan_to_num(hacc.detach().double().cpu(), nan=math.inf)
        order = torch.sort(score if self.rule == "best" else -score, stable=True).indices
        return order[: self.count].tolist()


@dataclass
class ExperimentContext:
    """Everything the experiment steps share: where to cache, how to train, simulate and log.

    Attributes:
        run_dir: the run directory (caches and outputs).
        seed: the run seed.
        settings: model settings for training and prediction.
        samples_per_action: training pushes per action (paper: 500).
        actions: ``(A, 2)`` the actions (ẋ m/s, θ̇ rad/s), float32.
        duration: s per push.
        sim: simulator settings (training and ground truth alike).
        priors: ``{"friction": {name: Prior}, "mass": {name: Prior}}``.
        workers: simulation processes (0: all cores); shard_size: pushes per shard.
        progress: show tqdm progress bars.
        recording: an open Rerun recording, or None.
        log_examples: which test conditions per part and object have their predictions (every action)
            logged: ``recording.conditions``, default the first ``experiment.log_examples``.
        logged_predictions: ``(root entity path, summary)`` of every prediction :func:`log_examples` logged
            (for the recording's blueprint and part summaries; shared by :meth:`with_model` contexts).
        placement: how training places the robot (``model.placement``; default the paper's single
            placement, see docs/method.md "Training placement").
        test_placement: None (default): every test push starts where the model's contact model puts the
            robot; a :class:`Placement`: the ``placement_spread`` test set (``test_placement=spread``), the
            robot placed off-centre against the test object by that law and the model predicting from there.
    """

    run_dir: Path
    seed: int
    settings: ModelSettings
    samples_per_action: int
    actions: torch.Tensor
    duration: float
    sim: SimSettings
    priors: dict[str, dict[str, Prior]]
    workers: int = 0
    shard_size: int = 100
    progress: bool = True
    recording: Any = None
    log_examples: LogConditions = field(default_factory=LogConditions)
    placement: Placement = Placement()
    test_placement: Placement | None = None
    logged_predictions: list[tuple[str, str]] = field(default_factory=list, repr=False)
    _models: dict[str, PushModel] = field(default_factory=dict, repr=False)
    _slots: list[int] = field(default_factory=lambda: [0], repr=False)
    # the last ground-truth plan and its (C, N, A, S) shape, keyed by the predictions' fingerprint:
    # log_examples re-simulates its examples' pushes from it (set only while recording)
    _truth_plan: tuple[str, Any, tuple[int, ...]] | None = field(default=None, repr=False)

    def prior(self, kind: str, name: str) -> Prior:
        """The prior ``priors.<kind>.<name>`` (kind: ``friction`` or ``mass``).

        Raises:
            InvalidParameterError: no such prior in the config.
        """
        table = self.priors.get(kind, {})
        if name not in table:
            raise InvalidParameterError(
                f"no {kind} prior named {name!r} in this experiment's config (priors.{kind}: "
                f"{', '.join(sorted(table)) or 'none'}); add it with +priors.{kind}.{name}={{kind: normal, "
                "mean: ..., std: ...}}"
            )
        return table[name]

    def with_model(self, model_cfg: Mapping[str, Any]) -> ExperimentContext:
        """The same context with another model config's settings, training size and placement."""
        settings = ModelSettings.from_mapping(model_cfg.get("settings", {}))
        samples = int(model_cfg.get("samples_per_action", self.samples_per_action))
        placement = _model_placement(model_cfg) if "placement" in model_cfg else self.placement
        # the model and slot caches stay shared: replace passes the same dict and list on
        return replace(self, settings=settings, samples_per_action=samples, placement=placement)

    def next_slot(self) -> tuple[float, float]:
        """Where the next logged example goes in the recording: a grid of 1.5 m cells from (0, 1.5)."""
        k = self._slots[0]
        self._slots[0] += 1
        return 1.5 * (k % 8), 1.5 * (1 + k // 8)


def merged_model_config(base: Mapping[str, Any], override: Mapping[str, Any] | None) -> dict[str, Any]:
    """``base`` (the ``model`` config) with a part's ``model`` overrides merged in (nested dicts merge)."""
    merged = OmegaConf.merge(OmegaConf.create(plain(base)), OmegaConf.create(plain(override or {})))
    return OmegaConf.to_container(merged, resolve=True)


def _placement(entry: Mapping[str, Any] | None, name: str, known: Sequence[str]) -> Placement:
    """A :class:`Placement` from the config mapping ``name`` whose keys may be ``known``."""
    entry = entry or {}
    unknown = set(entry) - set(known)
    if unknown:
        raise InvalidParameterError(f"unknown {name} keys {sorted(unknown)}; known: {', '.join(known)}")
    return Placement(**{k: float(v) for k, v in entry.items()})


def _model_placement(model_cfg: Mapping[str, Any]) -> Placement:
    """Where training places the robot (``model.placement``)."""
    return _placement(model_cfg.get("placement"), "model.placement",
                      ("gap", "lateral_jitter", "yaw_jitter_deg", "object_yaw_deg"))


def _test_placement(entry: Mapping[str, Any] | None) -> Placement | None:
    """None for the model's own starts (``test_placement=model``), else the spread set's placement."""
    entry = dict(entry or {})
    if not entry.pop("spread", False):
        return None
    return _placement(entry, "test_placement", ("gap", "lateral_jitter", "yaw_jitter_deg"))


def context_from_config(cfg: DictConfig | Mapping[str, Any], run_dir: str | Path) -> ExperimentContext:
    """Build the context from a composed experiment config (keys ``seed``, ``model``, ``priors``, ``sim``,
    ``experiment.actions``, ``experiment.workers``, ``recording.conditions``, ...).

    Raises:
        InvalidParameterError: an invalid model setting, prior or size.
    """
    from pushtorch.sim.push import make_actions

    c = plain(cfg)
    exp = c.get("experiment", {})
    model_cfg = c.get("model", {})
    actions_cfg = exp.get("actions", {})
    priors = {
        kind: {name: prior_from_config(p) for name, p in (c.get("priors", {}).get(kind) or {}).items()}
        for kind in ("friction", "mass")
    }
    samples = int(model_cfg.get("samples_per_action", 500))
    if samples < 1:
        raise InvalidParameterError(f"model.samples_per_action must be >= 1, got {samples}")
    return ExperimentContext(
        run_dir=Path(run_dir),
        seed=int(c.get("seed", 0)),
        settings=ModelSettings.from_mapping(model_cfg.get("settings", {})),
        samples_per_action=samples,
        actions=make_actions(
            int(actions_cfg.get("count", 3)),
            tuple(actions_cfg.get("angle_range_deg", (-10.0, 10.0))),
            float(actions_cfg.get("speed", 0.1)),
        ),
        duration=float(actions_cfg.get("duration", 4.0)),
        sim=SimSettings(**(c.get("sim") or {})),
        priors=priors,
        workers=int(exp.get("workers", 0)),
        shard_size=int(exp.get("shard_size", 100)),
        progress=bool(exp.get("progress", True)),
        log_examples=LogConditions.parse((c.get("recording") or {}).get("conditions"),
                                         int(exp.get("log_examples", 1))),
        placement=_model_placement(model_cfg),
        test_placement=_test_placement(c.get("test_placement")),
    )


def progress_bar(ctx: ExperimentContext, total: int, desc: str):
    """A tqdm bar of ``total`` steps (disabled when ``ctx.progress`` is false)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="pred", disable=not ctx.progress, dynamic_ncols=True)


def load_test_objects(cfg: DictConfig | Mapping[str, Any], default: Sequence[str]) -> list[ObjectModel]:
    """The test objects: ``object=<name>`` (or ``object=mesh object.path=...``) if given, else ``default``."""
    c = plain(cfg)
    chosen = c.get("object")
    if chosen:
        return [load_object(chosen["name"], chosen.get("path"), float(chosen.get("scale", 1.0)),
                            up=chosen.get("up", "z"))]
    return [load_object(name) for name in default]


# --- training ---------------------------------------------------------------------------------------


def _model_key(obj_name: str, friction: str, mass: str) -> str:
    return f"{obj_name}_{friction}_{mass}"


def _placement_tag(placement: Placement) -> str:
    """'' for the paper's placement, else a suffix naming what differs from it, e.g. ``_lateral_jitter0.05``
    (cached pushes and models of each placement keep apart)."""
    paper = asdict(Placement())
    return "".join(f"_{k}{v:g}" for k, v in asdict(placement).items() if v != paper[k])


def _training_folder(ctx: ExperimentContext, obj_name: str, friction: str, mass: str) -> Path:
    return contained_path(ctx.run_dir, "data", _model_key(obj_name, friction, mass) + _placement_tag(ctx.placement),
                          what="object or prior name")


def training_records(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str,
                     progress: bool | None = None):
    """The training pushes of ``obj`` under the named priors, simulated into the run's cache if missing.

    Paper, Experimental Setup: the robot placed against the object, mass and friction drawn from the
    training prior, ``samples_per_action`` pushes per action.
    """
    from pushtorch.sim.plan import plan_training_pushes
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.world import object_spec

    plan = plan_training_pushes(
        obj, ctx.actions, ctx.samples_per_action, ctx.prior("mass", mass), ctx.prior("friction", friction),
        seed=stable_seed(ctx.seed, "training", obj.name, friction, mass), duration=ctx.duration,
        placement=ctx.placement,
    )
    folder = _training_folder(ctx, obj.name, friction, mass)
    run_plan(object_spec(obj), plan, folder, ctx.sim, workers=ctx.workers, shard_size=ctx.shard_size,
             progress=ctx.progress if progress is None else progress)
    return load_records(folder)


def train_model(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str) -> PushModel:
    """A model of ``obj`` trained under the named friction and mass priors (cached in the run directory).

    The model file is reused when its settings and training size match the context's; otherwise the
    model is retrained from the (cached) training pushes.
    """
    key = _model_key(obj.name, friction, mass)
    meta = {"friction": friction, "mass": mass, "samples_per_action": ctx.samples_per_action,
            "seed": ctx.seed}
    if ctx.placement != Placement():  # absent at the paper's placement, so earlier caches stay valid
        meta["placement"] = asdict(ctx.placement)
    cache_key = (f"{key}|{json.dumps(asdict(ctx.settings), sort_keys=True)}|{ctx.samples_per_action}"
                 f"|{_placement_tag(ctx.placement)}")
    if cache_key in ctx._models:
        return ctx._models[cache_key]
    path = contained_path(ctx.run_dir, "models", f"{key}{_placement_tag(ctx.placement)}.npz",
                          what="object or prior name")
    model = None
    if path.is_file():
        try:
            cached = load_model(path)
        except RecordFormatError as exc:
            log.warning("retraining %s: %s", key, exc)
        else:
            trained_meta = {k: v for k, v in cached.meta.items() if k != "bandwidths"}
            if cached.configured_settings == ctx.settings and trained_meta == meta:
                model = cached
    if model is None:
        records = training_records(ctx, obj, friction, mass)
        log.info("training %s on %d pushes (%d valid)", key, len(records), int(records.valid.sum()))
        model = train_push_model(obj, records, ctx.settings, name=key,
                                 generator=torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key)),
                                 meta=meta)
        model.save(path)
    if ctx.recording is not None and all(m.name != model.name for m in ctx._models.values()):
        _log_training(ctx, model, obj)
    ctx._models[cache_key] = model
    return model


def _log_training(ctx: ExperimentContext, model: PushModel, obj: ObjectModel) -> None:
    from pushtorch.viz.model import log_contact_model

    # one row of trained models along +x at y = -1.5 m, clear of the experiments around the origin
    index = len({m.name for m in ctx._models.values()})
    log_contact_model(ctx.recording, model, obj, object_pose=obj.resting_pose(x=1.0 * index, y=-1.5))


# --- test conditions ----------------------------------------------------------------------------------


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


# --- predictions --------------------------------------------------------------------------------------


def save_arrays(path: Path, arrays: Mapping[str, torch.Tensor], meta: Mapping[str, Any]) -> None:
    """Write tensors and a JSON-able ``meta`` atomically as one plain ``.npz`` (read without pickle)."""
    from pushtorch.io import atomic_write_bytes

    buffer = io.BytesIO()
    np.savez(buffer, __meta__=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
             **{k: v.detach().cpu().numpy() for k, v in arrays.items()})
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buffer.getvalue())


def load_arrays(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a file written by :func:`save_arrays`.

    Raises:
        RecordFormatError: a missing, unreadable or foreign file.
    """
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {k: archive[k] for k in archive.files}
        meta = json.loads(arrays.pop("__meta__").tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise RecordFormatError(f"{path} is not a readable pushtorch cache file: {exc}") from exc
    return {k: torch.from_numpy(v) for k, v in arrays.items()}, meta


def fingerprint(**inputs: Any) -> str:
    """SHA-256 of JSON-able inputs: a cached result is reused only if what made it is unchanged."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()


_POSE_FIELDS = ("truth_initial", "robot_start", "estimate", "final", "mean_motion", "nearest", "oracle",
                "cloud_start", "cloud_final")
#: Bump when the predictions a cached set holds would come out differently for the same settings (collision-free
#: starts, new baselines): cached sets of an older version are recomputed.
PREDICTION_VERSION = 3


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
        backoff: ``(N, A)`` metres each robot start was backed off to clear the observed cloud
            (:attr:`pushtorch.predict.PushCondition.backoff`).
        selected: ``(N, A)`` index into ``model_names`` of the model that made each prediction.
        model_names: names of the candidate models.
        fingerprint: what the set was computed from (a cached set is reused only if it matches).
        densities: per condition and action, ``{method: PoseDensity}`` of the methods that predict a
            density (``pushtorch``, ``mean_motion``), kept in memory for :func:`likelihood_scores`; None
            for a set read from the cache (its scores were cached with it).
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

    @property
    def invalid_starts(self) -> int:
        """How many robot starts needed more back-off than :data:`pushtorch.predict.MAX_BACKOFF` (invalid
        conditions, pushed from the cleared start all the same)."""
        from pushtorch.predict import MAX_BACKOFF

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
    """A group's cache name: its key, tagged when the test pushes start off-centre (``test_placement``), so
    both test sets' predictions, scores and ground truth keep apart in one run folder."""
    if ctx.test_placement is None:
        return key
    return f"{key}_test_spread{_placement_tag(ctx.test_placement)}"


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
        physics_from_cloud_prediction,
    )
    from pushtorch.evaluation.likelihood import mean_motion_density, motion_product_density
    from pushtorch.predict import contact_bandwidth, predict

    n, a_count = int(poses.p.shape[0]), int(ctx.actions.shape[0])
    choose = choose or (lambda i: 0)
    seed_key = seed_key or key
    made_from = fingerprint(
        key=key, seed=ctx.seed, seed_key=seed_key, models=[m.name for m in candidates], adaptive=adaptive,
        choice=[choose(i) for i in range(n)], settings=asdict(ctx.settings),
        poses=poses.p.tolist() + poses.q.tolist(), actions=ctx.actions.tolist(),
        physics=physics, samples_per_action=ctx.samples_per_action, version=PREDICTION_VERSION,
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

    names = ("robot_start", "estimate", "final", "mean_motion", "nearest", "oracle", "cloud_start", "cloud_final")
    fields: dict[str, list] = {name: [] for name in names}
    selected = torch.zeros(n, a_count, dtype=torch.int64)
    backoff = torch.zeros(n, a_count)
    densities: list[list[dict]] = []
    for i in range(n):
        _, features = observe(obj, poses.take(i), ctx.settings)
        index, derived = predict_condition(i, features, i in wanted)
        selected[i] = index
        densities.append([d["densities"] for d in derived])
        for j, poses_ij in enumerate(derived):
            for name in ("robot_start", "estimate", "final", "mean_motion", "nearest"):
                fields[name].append(poses_ij[name])
            backoff[i, j] = poses_ij["backoff"]
            if physics is not None:
                fields["oracle"].append(oracle_physics_prediction(
                    obj, poses_ij["robot_start"], poses.take(i), ctx.actions[j], *physics))
                cloud_start, cloud_final = physics_from_cloud_prediction(
                    features.p, poses_ij["estimate"], poses_ij["robot_start"], ctx.actions[j], *physics)
                fields["cloud_start"].append(cloud_start)
                fields["cloud_final"].append(cloud_final)
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
    density, in the displacement sense (:func:`pushtorch.evaluation.likelihood.nll`): ``{method: (C, N, A, S)}``.

    ``pushtorch`` and ``mean_motion`` are scored under their own densities; the point predictions under one
    kernel of the model's motion bandwidth (:func:`pushtorch.evaluation.likelihood.point_density`). Cached as
    ``<run_dir>/scores/<key>.npz`` with the set's and the truth's fingerprints (``truth``:
    :func:`truth_fingerprint`).

    Raises:
        RecordFormatError: the set came from the cache but its scores did not (they are written together).
    """
    from pushtorch.evaluation.likelihood import nll, point_density

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
        for i in range(n):
            for j in range(a_count):
                density = predictions.densities[i][j].get(method) or point_density(final.take((i, j)), p_std,
                                                                                  rot_std)
                truths = se3.Pose.unchecked(truth_final.p[:, i, j].reshape(-1, 3),
                                            truth_final.q[:, i, j].reshape(-1, 4))
                values = nll(density, truths, predictions.truth_initial.take(i), start.take((i, j)),
                             obj.symmetry)
                out[:, i, j] = values.reshape(c_count, samples).float()
        scores[method] = out
    save_arrays(path, scores, {"made_from": made_from})
    return scores


# --- ground truth -------------------------------------------------------------------------------------


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
    from pushtorch.sim.world import object_spec

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
    workers = 1 if len(plan) < 4 * ctx.shard_size else ctx.workers
    run_plan(object_spec(obj), plan, folder, ctx.sim, workers=workers, shard_size=ctx.shard_size,
             progress=False)
    records = load_records(folder)
    final = se3.Pose.unchecked(records.object_final.p.reshape(*shape, 3), records.object_final.q.reshape(*shape, 4))
    return final, (records.tipped | records.left_ground).reshape(shape)


# --- records ------------------------------------------------------------------------------------------


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
) -> dict[str, Any]:
    """One results.json record: a group's H_acc mean and std, and mean raw errors, over ``n`` comparisons.

    ``metric`` (prediction and selection records): ``displacement``, the predicted motion applied to the
    true start pose (:func:`pushtorch.evaluation.metrics.displaced`, the primary score), or ``frame``, the predicted
    final pose as it is (the estimated frame against the test object's own); pose records carry none.
    ``nll`` (displacement records): the per-comparison negative log-likelihoods of the truth under the
    method's density (:func:`likelihood_scores`), summarised as ``nll_mean`` and ``nll_median`` (nats)."""
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
    return record


# --- recording ----------------------------------------------------------------------------------------


def entity_label(*parts: str) -> str:
    """A prediction's entity path below ``world/model/prediction`` from words, one level each:
    ``entity_label("model_selection", "cube", "adaptive")`` is ``model_selection/cube/adaptive``. Within a
    level, anything outside ``[A-Za-z0-9_.-]`` (a ``/`` too) becomes ``_``
    (:func:`pushtorch.viz.core.entity_name`)."""
    from pushtorch.viz.core import entity_name

    return "/".join(entity_name(str(p).replace("/", "_")) for p in parts)


def _one_push(plan, k: int):
    """Push ``k`` of a :class:`~pushtorch.sim.plan.PushPlan` as a plan of its own (same index and seed)."""
    from pushtorch.sim.plan import PushPlan

    one = slice(k, k + 1)
    return PushPlan(
        object_name=plan.object_name,
        robot_start=se3.Pose.unchecked(plan.robot_start.p[one], plan.robot_start.q[one]),
        object_initial=se3.Pose.unchecked(plan.object_initial.p[one], plan.object_initial.q[one]),
        action=plan.action[one], mass=plan.mass[one], ground_friction=plan.ground_friction[one],
        action_index=plan.action_index[one], index=plan.index[one], seed=plan.seed, duration=plan.duration,
    )


def _truth_push(ctx: ExperimentContext, obj: ObjectModel, predictions: PredictionSet, i: int, j: int):
    """The ground-truth push shown with example ``(i, j)``: test condition 0, sample 0, re-simulated here
    with its trajectory (its final pose is compared with the recorded one by :func:`log_examples`: since
    every push rebuilds the object's shape they agree bit for bit; the check guards that); None if
    :func:`simulate_truth` did not run for these predictions while recording."""
    from pushtorch.sim.runner import simulate_plan
    from pushtorch.sim.world import object_spec

    if ctx._truth_plan is None or ctx._truth_plan[0] != predictions.fingerprint:
        log.warning("no ground-truth plan for %s: its pushes are not animated", predictions.fingerprint[:8])
        return None
    _, plan, (_, n, a_count, samples) = ctx._truth_plan
    return simulate_plan(object_spec(obj), _one_push(plan, (i * a_count + j) * samples), ctx.sim)


def _condition_hacc(predictions: PredictionSet, truth_final: se3.Pose, obj: ObjectModel) -> torch.Tensor:
    """Each test condition's H_acc ``(N,)``: the group's primary score (displacement) against the ground truth
    ``(N, A, S)``, averaged over actions and truth samples (what ``worst:k`` and ``best:k`` rank by)."""
    n, a_count = predictions.final.batch_shape
    acc = compare_displacement(predictions.estimate, predictions.final, predictions.truth_initial, truth_final, obj)
    return acc.hacc.double().reshape(n, a_count, -1).mean((1, 2))


def _chosen_examples(predictions: PredictionSet, examples: Examples, truth_final: se3.Pose,
                    obj: ObjectModel) -> tuple[list[Example], dict[int, float]]:
    """The examples ``examples.choice`` picks, in its order (each condition's actions in order), and each
    chosen condition's mean H_acc (:func:`_condition_hacc`; the ranking of ``worst`` and ``best``)."""
    choice = examples.choice
    if choice is None:
        return [], {}
    n = int(predictions.final.batch_shape[0])
    hacc = _condition_hacc(predictions, truth_final, obj)
    indices = choice.choose(hacc)
    if choice.rule == "list" and len(indices) < len(choice.indices):
        log.warning("recording.conditions %s: this group has test conditions 0..%d only; logging %s",
                    choice, n - 1, indices)
    if choice.by_hacc:
        if examples.again is None:
            raise InvalidParameterError("these examples cannot be predicted again: no predict_set behind them")
        picked = [e for i in indices for e in examples.again(i)]
    else:
        by_condition: dict[int, list[Example]] = {}
        for e in examples.kept:
            by_condition.setdefault(e.condition, []).append(e)
        picked = [e for i in indices for e in sorted(by_condition.get(i, []), key=lambda e: e.action)]
    return picked, {i: float(hacc[i]) for i in indices}


def log_examples(
    ctx: ExperimentContext,
    label: str,
    obj: ObjectModel,
    examples: Examples,
    predictions: PredictionSet,
    truth_final: se3.Pose,
    nll: torch.Tensor | None = None,
) -> None:
    """Log example predictions with their true initial and final poses, ground-truth push and density.

    The conditions logged are ``examples.choice`` (``recording.conditions``, :class:`LogConditions`), each
    with every action. Every example goes under ``world/model/prediction/<label>/c<i>a<j>`` (``label`` from
    :func:`entity_label`: ``<part>/<object>/<model or method>``; entities as in :mod:`pushtorch.viz.model`,
    the predicted density included), whose transform shifts it to a free cell of the recording's grid. Its
    ground-truth push (test condition 0, sample 0: the pose ``truth_final`` holds) is re-simulated in this
    process with its trajectory and played on ``sim_time`` at ``<root>/truth_push``; a re-simulated final
    pose that differs from the recorded one is reported in the log and the summary. ``<root>/summary``
    holds the example's scores as text, also kept in ``ctx.logged_predictions``: H_acc (displacement, the
    records' primary score, with the frame score beside it), ``nll`` (the records' score of that truth,
    :func:`likelihood_scores`) and the raw errors.

    Args:
        truth_final: ground-truth final poses ``(N, A, S)`` of test condition 0 (sample 0 is shown).
        nll: the group's ``pushtorch`` negative log-likelihoods ``(N, A, S)`` of the same truths
            (:func:`likelihood_scores` of test condition 0), or None (the summary then has none).
    """
    import rerun as rr

    from pushtorch.viz.model import PREDICTION, log_prediction

    if ctx.recording is None or not examples:
        return
    picked, condition_hacc = _chosen_examples(predictions, examples, truth_final, obj)
    for example in picked:
        i, j = example.condition, example.action
        root = f"{PREDICTION}/{label}/c{i}a{j}"
        x, y = ctx.next_slot()
        ctx.recording.log(root, rr.Transform3D(translation=[x, y, 0.0]), static=True)
        truth = truth_final.take((i, j, 0))
        push = _truth_push(ctx, obj, predictions, i, j)
        replay = "ground-truth push not re-simulated"
        if push is not None:
            gap = float((push.object_final.p[0].to(truth.p) - truth.p.reshape(3)).abs().max())
            same = torch.equal(push.object_final.p[0].to(truth.p), truth.p.reshape(3)) and torch.equal(
                push.object_final.q[0].to(truth.q), truth.q.reshape(4))
            replay = ("re-simulated ground-truth push ends at the recorded final pose" if same else
                      f"re-simulated ground-truth push ends {gap:.2e} m from the recorded final pose")
            if not same:
                log.warning("%s/c%da%d: %s", label, i, j, replay)
        truth_initial = predictions.truth_initial.take(i)
        log_prediction(ctx.recording, example.prediction, truth_initial, truth, obj,
                       label=f"{label}/c{i}a{j}", cloud=example.features, truth_push=push)
        estimate, final = predictions.estimate.take((i, j)), predictions.final.take((i, j))
        acc = accuracy(displaced(estimate, final, truth_initial), truth, obj)
        frame = accuracy(final, truth, obj)
        score = "nll –" if nll is None else f"nll {float(nll[i, j, 0]):.2f} nats (of this truth, displacement)"
        why = ("" if not examples.choice.by_hacc else
               f" ({examples.choice}: mean H_acc {condition_hacc[i]:.3f} over its actions and truth samples)")
        summary = (f"`{label}/c{i}a{j}`: condition {i}{why}, action {ctx.actions[j].tolist()}: "
                   f"H_acc {float(acc.hacc):.3f} (displacement; frame {float(frame.hacc):.3f}), {score}, "
                   f"linear {float(acc.linear_cm):.2f} cm, angular {float(acc.angular_deg):.1f} deg; {replay}")
        ctx.recording.log(f"{root}/summary", rr.TextDocument(summary, media_type=rr.MediaType.MARKDOWN),
                          static=True)
        ctx.logged_predictions.append((root, summary))
