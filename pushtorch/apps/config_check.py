"""Typed, bounded configs: every app's composed config is checked before any folder is made or work starts.

No paper section; issue 21 (typed configs). The configs stay plain YAML (users override any key from the
command line and sweep it); this module is their schema: a table of rules by key pattern (type, bounds,
unit) plus the library's own constructors for the structured parts (``ModelSettings``, ``SimSettings``,
priors). :func:`check_config` reports every problem at once, as one line naming each key, so a typo in a
value (``seed=abc``, ``object.scale=abc``, ``model.settings.position_frames=2.5``) or an absurd size
(``experiment.actions.duration=1e9``) never reaches the code that would allocate, loop or write.

Bounds (decisions, docs/method.md "Config bounds"): durations at most 60 s per push (the paper's is 4 s);
counts capped far above the paper's tables (kernels and candidates at 10^6); the trajectories a run keeps
in memory at most a quarter of this machine's RAM; positions inside the simulated ground with room for the
robot and the push. The Hydra callback :class:`ConfigCheck` (``conf/hydra/output/pushtorch.yaml``) runs the
check before Hydra makes a run folder (:func:`pushtorch.apps.cli.compose_or_exit` checks every job of a sweep
before the sweep folder exists);
:func:`pushtorch.apps.cli.run_stage` runs it again for configs that did not come through that callback.
"""

from __future__ import annotations

import fnmatch
import math
import os
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.registry import EXPERIMENTS, experiment_names

__all__ = ["APPS", "ConfigCheck", "ConfigError", "check_config", "memory_budget"]

#: The apps whose configs are checked, by Hydra config name.
APPS = ("config", "simulate", "train", "predict")

_MAX_SEED = 2**63 - 1
#: Longest push the apps accept (s); the paper's Action Duration is 4 s.
MAX_DURATION = 60.0
_MISSING = "???"


class ConfigError(InvalidParameterError):
    """A composed configuration holds a value of the wrong type, out of its bounds, or unset."""


@dataclass(frozen=True)
class Rule:
    """What one key accepts: ``kind`` (int, float, bool, str, name, pair, names, conditions: which test
    conditions a recording logs; training: training objects, names or ``shapes:`` entries or mesh files) and
    closed bounds."""

    kind: str
    low: float | None = None
    high: float | None = None
    nullable: bool = False
    choices: tuple[str, ...] = ()


def _int(low: float, high: float) -> Rule:
    return Rule("int", low, high)


def _float(low: float, high: float) -> Rule:
    return Rule("float", low, high)


_BOOL = Rule("bool")
_POSITIVE = 1e-12  # "> 0" as a closed bound

