"""Online adaptation: predictions conditioned on k observed pushes of the test object, against the biased,
general and physics predictors on the same pushes (paper, §Conclusions and future work: "several sample pushes
in an online fashion"; §Biasing Transferable Push Manipulation Models for the models and conditions).

For each test object (its training object from ``training_object_of``) and each test condition
(``friction:low|medium|high`` with the mass at the paper's default, ``mass:low|medium|high`` with the friction at
its default), ``test_conditions`` cases are drawn. A case is one object with one friction and mass drawn from
the condition: a test pose pushed with every action from a given robot start (the scored pushes, the same starts
and seeds in every condition: a paired comparison), and ``max(observed)`` pushes of the same object at other
poses, in the same physics (the observations, with the robot's own final pose unless ``odometry: false``). Every
predictor of a case gets the same observations, their
first ``k`` for ``k`` in ``observed``; the scored pushes are never observed.

Predictors (results ``method``): ``online`` (the library of the bias's models, general, low, medium, high, of
the training object, conditioned: the model of highest evidence predicts), ``online_general`` (the general model
conditioned), ``general``, ``congruent`` (the biased model of the true condition: the oracle's choice),
``incongruent`` (the biased model farthest from it, in μ or log m), ``debiased`` (the general model de-biased
to its training prior, ``k = 0``), ``physics_from_cloud`` (the cloud's body at the general prior's means) and
``physics_from_cloud_online`` (its friction and mass fitted to the observations,
:func:`pushtorch.evaluation.baselines.fit_cloud_physics`). Independent of ``k``, ``general``, ``congruent``,
``incongruent`` and ``physics_from_cloud`` are recorded once per ``k`` all the same, for the tables and figures.

The separability of adjacent conditions (the distance between the mean outcomes of two conditions over their
pooled spread, per action, averaged) says where the outcomes can tell the conditions apart at all.

Each object and condition's scores are written to ``<run_dir>/online/`` as soon as they are done, with what made
them: a killed run resumes there, and a run with more objects reuses the ones it has.

Run: ``python -m pushtorch experiment=online_adaptation``; it is a part of the quickstart at small sizes.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.experiments.common import (
    ExperimentContext,
    as_names,
    compare_displacement,
    fingerprint,
    load_test_objects,
    plain,
    progress_bar,
    sample_test_poses,
    stable_seed,
    train_model,
)
from pushtorch.experiments.prediction_sets import observe
from pushtorch.experiments.suite import run_suite
from pushtorch.experiments.tasks import prefetch
from pushtorch.experiments.training import train_models, train_residual
from pushtorch.io import atomic_write_bytes
from pushtorch.models.conditioning import Observation
from pushtorch.models.library import ModelLibrary
from pushtorch.models.residual import DEFAULT_ENSEMBLE
from pushtorch.objects import ObjectModel, load_object
from pushtorch.paths import contained_path

__all__ = ["run", "run_part", "separability"]

#: The robot starts of observed and scored pushes: heading within ± this of the object's x axis (deg) …
HEADING_JITTER_DEG = 5.0
#: … the bumper's centre line within ± this of the object's centre (m), this far short of touching (m).
LATERAL_JITTER, GAP = 0.02, 0.002
LEVELS = ("low", "medium", "high")
#: Part keys that do not change a condition's scores (left out of its cache's fingerprint).
RUN_CONTROL = ("objects", "name", "progress", "workers", "shard_size", "log_examples", "kind")
#: Bump when a condition's cached scores (``<run_dir>/online/*.json``) would come out differently.
ONLINE_VERSION = 4


def _start(obj, pose: se3.Pose, seed: int) -> se3.Pose:
    from pushtorch.sim.push import place_robot_against

    u = torch.rand(2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 2 - 1
    heading = float(se3.yaw_of(pose.q.double())) + float(u[0]) * math.radians(HEADING_JITTER_DEG)
    return place_robot_against(obj.mesh, pose, heading, float(u[1]) * LATERAL_JITTER, GAP)


def _incongruent(ctx: ExperimentContext, bias: str, level: str) -> str:
    """The biased prior farthest from ``level`` (in μ, or in log m): the first of a tie."""
    def value(name: str) -> float:
        mean = ctx.prior(bias, name).mean
        return math.log(mean) if bias == "mass" else mean

    return max((n for n in LEVELS if n != level), key=lambda n: abs(value(n) - value(level)))


def _pose(p: se3.Pose) -> se3.Pose:
    return se3.Pose.unchecked(p.p.reshape(3).float(), p.q.reshape(4).float())


@dataclass
class _Group:
    """One test object under one bias: its test cases (clouds, starts, poses), the bias's models and the memo of
    predictions that do not depend on the condition (the same pushes, the same seeds)."""

    ctx: ExperimentContext
    name: str
    obj: ObjectModel
    poses: se3.Pose
    clouds: list
    starts: list
    models: dict
    general_prior: tuple
    memo: dict = field(default_factory=dict)
    #: the general model's residual model (``pushtorch_residual``; the part's ``residual: true``), or None
    residual: Any = None

    def residual_predicted(self, model, i: int, j: int, key: str):
        """``(start, final, density)`` of a residual model on case ``i``, action ``j`` from the case's robot start
        (memoised by ``key``; a model whose point is learned reports its own push model's prediction, as
        conditioned as it is)."""
        from pushtorch.prediction.residual import predict_residual

        if key not in self.memo:
            seed = stable_seed(self.ctx.seed, self.name, self.obj.name, i, j, "residual")
            learned = self.predicted(model.model, i, j, f"{key}|learned")[:2] if model.needs_learned else None
            pred = predict_residual(model, self.clouds[i][1], self.ctx.actions[j], seed, robot_start=self.starts[i][j],
                                    learned=learned)
            self.memo[key] = (pred.start, pred.final_pose, pred.density)
        return self.memo[key]

    def predicted(self, model, i: int, j: int, key: str):
        """``(estimate, final, density)`` of ``model`` on case ``i``, action ``j`` (memoised by ``key``)."""
        from pushtorch.evaluation.likelihood import motion_product_density
        from pushtorch.prediction import predict

        if key not in self.memo:
            seed = stable_seed(self.ctx.seed, self.name, self.obj.name, i, j)
            pred = predict(model, self.clouds[i][1], self.ctx.actions[j], torch.Generator().manual_seed(seed),
                           robot_start=self.starts[i][j])
            scoring = torch.Generator().manual_seed(stable_seed(self.ctx.seed, self.name, self.obj.name, i, j,
                                                                "likelihood"))
            self.memo[key] = (pred.condition.object_pose, pred.final_pose,
                              motion_product_density(pred.motion_density, scoring, pred.candidates))
        return self.memo[key]

    def cloud_physics(self, i: int, j: int, friction: float, mass: float, key: str):
        """``(start, final, density)`` of physics on the body case ``i``'s cloud reconstructs, action ``j`` (every
        action of the case pushed in one call and memoised under ``key``)."""
        from pushtorch.evaluation.baselines import cloud_body
        from pushtorch.evaluation.likelihood import point_density
        from pushtorch.sim.runner import simulate_pushes

        if (key, j) not in self.memo:
            estimate = self.predicted(self.models["general"], i, 0, f"general|{i}|0")[0]  # names the body only
            body, start = cloud_body(self.clouds[i][0].points, estimate)
            count = len(self.starts[i])
            finals = simulate_pushes(body, se3.Pose.stack(self.starts[i]), se3.Pose.stack([start] * count),
                                     self.ctx.actions.double(), mass, friction, settings=self.ctx.physics).object_final
            settings = self.ctx.settings
            for a in range(count):
                final = se3.Pose.unchecked(finals.p[a].float(), finals.q[a].float())
                self.memo[(key, a)] = (start.to(torch.float32), final,
                                       point_density(final, settings.motion_p_std, settings.motion_rot_std))
        return self.memo[(key, j)]


def _observations(group: _Group, condition: str, i: int, count: int, yaw_range, mass: float,
                  mu: float, odometry: bool) -> list[Observation]:
    """``count`` pushes of the case's object at other poses, in the case's physics, as observations (with the
    robot's own final pose where ``odometry``)."""
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.sim.runner import simulate_pushes

    ctx, obj = group.ctx, group.obj
    low, high = (math.radians(float(v)) for v in yaw_range)
    poses, starts, actions = [], [], []
    for o in range(count):
        g = torch.Generator().manual_seed(stable_seed(ctx.seed, group.name, obj.name, condition, i, "obs", o))
        poses.append(obj.resting_pose(0.0, 0.0, low + (high - low) * float(torch.rand(1, generator=g,
                                                                                       dtype=torch.float64))))
        actions.append(int(torch.randint(int(ctx.actions.shape[0]), (1,), generator=g)))
        starts.append(_start(obj, poses[-1], stable_seed(ctx.seed, group.name, obj.name, condition, i, "obs-start", o)))
    if not count:
        return []
    pushed = simulate_pushes(obj, se3.Pose.stack(starts), se3.Pose.stack(poses), ctx.actions.double()[actions],
                             mass, mu, settings=ctx.sim)  # every observed push in one call, in the world
    out = []
    for o in range(count):
        cloud = capture_partial_cloud(obj, poses[o], voxel_size=ctx.settings.voxel_size)
        robot = se3.Pose.unchecked(pushed.robot_trajectory.p[o, -1], pushed.robot_trajectory.q[o, -1])
        final = se3.Pose.unchecked(pushed.object_final.p[o], pushed.object_final.q[o])
        out.append(Observation(cloud, ctx.actions[actions[o]], _pose(poses[o]), _pose(final), _pose(starts[o]),
                               _pose(robot) if odometry else None))
    return out


@dataclass
class _Scores:
    """Per (method, k): each scored push's (H_acc, nll, linear cm, angular deg); the posteriors' summaries."""

    pushes: dict = field(default_factory=dict)
    posteriors: dict = field(default_factory=dict)
    #: per k, per case: each library model's log evidence and the library's log posterior weights
    evidence: dict = field(default_factory=dict)
    #: one case's scores by (prediction, action): a prediction every k shares is scored once
    scored: dict = field(default_factory=dict)

    def add(self, predictor: str, k: int, prediction, truth_initial: se3.Pose, truth_final: se3.Pose, obj,
            j: int) -> None:
        """Score ``predictor``'s ``prediction`` (estimate, final, density) of action ``j`` after ``k`` observed
        pushes against the truth."""
        from pushtorch.evaluation.likelihood import nll

        key = (id(prediction), j)
        if key not in self.scored:
            estimate, final, density = prediction
            acc = compare_displacement(estimate.reshape(1, 1), final.reshape(1, 1), truth_initial.unsqueeze(0),
                                       truth_final.reshape(1, 1, 1), obj)
            value = nll(density, truth_final.reshape(1), truth_initial, estimate, obj.symmetry)
            numbers = (float(acc.hacc.reshape(-1)[0]), float(value.reshape(-1)[0]),
                       float(acc.linear_cm.reshape(-1)[0]), float(acc.angular_deg.reshape(-1)[0]))
            self.scored[key] = (prediction, numbers)  # the prediction kept: its id stays its own
        self.pushes.setdefault((predictor, k), []).append(self.scored[key][1])


def _observed(group: _Group, part: Mapping[str, Any], bias: str, level: str, i: int, observed: list[int]):
    """Case ``i`` of one condition up to its conditioning: its physics ``(μ, m)``, its observations and the chain
    of conditioned libraries (``chain[k]`` has seen ``k`` of them; one observation at a time, the same posterior
    as all at once). Everything is seeded by the case, so the recording's re-run of a case is that case."""
    ctx, obj, name, models = group.ctx, group.obj, group.name, group.models
    condition, other = f"{bias}:{level}", _other(bias)
    default = _default(part, bias)
    gen = torch.Generator().manual_seed(stable_seed(ctx.seed, name, obj.name, condition, i))
    priors = {bias: ctx.prior(bias, level), other: ctx.prior(other, default)}
    mu = float(priors["friction"].sample((1,), gen)[0])
    mass = float(priors["mass"].sample((1,), gen)[0])
    obs = _observations(group, condition, i, observed[-1], part["yaw_range_deg"], mass, mu,
                        bool(part.get("odometry", True)))
    seed = stable_seed(ctx.seed, name, obj.name, condition, i, "condition")
    library = ModelLibrary([models[lv] for lv in ("general", *LEVELS)])
    chain = [library.condition_on([], seed=seed)]  # selects by H_r, as the library does
    for o in obs:
        chain.append(chain[-1].condition_on([o], seed=seed))
    return mu, mass, obs, chain


def _log_case(group: _Group, part: Mapping[str, Any], bias: str, level: str, i: int, observed: list[int]) -> None:
    """Case ``i``'s posterior timeline in the recording (its observations and conditioned libraries)."""
    from pushtorch.viz.core import WORLD, entity_name
    from pushtorch.viz.online import log_online_adaptation

    _, _, obs, chain = _observed(group, part, bias, level, i, observed)
    log_online_adaptation(group.ctx.recording, f"{WORLD}/experiments/{group.name}/{entity_name(group.obj.name)}/"
                          f"{entity_name(f'{bias}:{level}')}/case{i}", chain, obs)


def _case(group: _Group, part: Mapping[str, Any], bias: str, level: str, i: int, observed: list[int],
          scores: _Scores) -> torch.Tensor:
    """Score every predictor on case ``i`` of one condition; returns the case's true outcomes ``(A, 2)`` (the
    object's final position in each push's robot start frame) for the separability."""
    from pushtorch.evaluation.baselines import fit_cloud_physics, physics_grid
    from pushtorch.sim.runner import simulate_pushes

    ctx, obj, models, condition = group.ctx, group.obj, group.models, f"{bias}:{level}"
    mu, mass, obs, chain = _observed(group, part, bias, level, i, observed)
    a_count = int(ctx.actions.shape[0])
    starts = se3.Pose.stack(group.starts[i])
    initial = se3.Pose.stack([group.poses.take(i)] * a_count)
    truth = simulate_pushes(obj, starts, initial, ctx.actions.double(), mass, mu,
                            settings=ctx.sim).object_final  # the scored pushes
    grid = physics_grid(*group.general_prior, int(part.get("peer_grid", 8)))
    errors = fit_cloud_physics(obs, grid, ctx.physics)
    wrong = _incongruent(ctx, bias, level)
    means = (group.general_prior[0].mean, group.general_prior[1].mean)
    debiased = group.memo.setdefault("debiased model", models["general"].condition_on([], prior=group.general_prior))
    truth_initial = _pose(group.poses.take(i))
    scores.scored.clear()  # the truth is this case's
    for k in observed:
        conditioned = chain[k]
        # the residual model conditioned on the same observations, once per k
        residual = None if group.residual is None or k == 0 else \
            group.residual.condition_on(obs[:k], seed=_residual_seed(group, condition, i))
        for j in range(a_count):
            fixed = {m: group.predicted(models[lv], i, j, f"{lv}|{i}|{j}")
                     for m, lv in (("general", "general"), ("congruent", level), ("incongruent", wrong))}
            fixed["physics_from_cloud"] = group.cloud_physics(i, j, means[0], means[1], f"pfc|{i}")
            if group.residual is not None:
                fixed["pushtorch_residual"] = group.residual_predicted(
                    group.residual if residual is None else residual, i, j,
                    f"residual|{condition if k else ''}|{i}|{k}|{j}")
            if k == 0:
                fixed["debiased"] = group.predicted(debiased, i, j, f"debiased|{i}|{j}")
                online = online_general = fixed["general"]
                peer = fixed["physics_from_cloud"]
            else:
                online = group.predicted(conditioned, i, j, f"online|{condition}|{i}|{k}|{j}")
                online_general = group.predicted(conditioned.models[0], i, j, f"online_general|{condition}|{i}|{k}|{j}")
                best = grid[errors[:k].pow(2).sum(0).argmin()]
                peer = group.cloud_physics(i, j, float(best[0]), float(best[1]), f"pfco|{condition}|{i}|{k}")
            final = se3.Pose.unchecked(truth.p[j].float(), truth.q[j].float())
            for predictor, prediction in {**fixed, "online": online, "online_general": online_general,
                                          "physics_from_cloud_online": peer}.items():
                scores.add(predictor, k, prediction, truth_initial, final, obj, j)
        summaries = (conditioned.posterior(0).as_record(), conditioned.models[0].posterior(0).as_record())
        if k > 0:
            levels = ("general", *LEVELS)  # the library's models, in order
            weights = conditioned.model_log_posterior().tolist()
            scores.evidence.setdefault(k, []).append(
                {"log_evidence": {lv: float(m.physics_posterior.log_evidence())
                                  for lv, m in zip(levels, conditioned.models, strict=True)},
                 "log_weights": dict(zip(levels, weights, strict=True))})
        scores.posteriors.setdefault(("online", k), []).append(summaries[0])
        scores.posteriors.setdefault(("online_general", k), []).append(summaries[1])
    return torch.stack([se3.relative(group.starts[i][j], se3.Pose.unchecked(truth.p[j], truth.q[j])).p[:2]
                        for j in range(a_count)])


def _residual_seed(group: _Group, condition: str, i: int) -> int:
    """The seed of the residual model's conditioning on case ``i``'s observations (as the library's)."""
    return stable_seed(group.ctx.seed, group.name, group.obj.name, condition, i, "condition")


def _paired(hacc: torch.Tensor, other: list) -> dict[str, float]:
    """The mean per-push H_acc difference to ``other``'s scores of the same pushes, and its standard error."""
    diff = hacc - torch.tensor([v[0] for v in other], dtype=torch.float64)
    return {"difference": float(diff.mean()), "se": float(diff.std() / math.sqrt(len(diff))) if len(diff) > 1 else 0.0}


def _condition_records(obj: str, condition: str, scores: _Scores, priors: Mapping[str, Any]) -> list[dict]:
    """The records of one object and condition: one per predictor and k, with the posterior and the paired
    difference to ``congruent`` where they apply."""
    records = []
    for (predictor, k), values in scores.pushes.items():
        t = torch.tensor(values, dtype=torch.float64)
        record = _record(obj, predictor, k, condition, t[:, 0], t[:, 1], t[:, 2:])
        if predictor in ("online", "online_general"):
            summaries = scores.posteriors[(predictor, k)]
            record.update({key: float(sum(s[key] for s in summaries) / len(summaries))
                           for key in ("mu_mean", "mu_std", "log_mass_mean", "log_mass_std")})
            record.update({"mu_true": priors["friction"].mean, "mass_true": priors["mass"].mean})
        if predictor == "online" and k in scores.evidence:
            # the evidence itself: each library model's log evidence and the library's log posterior weight of
            # it after k observed pushes, per case (nats)
            cases = scores.evidence[k]
            record.update({key: {lv: [c[key][lv] for c in cases] for lv in cases[0][key]}
                           for key in ("log_evidence", "log_weights")})
        if predictor == "online":
            record["vs_congruent"] = _paired(t[:, 0], scores.pushes[("congruent", k)])
        if k > 0 and (predictor, 0) in scores.pushes:  # what the observed pushes changed, push by push
            record["vs_k0"] = _paired(t[:, 0], scores.pushes[(predictor, 0)])
        records.append(record)
    return records


def run_part(cfg, part: Mapping[str, Any], ctx: ExperimentContext,
             model_cfg: Mapping[str, Any]) -> tuple[list[dict], dict]:
    """Train (or reuse) the biasing models, condition them on each case's observations and score every
    predictor; returns the records (``task: online``) and extras: ``online_separability``, per object, parameter
    and adjacent pair (results.json's ``separability``)."""
    part = plain(part)
    name = str(part.get("name", "online_adaptation"))
    objects = load_test_objects(cfg, as_names(part["objects"]))
    training_of = {str(k): str(v) for k, v in (part.get("training_object_of") or {}).items()}
    observed = sorted({int(k) for k in part["observed"]})
    if not observed or observed[0] < 0 or observed[0] != 0:
        raise InvalidParameterError(f"observed must list k >= 0 observed pushes, 0 first, got {part['observed']}")
    n_cases = int(part["test_conditions"])
    biases = [b for b in ("friction", "mass") if as_names((part.get("conditions") or {}).get(b))]
    if not biases:
        raise InvalidParameterError("online_adaptation needs conditions.friction and/or conditions.mass levels")
    for bias in biases:
        unknown = [level for level in as_names(part["conditions"][bias]) if level not in LEVELS]
        if unknown:
            raise InvalidParameterError(f"online_adaptation's {bias} conditions are {LEVELS}, got {unknown}")
    records: list[dict] = []
    separability: list[dict] = []
    # the cases whose posterior timeline the recording shows (the first ones; worst/best choices need the truth)
    logged = sorted(set(ctx.log_examples.known_before_truth(n_cases)) or {0})
    groups, tasks = {}, []
    # every model the groups condition, trained first as tasks where there is room (a run of this part alone
    # trained them one after the other here)
    train_models(ctx, sorted({(training_of.get(obj.name, obj.name), *_levels(part, bias)[level])
                              for obj in objects for bias in biases for level in ("general", *LEVELS)}))
    for obj in objects:
        trained_on = load_object(training_of.get(obj.name, obj.name))
        poses = sample_test_poses(obj, n_cases, part["yaw_range_deg"], stable_seed(ctx.seed, name, "poses", obj.name))
        clouds = [observe(obj, poses.take(i), ctx.settings) for i in range(n_cases)]
        starts = [[_start(obj, poses.take(i), stable_seed(ctx.seed, name, obj.name, i, j, "start"))
                   for j in range(int(ctx.actions.shape[0]))] for i in range(n_cases)]
        for bias in biases:
            default = _default(part, bias)
            pairs = _levels(part, bias)
            models = {level: train_model(ctx, trained_on, *fm) for level, fm in pairs.items()}
            general_prior = (ctx.prior("friction", pairs["general"][0]), ctx.prior("mass", pairs["general"][1]))
            group = _Group(ctx, name, obj, poses, clouds, starts, models, general_prior)
            if part.get("residual"):
                group.residual = train_residual(ctx, trained_on, *pairs["general"],
                                                int(part.get("residual_ensemble") or DEFAULT_ENSEMBLE),
                                                part.get("residual_scale_pushes"))
            files = {}
            for level in as_names(part["conditions"][bias]):
                path = contained_path(ctx.run_dir, "online", f"{name}_{obj.name}_{bias}_{level}.json",
                                      what="experiment or object name")
                made_from = fingerprint(version=ONLINE_VERSION, seed=ctx.seed, settings=asdict(ctx.settings),
                                        samples_per_action=ctx.samples_per_action, actions=ctx.actions.tolist(),
                                        models=[m.name for m in models.values()], cases=n_cases, observed=observed,
                                        part={k: v for k, v in part.items() if k not in RUN_CONTROL},
                                        priors=[repr(ctx.prior(k, n)) for k in ("friction", "mass")
                                                for n in (*LEVELS, "general", default)],
                                        sim=asdict(ctx.sim), physics=ctx.physics.engine, duration=ctx.duration)
                files[level] = (path, made_from)
            groups[(obj.name, bias)] = (group, files, bias)
            pending = [lv for lv, (path, made_from) in files.items() if _cached(path, made_from) is None]
            if pending:
                tasks.append((obj.name, bias, tuple(pending)))
    # every group's uncached conditions, in worker processes where there are cores to spare (they inherit the
    # trained models and clouds); each condition's scores are written as soon as they are done (a killed run
    # resumes), and the recording's cases are logged here
    bar = progress_bar(ctx, sum(n_cases * len(levels) for *_, levels in tasks), f"{name}: cases")

    def step(_, key: tuple) -> None:
        _run_conditions(groups[key[:2]], part, observed, n_cases, key[2])

    warm = next(iter(groups.values()))[0].models["general"] if groups else None
    if not prefetch(ctx, step, tasks, on_done=lambda key: bar.update(n_cases * len(key[2])), warm=warm,
                    what="groups of conditions scored"):
        for key in tasks:
            step(ctx, key)
            bar.update(n_cases * len(key[2]))
    bar.close()
    for (obj_name, bias), (group, files, _) in groups.items():
        outcomes = {}
        for level, (path, made_from) in files.items():
            cached = _cached(path, made_from)
            outcomes[level] = torch.tensor(cached["outcomes"], dtype=torch.float64)
            records += cached["records"]
            if ctx.recording is not None:
                for i in logged:
                    _log_case(group, part, bias, level, i, observed)
        separability.extend(_separability(obj_name, bias, outcomes))
    return records, {"online_separability": separability}


def _other(bias: str) -> str:
    """The parameter ``bias`` leaves fixed: mass under friction, friction under mass."""
    return "mass" if bias == "friction" else "friction"


def _default(part: Mapping[str, Any], bias: str) -> str:
    """The prior name of the parameter ``bias`` leaves fixed: ``default_mass`` or ``default_friction``, the
    paper's by default."""
    return str(part.get(f"default_{_other(bias)}", "paper_default"))


def _levels(part: Mapping[str, Any], bias: str) -> dict[str, tuple[str, str]]:
    """The (friction, mass) prior names of the library's models under ``bias``: each level of it, the other
    parameter at its default."""
    default = _default(part, bias)
    return {level: ((level, default) if bias == "friction" else (default, level)) for level in ("general", *LEVELS)}


def _cached(path, made_from) -> dict | None:
    """A condition's scores written earlier, if they were made from ``made_from``."""
    cached = json.loads(path.read_text()) if path.is_file() else None
    return cached if cached is not None and cached.get("made_from") == made_from else None


def _run_conditions(grouped: tuple, part: Mapping[str, Any], observed: list[int], n_cases: int,
                    levels: Sequence[str]) -> None:
    """Score the conditions ``levels`` of one object and bias: every case, then the condition's file, written
    atomically. The group's predictions that do not depend on the condition are made once for all of its
    conditions (its memo)."""
    group, files, bias = grouped
    other, default = _other(bias), _default(part, bias)
    for level in levels:
        path, made_from = files[level]
        scores = _Scores()
        cases = [_case(group, part, bias, level, i, observed, scores) for i in range(n_cases)]
        priors = {bias: group.ctx.prior(bias, level), other: group.ctx.prior(other, default)}
        written = {"made_from": made_from, "outcomes": torch.stack(cases).tolist(),
                   "records": _condition_records(group.obj.name, f"{bias}:{level}", scores, priors)}
        atomic_write_bytes(path, json.dumps(written).encode())


def _record(obj: str, predictor: str, k: int, condition: str, hacc: torch.Tensor, nll: torch.Tensor,
            errors: torch.Tensor) -> dict[str, Any]:
    """One results record of ``predictor`` (its ``method``; ``errors``: ``(n, 2)`` linear cm and angular deg of
    each scored push)."""
    return {"task": "online", "object": obj, "method": predictor, "model": None, "condition": condition,
            "observed": int(k), "metric": "displacement", "n": int(hacc.numel()),
            "hacc_mean": float(hacc.mean()), "hacc_std": float(hacc.std(unbiased=False)) if hacc.numel() > 1 else 0.0,
            "linear_cm": float(errors[:, 0].mean()), "angular_deg": float(errors[:, 1].mean()),
            "nll_mean": float(nll.mean()), "nll_median": float(nll.median())}


def separability(x: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    """How far apart two conditions' outcomes are: their mean outcomes (``(N, A, 2)``, the object's final position
    in each push's robot start frame) apart over their pooled spread, averaged over the actions; and the mean
    gap (cm)."""
    x, y = x.double(), y.double()
    gap = (x.mean(0) - y.mean(0)).norm(dim=-1)  # (A,)
    pooled = ((x.var(0, unbiased=True).sum(-1) + y.var(0, unbiased=True).sum(-1)) / 2).sqrt() if len(x) > 1 \
        else torch.full_like(gap, math.nan)
    return float((gap / pooled.clamp_min(1e-9)).mean()), float(gap.mean() * 100)


def _separability(obj: str, bias: str, outcomes: Mapping[str, torch.Tensor]) -> list[dict]:
    """:func:`separability` of adjacent conditions among those run (low and high are adjacent without medium)."""
    present = [level for level in LEVELS if level in outcomes]
    out = []
    for a, b in zip(present, present[1:], strict=False):
        value, gap_cm = separability(outcomes[a], outcomes[b])
        out.append({"object": obj, "parameter": bias, "pair": f"{a}|{b}", "separability": value,
                    "mean_gap_cm": gap_cm})
    return out


def run(cfg, out_dir, overrides=()) -> dict:
    """``python -m pushtorch experiment=online_adaptation`` with its report."""
    return run_suite(cfg, out_dir, [("online_adaptation", cfg.experiment, cfg.model)], overrides)
