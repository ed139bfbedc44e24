"""An experiment's context: its configuration as plain values, seeds, test objects, cached arrays and
fingerprints, and which conditions it records (paper, Experimental Setup).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.models.model import PushModel
from pushtorch.models.settings import ModelSettings
from pushtorch.objects import ObjectModel, load_object
from pushtorch.sim.executors import Executor, executor_from_config
from pushtorch.sim.plan import Placement
from pushtorch.sim.priors import Prior, prior_from_config
from pushtorch.sim.settings import SimSettings, settings_from_config

__all__ = [
    "ExperimentContext",
    "LOG_RULES",
    "LogConditions",
    "MAX_LOGGED_CONDITIONS",
    "SCORES_VERSION",
    "as_names",
    "context_from_config",
    "fingerprint",
    "load_arrays",
    "load_test_objects",
    "merged_model_config",
    "plain",
    "prior_pairs",
    "progress_bar",
    "save_arrays",
    "scores_made_from",
    "stable_seed",
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


def prior_pairs(node: Mapping[str, Any], what: str) -> list[tuple[str, str]]:
    """Every (friction, mass) pair of prior names in ``node["friction"]`` × ``node["mass"]`` (a name or a list each).

    Raises:
        InvalidParameterError: no friction or no mass name; ``what`` names the config section.
    """
    frictions, masses = as_names(node.get("friction")), as_names(node.get("mass"))
    if not frictions or not masses:
        raise InvalidParameterError(f"{what} needs at least one friction and one mass prior name")
    return [(f, m) for f in frictions for m in masses]


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
        sim: simulator settings of the world (training pushes and ground truth alike; ``world.engine``).
        physics: the same settings in the engine the physics peers roll out in (``physics.engine``).
        executor: where the training and ground-truth pushes' shards run (``executor``: local, ray, slurm).
        priors: ``{"friction": {name: Prior}, "mass": {name: Prior}}``.
        workers: simulation processes (0: all cores); shard_size: pushes per shard.
        progress: show tqdm progress bars.
        recording: an open Rerun recording, or None.
        keep_examples: a task's context for a run that records: its prediction sets keep the examples the
            recording logs and write them beside the set (:mod:`pushtorch.experiments.prediction_sets`), so the
            submitting process logs them without predicting (or compiling) anything.
        log_examples: which test conditions per part and object have their predictions (every action)
            logged: ``recording.conditions``, default the first ``experiment.log_examples``.
        logged_predictions: ``(root entity path, summary)`` of every prediction :func:`log_examples` logged
            (for the recording's blueprint and part summaries; shared by :meth:`with_model` contexts).
        task_counts: ``{"<kind> | <where>": count}`` of the tasks :func:`pushtorch.experiments.tasks.prefetch`
            ran (results.json's ``tasks``; shared by :meth:`with_model` contexts).
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
    physics: SimSettings = field(default_factory=SimSettings)
    executor: Executor = field(default_factory=Executor)
    workers: int = 0
    shard_size: int = 100
    progress: bool = True
    recording: Any = None
    keep_examples: bool = False
    log_examples: LogConditions = field(default_factory=LogConditions)
    placement: Placement = Placement()
    test_placement: Placement | None = None
    logged_predictions: list[tuple[str, str]] = field(default_factory=list, repr=False)
    task_counts: dict[str, int] = field(default_factory=dict, repr=False)
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
        # the model and slot caches and the task counts stay shared: replace passes the same dicts and list on
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
        sim=settings_from_config(c, "world"),
        physics=settings_from_config(c, "physics"),
        executor=executor_from_config(c.get("executor")),
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


#: Bump when a group's scores would come out differently for the same predictions and truth (2: the coverage's
#: draws scored by their nearest symmetric copy, as the truths are; 3: the draws moved onto the start's plane):
#: cached sets of an older one are recomputed.
SCORES_VERSION = 3


def scores_made_from(made_from: str, truth: str) -> list:
    """What a group's cached scores were computed from: its prediction set's fingerprint, its ground truth's
    (:func:`~pushtorch.experiments.scoring.truth_fingerprint`) and :data:`SCORES_VERSION`."""
    return [made_from, truth, SCORES_VERSION]