# Keys by pattern: "*" is one level, "**" any number (also none). The first matching rule applies.
_RULES: list[tuple[str, Rule]] = [
    ("seed", _int(0, _MAX_SEED)),
    ("object.name", Rule("name")),
    ("object.path", Rule("str", nullable=True)),
    ("object.scale", _float(1e-6, 1e3)),
    ("object.up", Rule("str", choices=("z", "y"))),  # pushtorch.objects.UP_AXES
    ("sim.time_step", _float(1e-4, 0.05)),
    ("sim.solver_iterations", _int(1, 1000)),
    ("sim.control_every", _int(1, 1000)),
    ("sim.record_rate", _float(1e-3, 1000.0)),
    ("sim.settle_time", _float(0.0, 10.0)),
    ("sim.bumper_friction", _float(0.0, 10.0)),
    ("sim.object_friction", _float(1e-3, 10.0)),
    ("sim.max_force", _float(_POSITIVE, 1e4)),
    ("sim.max_torque", _float(_POSITIVE, 1e4)),
    ("sim.tip_angle_deg", _float(_POSITIVE, 180.0)),
    ("sim.lift_tolerance", _float(1e-6, 1.0)),
    ("sim.ground_half_extent", _float(1.0, 1000.0)),
    ("sim.robot", Rule("str", choices=("p3dx", "ideal"))),
    ("world.engine", Rule("str", choices=("pybullet", "mujoco"))),
    ("physics.engine", Rule("str", choices=("pybullet", "mujoco"))),
    ("executor.kind", Rule("str", choices=("local", "ray", "slurm"))),
    ("sim.drive.robot_mass", _float(0.1, 1000.0)),
    ("sim.drive.wheel_radius", _float(1e-3, 2.0)),
    ("sim.drive.wheel_separation", _float(1e-2, 5.0)),
    ("sim.drive.wheel_friction", _float(_POSITIVE, 5.0)),
    ("sim.drive.drive_load_share", _float(_POSITIVE, 1.0)),
    ("sim.drive.wheel_torque", _float(_POSITIVE, 1e4)),
    ("sim.drive.max_wheel_speed", _float(_POSITIVE, 10.0)),
    ("sim.drive.speed_gain", _float(_POSITIVE, 1e6)),
    ("sim.drive.integral_gain", _float(_POSITIVE, 1e7)),
    ("**.actions.count", _int(1, 100)),
    ("**.actions.angle_range_deg", Rule("pair", -180.0, 180.0)),
    ("**.actions.speed", _float(1e-4, 2.0)),  # m/s; a Pioneer 3-DX drives at most 1.2 m/s
    ("**.actions.duration", _float(1e-3, MAX_DURATION)),
    ("**.placement.gap", _float(0.0, 0.5)),
    ("**.placement.lateral_jitter", _float(0.0, 1.0)),
    ("**.placement.yaw_jitter_deg", _float(0.0, 180.0)),
    ("**.placement.object_yaw_deg", _float(-360.0, 360.0)),
    ("test_placement.spread", _BOOL),
    ("test_placement.gap", _float(0.0, 0.05)),
    # beyond 0.2 m off the object's centre the 0.4 m bumper's centre line can miss a thin object
    ("test_placement.lateral_jitter", _float(0.0, 0.2)),
    ("test_placement.yaw_jitter_deg", _float(0.0, 45.0)),
    ("**.settings.voxel_size", _float(5e-4, 0.1)),
    ("**.settings.feature_radius", _float(1e-3, 0.5)),
    ("**.settings.environment_kernels", _int(1, 1_000_000)),
    ("**.settings.manipulator_kernels", _int(1, 1_000_000)),
    ("**.settings.query_kernels", _int(1, 1_000_000)),
    ("**.settings.position_frames", _int(1, 1_000_000)),
    ("**.settings.anneal_candidates", _int(1, 1_000_000)),
    ("**.settings.anneal_steps", _int(0, 100_000)),
    ("**.settings.environment_samples", _int(1, 100_000)),
    ("**.settings.environment_contacts", _int(1, 1000)),
    ("**.settings.environment_contacts_training", _int(1, 1000)),
    ("**.settings.manipulator_kernels_per_push", _int(1, 1000)),
    ("**.settings.polish_steps", _int(0, 1000)),
    ("**.settings.transfer_scale", _float(1e-3, 1000.0)),
    ("**.settings.transfer_widening", _float(0.0, 1e6)),
    ("**.samples_per_action", _int(1, 100_000)),
    ("**.workers", _int(0, 1024)),
    ("**.shard_size", _int(1, 100_000)),
    ("**.progress", _BOOL),
    ("experiment.compile", _BOOL),  # whether the experiment compiles the fast path (apps.experiment)
    ("**.log_examples", _int(0, 100)),
    ("recording.conditions", Rule("conditions", nullable=True)),  # experiments.common.LogConditions
    ("**.test_conditions", _int(1, 100_000)),
    ("**.peer_grid", _int(1, 32)),
    ("**.odometry", _BOOL),  # physics_from_cloud_online: at most 32 rollouts per observation and parameter
    ("**.runs", _int(1, 100_000)),
    ("**.yaw_range_deg", Rule("pair", -360.0, 360.0)),
    ("**.objects", Rule("names")),
    ("**.training_objects", Rule("training", nullable=True)),
    ("**.training_pushes", Rule("int", 1, 10**7, nullable=True)),
    ("experiment.**.held_out", _int(0, 1000)),      # shape_transfer: held-out shapes in the test set
    ("experiment.**.ensemble", _int(1, 10_000)),     # physics_ensemble's rollouts
    ("experiment.**.widening_pushes", _int(1, 1000)),
    ("experiment.**.coverage_band", Rule("pair", 0.0, 1.0)),
    ("experiment.**.library", _BOOL),
    ("experiment.**.transfer_objects", Rule("names", nullable=True)),
    ("**.methods", Rule("names")),
    ("experiment.name", Rule("name")),
    ("experiment.**.name", Rule("name")),
    ("experiment.**.truth_samples", _int(1, 1000)),
    ("experiment.**.yaw_deg", _float(-3600.0, 3600.0)),
    ("truth_samples", _int(0, 1000)),  # predict: 0 predicts only
    ("yaw_deg", _float(-3600.0, 3600.0)),
    ("x", _float(-1000.0, 1000.0)),
    ("y", _float(-1000.0, 1000.0)),
    ("duration", _float(1e-3, MAX_DURATION)),
    ("recording", _BOOL),
    ("allow_partial", _BOOL),
    ("export_table", _BOOL),
    ("name", Rule("name", nullable=True)),
    ("rerun_pushes", _int(0, 1000)),
    ("start_method", Rule("str", nullable=True, choices=("fork", "spawn", "forkserver"))),
]

_KIND_WORDS = {"int": "an integer", "float": "a number", "bool": "true or false", "str": "a string",
               "name": "a name", "pair": "a pair [low, high] of numbers", "names": "a list of names",
               "conditions": "first:k, worst:k, best:k or a list of indices", "training": "a list of objects"}


def _training_problem(key: str, value: Any) -> str | None:
    """A training list's problem: each entry a name, a mesh file (.stl, .obj, .ply) or a generated-shapes entry
    (:func:`pushtorch.objects.shapes.training_shape_seeds`)."""
    from pushtorch.objects.shapes import training_shape_seeds

    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        return f"{key} must be a non-empty list of names, got {_shown(value)}"
    for entry in value:
        if entry.startswith("shapes:"):
            try:
                training_shape_seeds(entry)
            except InvalidParameterError as exc:
                return f"{key}: {exc}"
        elif not entry.lower().endswith((".stl", ".obj", ".ply")):
            problem = _name_problem(key, entry)
            if problem:
                return problem
    return None


def _matches(key: str, pattern: str) -> bool:
    keys, parts = key.split("."), pattern.split(".")

    def match(i: int, j: int) -> bool:
        if j == len(parts):
            return i == len(keys)
        if parts[j] == "**":
            return any(match(k, j + 1) for k in range(i, len(keys) + 1))
        return i < len(keys) and fnmatch.fnmatchcase(keys[i], parts[j]) and match(i + 1, j + 1)

    return match(0, 0)


def _leaves(node: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """Every (dotted key, value) of a plain config; lists are values, mappings are walked."""
    if isinstance(node, Mapping):
        for key, value in node.items():
            yield from _leaves(value, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, node


def _shown(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})" if not isinstance(value, bool) else repr(value)


def _number(value: Any, integer: bool) -> float | int | None:
    """``value`` as a finite number (an int if ``integer``: 3000.0 is the count 3000), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    if integer:
        return int(value) if float(value).is_integer() else None
    return float(value)


def _bounds(rule: Rule) -> str:
    high = "2**63" if rule.high == _MAX_SEED else f"{rule.high:g}"
    low = "0 (exclusive)" if rule.low == _POSITIVE else f"{rule.low:g}"
    return f" in [{low}, {high}]" if rule.high != _MAX_SEED else f" in [{low}, {high})"


def _check_value(key: str, value: Any, rule: Rule) -> str | None:
    """The problem with ``value`` under ``rule``, or None."""
    if value is None:
        return None if rule.nullable else f"{key} must be {_KIND_WORDS[rule.kind]}, not null"
    if rule.kind in ("int", "float"):
        number = _number(value, rule.kind == "int")
        if number is None or not rule.low <= number <= rule.high:
            return f"{key} must be {_KIND_WORDS[rule.kind]}{_bounds(rule)}, got {_shown(value)}"
        return None
    if rule.kind == "bool":
        return None if isinstance(value, bool) else f"{key} must be true or false, got {_shown(value)}"
    if rule.kind == "pair":
        numbers = [_number(v, False) for v in value] if isinstance(value, list) else []
        if len(numbers) != 2 or None in numbers or not rule.low <= numbers[0] <= numbers[1] <= rule.high:
            return (f"{key} must be [low, high] with {rule.low:g} <= low <= high <= {rule.high:g}, "
                    f"got {_shown(value)}")
        return None
    if rule.kind == "conditions":
        from pushtorch.experiments.common import LogConditions

        try:
            LogConditions.parse(value, key=key)
        except InvalidParameterError as exc:
            return str(exc)
        return None
    if rule.kind == "training":
        return _training_problem(key, value)
    if rule.kind == "names":
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
            return f"{key} must be a non-empty list of names, got {_shown(value)}"
        return next((p for p in (_name_problem(key, v) for v in value) if p), None)
    if not isinstance(value, str):
        return f"{key} must be {_KIND_WORDS[rule.kind]}, got {_shown(value)}"
    if rule.choices and value not in rule.choices:
        return f"{key} must be one of {', '.join(rule.choices)}, got {value!r}"
    return _name_problem(key, value) if rule.kind == "name" else None


def _name_problem(key: str, value: str) -> str | None:
    from pushtorch.errors import UnsafeNameError
    from pushtorch.paths import safe_name

    try:
        safe_name(value, key)
    except UnsafeNameError as exc:
        return str(exc)
    return None


def memory_budget() -> int:
    """Bytes a run may keep in trajectories: a quarter of this machine's physical memory (8 GiB if unknown)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 4
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def _trajectory_bytes(pushes: int, duration: float, record_rate: float) -> int:
    """Bytes of a run's recorded trajectories: object and robot poses (7 float64) per recorded time."""
    return int(pushes * (duration * record_rate + 1) * 2 * 7 * 8)


def _plain(cfg: Any) -> tuple[dict, list[str]]:
    """The config without its ``hydra`` node as plain containers, and the mandatory keys left unset (``???``).

    An interpolation that cannot resolve yet (``${hydra:...}`` before Hydra has set up the job) stays as its
    ``${...}`` text, which no rule checks: :func:`pushtorch.apps.cli.run_stage` checks the resolved job again.
    """
    if not OmegaConf.is_config(cfg):
        c = {k: v for k, v in dict(cfg).items() if k != "hydra"}
        return c, [k for k, v in _leaves(c) if v == _MISSING]
    if isinstance(cfg, DictConfig) and "hydra" in cfg:
        cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    missing = sorted(OmegaConf.missing_keys(cfg)) if isinstance(cfg, DictConfig) else []
    try:
        container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    except Exception:  # an interpolation that does not resolve here
        container = OmegaConf.to_container(cfg, resolve=False, throw_on_missing=False)
    return container, missing


def _unresolved(value: Any) -> bool:
    return isinstance(value, str) and value.startswith("${")


def _prior_problems(key: str, node: Any) -> list[str]:
    from pushtorch.sim.priors import prior_from_config

    if not isinstance(node, Mapping):
        return [f"{key} must be a prior (kind: uniform|normal|fixed and its numbers), got {_shown(node)}"]
    numbers = {k: v for k, v in node.items() if k in ("low", "high", "mean", "std", "value", "minimum")}
    bad = [f"{key}.{k} must be a number, got {_shown(v)}" for k, v in numbers.items() if _number(v, False) is None]
    if bad:
        return bad
    try:
        prior_from_config(node)
    except InvalidParameterError as exc:
        return [f"{key}: {exc}"]
    return []


def _structured_problems(app: str, c: Mapping[str, Any]) -> list[str]:
    """Checks of whole sections by the library's constructors, and of names against what exists."""
    from pushtorch.models.settings import ModelSettings
    from pushtorch.sim.settings import SimSettings

    problems: list[str] = []
    if isinstance(c.get("sim"), Mapping):
        try:
            SimSettings(**c["sim"])
        except (InvalidParameterError, TypeError) as exc:
            problems.append(f"sim: {exc}")
    if isinstance(c.get("executor"), Mapping):
        from pushtorch.sim.executors import executor_from_config, slurm_problem

        try:
            if problem := slurm_problem(executor_from_config(c["executor"])):
                problems.append(problem)
        except InvalidParameterError as exc:
            problems.append(f"executor: {exc}")
    settings = [(k[: -len(".settings")], v) for k, v in _sections(c, "settings")]
    for where, node in settings:
        if where.endswith("model") or where == "model":
            try:
                ModelSettings.from_mapping(node)
            except (InvalidParameterError, TypeError, ValueError) as exc:
                problems.append(f"{where}.settings: {exc}")
    if app in ("simulate", "predict"):
        for kind in ("friction", "mass"):
            if kind in c:
                problems += _prior_problems(kind, c[kind])
    for kind, named in (c.get("priors") or {}).items():
        for name, node in (named or {}).items():
            problems += _prior_problems(f"priors.{kind}.{name}", node)
    obj = c.get("object")
    if isinstance(obj, Mapping) and isinstance(obj.get("name"), str):
        from pushtorch.objects import catalogue_names

        if obj["name"] == "mesh":
            if not isinstance(obj.get("path"), str) or not obj["path"]:
                problems.append("object.path is not set: object=mesh needs object.path=<an STL, OBJ or PLY file>")
        elif obj["name"] not in catalogue_names() and not obj.get("path"):
            problems.append(f"object.name {obj['name']!r} is not a catalogue object ({', '.join(catalogue_names())})"
                            " and no object.path is given")
    if app == "config":
        problems += _experiment_problems(c)
    if app == "predict":
        problems += _predict_problems(c)
    return problems


def _sections(node: Any, name: str, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """Every mapping called ``name`` in the config, with its dotted key."""
    if isinstance(node, Mapping):
        for key, value in node.items():
            dotted = f"{prefix}.{key}" if prefix else str(key)
            if key == name and isinstance(value, Mapping):
                yield dotted, value
            else:
                yield from _sections(value, name, dotted)


def _experiment_problems(c: Mapping[str, Any]) -> list[str]:
    exp = c.get("experiment")
    if not isinstance(exp, Mapping):
        return ["experiment is not set: choose one, e.g. experiment=quickstart"]
    name = exp.get("name")
    if isinstance(name, str) and _name_problem("experiment.name", name) is None and name not in EXPERIMENTS:
        return [f"experiment.name {name!r} is not an experiment; known: {', '.join(experiment_names())}"]
    problems = _prior_name_problems(c, exp)
    # the trajectories one simulation run keeps: the larger of a training run and a part's ground truth
    actions = exp.get("actions") or {}
    count, duration = _number(actions.get("count", 3), True), _number(actions.get("duration", 4.0), False)
    rate = _number((c.get("sim") or {}).get("record_rate", 10.0), False)
    samples = _number((c.get("model") or {}).get("samples_per_action", 500), True)
    if None in (count, duration, rate, samples):
        return problems  # reported by the rules
    problems += _logged_condition_problems(c, exp)
    runs = [samples]
    for part in list((exp.get("parts") or {}).values()) or [exp]:
        if not isinstance(part, Mapping):
            continue
        conditions = part.get("conditions") or {}
        combinations = math.prod(len(v) if isinstance(v, list) else 1 for v in conditions.values()) \
            if isinstance(conditions, Mapping) else 1
        runs.append(int(part.get("test_conditions", 1)) * int(part.get("truth_samples", 1)) * combinations)
    return problems + _memory_problems("experiment", max(runs) * count, duration, rate)


def _logged_condition_problems(c: Mapping[str, Any], exp: Mapping[str, Any]) -> list[str]:
    """``recording.conditions`` may not list an index beyond every part's test conditions."""
    listed = (c.get("recording") or {}).get("conditions")
    if not isinstance(listed, list) or not listed:
        return []
    sizes = [_number(part.get("test_conditions"), True)
             for part in list((exp.get("parts") or {}).values()) or [exp] if isinstance(part, Mapping)]
    sizes = [size for size in sizes if size is not None]
    if not sizes or max(listed) < max(sizes):
        return []
    return [f"recording.conditions lists test condition {max(listed)}, but no part has more than {max(sizes)} "
            f"(indices 0..{max(sizes) - 1})"]


def _prior_name_problems(c: Mapping[str, Any], exp: Mapping[str, Any]) -> list[str]:
    """Every prior an experiment names (its models' and its test conditions') must be in ``priors``."""
    priors = c.get("priors") or {}
    if not any(priors.values()):  # an experiment that loads no prior trains no push model (pose estimation)
        return []
    named: list[tuple[str, str, Any]] = []
    for where, node in [("model", c.get("model"))] + [
            (f"experiment.parts.{k}", v) for k, v in (exp.get("parts") or {}).items()] + [("experiment", exp)]:
        if not isinstance(node, Mapping):
            continue
        for section in ("model", "condition", "conditions") if where != "model" else ("",):
            entry = node.get(section) if section else node
            if not isinstance(entry, Mapping):
                continue
            for kind in ("friction", "mass"):
                if kind in entry:
                    named.append((f"{where}{'.' + section if section else ''}.{kind}", kind, entry[kind]))
    problems = []
    for key, kind, value in named:
        for name in value if isinstance(value, list) else [value]:
            if not isinstance(name, str) or name not in (priors.get(kind) or {}):
                known = ", ".join(sorted(priors.get(kind) or {})) or "none"
                problems.append(f"{key} names the {kind} prior {name!r}, which is not in priors.{kind} "
                                f"(known: {known})")
    return problems


def _memory_problems(what: str, pushes: int, duration: float, rate: float) -> list[str]:
    need, budget = _trajectory_bytes(pushes, duration, rate), memory_budget()
    if need <= budget:
        return []
    return [f"{what}: {pushes} pushes of {duration:g} s recorded at {rate:g} Hz keep ~{need / 2**30:.1f} GiB of "
            f"trajectories, more than a quarter of this machine's memory ({budget / 2**30:.1f} GiB): use fewer "
            "pushes, shorter pushes or a lower sim.record_rate"]


def _predict_problems(c: Mapping[str, Any]) -> list[str]:
    from pushtorch.sim.geometry import ROBOT_REACH

    problems = []
    models = c.get("models")
    if isinstance(models, str):
        models = [models]
    if not isinstance(models, list) or not models or not all(isinstance(m, str) and m for m in models):
        problems.append(f"models must be a model file or a list of them, got {_shown(c.get('models'))}")
    wanted = c.get("actions", "all")
    if wanted != "all" and not (isinstance(wanted, list) and wanted
                                and all(_number(a, True) is not None and a >= 0 for a in wanted)):
        problems.append(f"actions must be 'all' or a list of action indices (integers >= 0), got {_shown(wanted)}")
    half = _number((c.get("sim") or {}).get("ground_half_extent", 50.0), False)
    duration = _number(c.get("duration", 4.0), False)
    if half is not None and duration is not None:
        # the object, the robot behind it (its reach) and a push at up to 1 m/s stay on the ground
        limit = half - 1.0 - ROBOT_REACH - 1.0 * duration
        for axis in ("x", "y"):
            value = _number(c.get(axis, 0.0), False)
            if value is not None and abs(value) > limit:
                problems.append(f"{axis} = {value:g} m puts the object, the robot and the push off the simulated "
                                f"ground: |{axis}| <= {limit:g} m (sim.ground_half_extent = {half:g} m)")
    return problems


def check_config(cfg: Any, app: str) -> None:
    """Check an app's composed config (``app``: one of :data:`APPS`).

    Raises:
        ConfigError: every problem found, in one line: unset mandatory keys, values of the wrong type or
            out of bounds, unknown experiments or objects, sizes beyond the memory budget, positions off
            the simulated ground.
    """
    if app not in APPS:
        raise ConfigError(f"unknown app {app!r}; known: {', '.join(APPS)}")
    c, missing = _plain(cfg)
    problems = [f"{key} is not set (it is mandatory): give it, e.g. {key}=<value>" for key in missing]
    for key, value in _leaves(c):
        if key in missing or _unresolved(value):
            continue
        rule = next((rule for pattern, rule in _RULES if _matches(key, pattern)), None)
        if rule is not None and (problem := _check_value(key, value, rule)):
            problems.append(problem)
    if not problems:
        problems = _structured_problems(app, c)
    if not problems and app == "simulate":
        actions, sim = c.get("actions") or {}, c.get("sim") or {}
        problems = _memory_problems("simulate", c["samples_per_action"] * actions.get("count", 3),
                                    actions.get("duration", 4.0), sim.get("record_rate", 10.0))
    if problems:
        raise ConfigError("invalid configuration: " + "; ".join(problems))


try:
    from hydra.experimental.callback import Callback
except ImportError:  # pragma: no cover - hydra-core is a dependency
    Callback = object  # type: ignore[assignment,misc]


class ConfigCheck(Callback):
    """Hydra callback: :func:`check_config` before the run folder exists (``on_run_start``), and a check that
    the sweep folder can be made (``on_multirun_start``; each sweep job's config is checked by
    :func:`pushtorch.apps.cli.compose_or_exit` before Hydra starts). A bad config prints one line and exits with
    status 2."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check_or_exit(config, kwargs.get("config_name"))
        self._folder_or_exit(config, "run", kwargs.get("config_name"))

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        # every job's config was composed and checked by pushtorch.apps.cli.compose_or_exit already
        self._folder_or_exit(config, "sweep", kwargs.get("config_name"))

    @staticmethod
    def _folder_or_exit(config: DictConfig, mode: str, config_name: str | None) -> None:
        """Exit with one line if Hydra could not make the run (or sweep) folder: a file in its path, or
        a parent this user cannot write."""
        try:
            folder = Path(str(config.hydra[mode].dir))
        except Exception:  # a folder name Hydra resolves later: Hydra reports its own errors
            return
        existing = folder
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        problem = None
        if not existing.is_dir():
            problem = f"{existing} is a file, not a folder"
        elif not os.access(existing, os.W_OK | os.X_OK):
            problem = f"{existing} is not writable"
        if problem:
            app = {"config": "pushtorch"}.get(str(config_name), f"pushtorch-{config_name}")
            print(f"{app}: cannot make the {mode} folder {folder}: {problem} (hydra.{mode}.dir)", file=sys.stderr)
            sys.exit(2)

    @staticmethod
    def _check_or_exit(config: DictConfig, config_name: str | None, where: str = "") -> None:
        if config_name not in APPS:
            return
        try:
            check_config(config, config_name)
        except ConfigError as exc:
            app = {"config": "pushtorch"}.get(config_name, f"pushtorch-{config_name}")
            print(f"{app}: {exc}{where}", file=sys.stderr)
            sys.exit(2)
