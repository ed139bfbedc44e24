"""An experiment's training: simulated pushes under a training prior and the model trained on them,
cached per object and prior (paper, Experimental Setup, Fig. prediction_accuracy_methodology, training).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, replace
from pathlib import Path

import torch

from pushtorch.errors import RecordFormatError
from pushtorch.experiments.context import ExperimentContext, stable_seed
from pushtorch.experiments.tasks import prefetch, saved_as
from pushtorch.models.model import PushModel, load_model
from pushtorch.models.training import train_push_model
from pushtorch.objects import ObjectModel, load_object
from pushtorch.paths import contained_path
from pushtorch.sim.plan import Placement

__all__ = [
    "engine_tag",
    "placement_tag",
    "train_model",
    "train_models",
    "train_pooled",
    "train_residual",
    "training_records",
]

log = logging.getLogger("pushtorch.experiments")


def _model_key(obj_name: str, friction: str, mass: str) -> str:
    return f"{obj_name}_{friction}_{mass}"


def placement_tag(placement: Placement) -> str:
    """'' for the paper's placement, else a suffix naming what differs from it, e.g. ``_lateral_jitter0.05``
    (cached pushes, models and test sets of each placement keep apart)."""
    paper = asdict(Placement())
    return "".join(f"_{k}{v:g}" for k, v in asdict(placement).items() if v != paper[k])


def engine_tag(ctx: ExperimentContext) -> str:
    """'' in the pybullet world, else ``_<engine>`` (``_mujoco``): a run's cached pushes, models,
    predictions, truth and scores of one engine never stand in for another's, and a run directory may hold both."""
    return "" if ctx.sim.engine == "pybullet" else f"_{ctx.sim.engine}"


def _cache_tag(ctx: ExperimentContext) -> str:
    """What names a run's cached pushes and models besides object and priors: the placement and the engine."""
    return placement_tag(ctx.placement) + engine_tag(ctx)


def _training_folder(ctx: ExperimentContext, obj_name: str, friction: str, mass: str) -> Path:
    return contained_path(ctx.run_dir, "data", _model_key(obj_name, friction, mass) + _cache_tag(ctx),
                          what="object or prior name")


def training_records(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str,
                     progress: bool | None = None, plan=None):
    """The training pushes of ``obj`` under the named priors, simulated into the run's cache if missing.

    Paper, Experimental Setup: the robot placed against the object, mass and friction drawn from the
    training prior, ``samples_per_action`` pushes per action. ``plan``: that plan, where the caller drew it already
    (the same plan, drawn from the same seed).
    """
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import object_spec

    plan = _training_plan(ctx, obj, friction, mass) if plan is None else plan
    folder = _training_folder(ctx, obj.name, friction, mass)
    # a plan smaller than one shard (a generated shape's share of a pooled model's pushes) runs in this process:
    # a worker pool costs more than it saves
    small = len(plan) < ctx.shard_size
    run_plan(object_spec(obj), plan, folder, ctx.sim, workers=1 if small else ctx.workers,
             shard_size=ctx.shard_size, progress=ctx.progress if progress is None else progress,
             executor=None if small else ctx.executor)
    return load_records(folder, trajectories=False)  # training uses the final poses only


def _training_plan(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str):
    """The training pushes :func:`training_records` simulates: the same plan however often it is drawn."""
    from pushtorch.sim.plan import plan_training_pushes

    return plan_training_pushes(
        obj, ctx.actions, ctx.samples_per_action, ctx.prior("mass", mass), ctx.prior("friction", friction),
        seed=stable_seed(ctx.seed, "training", obj.name, friction, mass), duration=ctx.duration,
        placement=ctx.placement,
    )


#: Model meta keys a training writes besides what it was asked for (searches and what was pooled): a cached
#: model is reused when the rest matches.
_SEARCHED = ("bandwidths", "budget", "widening", "pooled")


def _training_meta(ctx: ExperimentContext, friction: str, mass: str, **extra) -> dict:
    """What a model's training was asked for, as its file's meta records it."""
    meta = {"friction": friction, "mass": mass, "samples_per_action": ctx.samples_per_action, "seed": ctx.seed,
            **extra}
    if ctx.placement != Placement():  # absent at the paper's placement, so earlier caches stay valid
        meta["placement"] = asdict(ctx.placement)
    if engine_tag(ctx):  # likewise absent in the default world
        meta["engine"] = ctx.sim.engine
    return meta


def _cached_model(ctx: ExperimentContext, path: Path, key: str, meta: dict) -> PushModel | None:
    """The model file at ``path`` if it was trained with the context's settings and ``meta``, else None."""
    if not path.is_file():
        return None
    try:
        cached = load_model(path)
    except RecordFormatError as exc:
        log.warning("retraining %s: %s", key, exc)
        return None
    trained = {k: v for k, v in cached.meta.items() if k not in _SEARCHED}
    return cached if cached.configured_settings == ctx.settings and trained == meta else None


def train_model(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str) -> PushModel:
    """A model of ``obj`` trained under the named friction and mass priors (cached in the run directory).

    The model file is reused when its settings and training size match the context's; otherwise the
    model is retrained from the (cached) training pushes.
    """
    key = _model_key(obj.name, friction, mass)
    meta = _training_meta(ctx, friction, mass)
    cache_key = (f"{key}|{json.dumps(asdict(ctx.settings), sort_keys=True)}|{ctx.samples_per_action}"
                 f"|{_cache_tag(ctx)}")
    if cache_key in ctx._models:
        return ctx._models[cache_key]
    path = contained_path(ctx.run_dir, "models", f"{key}{_cache_tag(ctx)}.npz",
                          what="object or prior name")
    model = _cached_model(ctx, path, key, meta)
    if model is None:
        records = training_records(ctx, obj, friction, mass)
        log.info("training %s on %d pushes (%d valid)", key, len(records), int(records.valid.sum()))
        model = train_push_model(obj, records, ctx.settings, name=key,
                                 generator=torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key)),
                                 meta=meta)
        model.save(path)
    if ctx.recording is not None and all(m.name != model.name for m in ctx._models.values()):
        _log_training(ctx, model, obj)
    ctx._models[cache_key] = saved_as(model, load_model, str(path))
    return model


def train_models(ctx: ExperimentContext, keys) -> dict[tuple[str, str, str], PushModel]:
    """:func:`train_model` for every ``(object name, friction, mass)`` of ``keys``, as tasks where there is
    room (:func:`pushtorch.experiments.tasks.prefetch`). On a Ray or Slurm executor the training pushes go to
    the cluster first as shards, every model's at once (a thread per model submits its run's shards and waits),
    so that the pushes are spread as widely as the cluster allows and each model's task only trains."""
    from concurrent.futures import ThreadPoolExecutor

    from pushtorch.sim.executors import connect

    keys = list(keys)
    # a run smaller than a shard simulates in this process (training_records), in one world at a time: no threads
    shards = ctx.samples_per_action * int(ctx.actions.shape[0]) >= ctx.shard_size
    if ctx.executor.kind != "local" and keys and shards:
        start = time.perf_counter()
        objects = [load_object(t) for t, _, _ in keys]
        with ThreadPoolExecutor(max_workers=len(keys), thread_name_prefix="pushtorch-training-pushes") as pool:
            # the threads draw the plans while this one connects (Ray starts in seconds; its processes stay tied to
            # the thread that starts them), then each submits its run's shards and waits
            plans = [pool.submit(_training_plan, ctx, o, f, m) for o, (_, f, m) in zip(objects, keys, strict=True)]
            connect(ctx.executor)
            connected = time.perf_counter()
            runs = [pool.submit(lambda o, f, m, plan: training_records(ctx, o, f, m, False, plan.result()), o, f, m,
                                plan) for o, (_, f, m), plan in zip(objects, keys, plans, strict=True)]
            for run in runs:
                run.result()  # a run's error, raised here
        log.info("the training pushes of %d models as %s shards: %.0f s (%.0f s connecting, while planning)",
                 len(keys), ctx.executor.kind, time.perf_counter() - start, connected - start)
    prefetch(ctx, lambda task_ctx, tfm: train_model(task_ctx, load_object(tfm[0]), *tfm[1:]), keys,
             what="models trained")
    return {(t, f, m): train_model(ctx, load_object(t), f, m) for t, f, m in keys}


def train_residual(ctx: ExperimentContext, obj: ObjectModel, friction: str, mass: str, ensemble: int,
                   scale_pushes: int | None = None):
    """The residual model (:mod:`pushtorch.models.residual`) of :func:`train_model`'s model, its residuals taken
    against the physics engine (``ctx.physics``: the peers' simulator, never the world's unless configured so),
    cached as ``<run_dir>/models/<key>_residual_vs_<engine>.npz``. Its kernels' scale is chosen on
    ``scale_pushes`` held-out training pushes per action (default
    :data:`~pushtorch.evaluation.transfer.RESIDUAL_SCALE_PUSHES`; 0: not chosen), predicted as test pushes are
    (:func:`pushtorch.evaluation.transfer.choose_residual_scale`).

    A push model read from its file no longer knows which push each kernel came from, so a residual not yet
    cached trains the push model again from the same cached pushes and seed (the same model, bit for bit)."""
    from pushtorch.evaluation.transfer import RESIDUAL_SCALE_PUSHES, choose_residual_scale
    from pushtorch.models.residual import train_residual_model, with_ensemble
    from pushtorch.models.residual_file import load_residual_model

    scale_pushes = RESIDUAL_SCALE_PUSHES if scale_pushes is None else int(scale_pushes)
    model = train_model(ctx, obj, friction, mass)
    key = _model_key(obj.name, friction, mass)
    path = _residual_path(ctx, key)
    if path.is_file():
        try:
            cached = load_residual_model(path)
            if cached.sim == ctx.physics and cached.model.name == model.name and cached.outcomes is not None \
                    and cached.model.settings == model.settings and _asked(cached.model.meta) == _asked(model.meta) \
                    and _scale_chosen(cached, scale_pushes):
                return saved_as(with_ensemble(cached, ensemble), _read_residual, str(path), int(ensemble))
        except RecordFormatError as exc:
            log.warning("retraining the residual of %s: %s", key, exc)
    records = training_records(ctx, obj, friction, mass, progress=False)
    fresh = _knowing_pushes(ctx, obj, model, records, key)
    log.info("training the residual of %s against %s on %d pushes", key, ctx.physics.engine,
             int(records.valid.sum()))
    residual = train_residual_model(fresh, obj, records, ctx.physics, ensemble)
    if scale_pushes > 0:
        residual = choose_residual_scale(residual, obj, records, scale_pushes,
                                         torch.Generator().manual_seed(stable_seed(ctx.seed, "residual_scale", key)))
    residual.save(path)
    return saved_as(residual, _read_residual, str(path), int(ensemble))


def _knowing_pushes(ctx: ExperimentContext, obj, model, records, key: str):
    """``model``, or where it was read from its file (its kernels no longer know which push gave them, which
    holding a push out needs) the same model trained again from the same cached pushes and seed, bit for bit."""
    if all(m.manipulator.push is not None for m in model.motions):
        return model
    return train_push_model(obj, records, ctx.settings, name=key,
                            generator=torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key)),
                            meta={k: v for k, v in model.meta.items() if k not in _SEARCHED})


def _asked(meta: dict) -> dict:
    """A model's meta without what its training searched (:data:`_SEARCHED`): the searches' reports differ between
    versions (a push model file cached by an earlier one), and their outcome is in the model's settings."""
    return {k: v for k, v in meta.items() if k not in _SEARCHED}


def _scale_chosen(residual, pushes: int) -> bool:
    """Whether a cached residual model's kernels' scale was chosen as asked: on ``pushes`` held-out pushes per
    action over today's grid, with its point prediction (0: not chosen)."""
    from pushtorch.evaluation.transfer import RESIDUAL_SCALES
    from pushtorch.models.residual import POINTS

    chosen = residual.meta.get("scale") or {}
    return chosen.get("pushes_per_action", 0) == pushes and (not pushes or (
        chosen.get("grid") == list(RESIDUAL_SCALES) and (chosen.get("point") or {}).get("points") == list(POINTS)))


def widen_residuals_by_novelty(ctx: ExperimentContext, trained: dict, pushes: int, shapes: str | None = None) -> dict:
    """``{(object, friction, mass): residual model}`` with each model's novelty widening, defensive part and
    uncorrected share chosen on the training objects of its prior
    (:func:`pushtorch.evaluation.transfer.choose_novelty_widening`: each object's model scores ``pushes`` of every
    other's training pushes per object, as many of each generated shape of ``shapes``, a ``shapes:<kind>:<count>``
    entry, pushed under the same prior, and as many of each action's own, held out; a tie in likelihood is broken
    by the same pushes' 90 % coverage, then sharpness), each saved back to its file. A prior with one
    training object keeps its models as they are; a model whose file already holds the choice across the same
    objects and shapes is kept as read."""
    from pushtorch.evaluation.transfer import choose_novelty_widening
    from pushtorch.models.residual import novelty_scored_as_now
    from pushtorch.objects.shapes import training_shapes

    generated = training_shapes(shapes) if shapes else []

    out = dict(trained)
    by_prior: dict[tuple[str, str], list] = {}
    for t, f, m in trained:
        by_prior.setdefault((f, m), []).append(t)
    for (f, m), names in sorted(by_prior.items()):
        names = sorted(names)
        models = [trained[(t, f, m)] for t in names]
        if len(names) < 2 or all((r.meta.get("novelty") or {}).get("across") == names
                                 and (r.meta.get("novelty") or {}).get("shapes", []) == [o.name for o in generated]
                                 and (r.meta.get("novelty") or {}).get("pushes_per_shape") == int(pushes)
                                 and novelty_scored_as_now(r.meta.get("novelty"))
                                 for r in models):
            continue
        objects = [load_object(t) for t in names]
        records = [training_records(ctx, o, f, m, progress=False) for o in objects]
        models = [replace(r, model=_knowing_pushes(ctx, o, r.model, rec, _model_key(t, f, m)))  # own pushes held out
                  for r, o, rec, t in zip(models, objects, records, names, strict=True)]
        shape_records = [training_records(ctx, o, f, m, progress=False) for o in generated]
        generator = torch.Generator().manual_seed(stable_seed(ctx.seed, "residual_novelty", f, m, *names))
        widened = choose_novelty_widening(models, objects, records, pushes, generator, shapes=generated,
                                          shape_records=shape_records)
        for t, residual in zip(names, widened, strict=True):
            path = _residual_path(ctx, _model_key(t, f, m))
            residual.save(path)
            out[(t, f, m)] = saved_as(residual, _read_residual, str(path), int(residual.ensemble))
    return out


def _residual_path(ctx: ExperimentContext, key: str) -> Path:
    """Where a residual model of the model ``key`` is cached: beside it, named by the engine it corrects."""
    return contained_path(ctx.run_dir, "models", f"{key}{_cache_tag(ctx)}_residual_vs_{ctx.physics.engine}.npz",
                          what="object or prior name")


def _read_residual(path: str, ensemble: int):
    """A residual model file with ``ensemble`` rollouts per prediction, as :func:`train_residual` returned it."""
    from pushtorch.models.residual import with_ensemble
    from pushtorch.models.residual_file import load_residual_model

    return with_ensemble(load_residual_model(path), ensemble)


def _log_training(ctx: ExperimentContext, model: PushModel, obj: ObjectModel) -> None:
    from pushtorch.viz.contacts import log_contact_model

    # one row of trained models along +x at y = -1.5 m, clear of the experiments around the origin
    index = len({m.name for m in ctx._models.values()})
    log_contact_model(ctx.recording, model, obj, object_pose=obj.resting_pose(x=1.0 * index, y=-1.5))


def train_pooled(ctx: ExperimentContext, shapes: list[ObjectModel], friction: str, mass: str,
                 widening_pushes: int, name: str = "shapes") -> PushModel:
    """One model pooled over ``shapes``' training pushes (:mod:`pushtorch.models.pooled`), its bandwidths chosen
    on the pool and its widening across shapes (:func:`pushtorch.evaluation.transfer.choose_widening`), cached as
    ``<run_dir>/models/<name>_<friction>_<mass>.npz``. The pushes are the shapes' own cached training pushes
    (:func:`training_records`, ``ctx.samples_per_action`` per action)."""
    from pushtorch.evaluation.transfer import choose_widening
    from pushtorch.models.pooled import fit_shape_parts, train_pooled_model

    key = _model_key(name, friction, mass)
    meta = _training_meta(ctx, friction, mass, shapes=[s.name for s in shapes], widening_pushes=int(widening_pushes))
    cache_key = f"{key}|{json.dumps(asdict(ctx.settings), sort_keys=True)}|{json.dumps(meta, sort_keys=True)}"
    if cache_key in ctx._models:
        return ctx._models[cache_key]
    path = contained_path(ctx.run_dir, "models", f"{key}{_cache_tag(ctx)}.npz", what="object or prior name")
    model = _cached_model(ctx, path, key, meta)
    if model is None:
        records = [training_records(ctx, s, friction, mass) for s in shapes]
        log.info("training %s on %d shapes, %d pushes", key, len(shapes), sum(len(r) for r in records))
        generator = torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key))
        parts = fit_shape_parts(shapes, records, ctx.settings, generator)
        model = train_pooled_model(shapes, records, ctx.settings, name=key, generator=generator, meta=meta,
                                   parts=parts)
        model = choose_widening(model, shapes, records, parts, widening_pushes, generator)
        model.save(path)
    ctx._models[cache_key] = saved_as(model, load_model, str(path))
    return model


def train_pooled_residual(ctx: ExperimentContext, shapes: list[ObjectModel], friction: str, mass: str,
                          widening_pushes: int, ensemble: int, name: str = "shapes"):
    """The residual model (:mod:`pushtorch.models.residual`) of :func:`train_pooled`'s model, its residuals taken
    against the physics engine on every shape's training pushes and its widening chosen across the shapes
    (:func:`pushtorch.evaluation.transfer.choose_residual_widening`), cached as
    ``<run_dir>/models/<key>_residual_vs_<engine>.npz``. A pooled model read from its file is fitted again from the
    same pushes and seed to recover which push each kernel came from (the same kernels, checked)."""
    from pushtorch.evaluation.transfer import choose_residual_widening
    from pushtorch.models.pooled import train_pooled_model
    from pushtorch.models.residual import (
        DEFENSIVE_PARTS,
        POINTS,
        UNCORRECTED_RATES,
        train_residual_model,
        with_ensemble,
    )
    from pushtorch.models.residual_file import load_residual_model

    model = train_pooled(ctx, shapes, friction, mass, widening_pushes, name)
    key = _model_key(name, friction, mass)
    path = _residual_path(ctx, key)
    if path.is_file():
        try:
            cached = load_residual_model(path)
            if cached.sim == ctx.physics and _asked(cached.model.meta) == _asked(model.meta) \
                    and cached.outcomes is not None and cached.model.settings == model.settings \
                    and cached.shape_names == [s.name for s in shapes] \
                    and (cached.meta.get("widening") or {}).get("defensive") == [list(d) for d in DEFENSIVE_PARTS] \
                    and (cached.meta.get("widening") or {}).get("uncorrected") == list(UNCORRECTED_RATES) \
                    and ((cached.meta.get("widening") or {}).get("point") or {}).get("points") == list(POINTS):
                return saved_as(with_ensemble(cached, ensemble), _read_residual, str(path), int(ensemble))
        except RecordFormatError as exc:
            log.warning("retraining the residual of %s: %s", key, exc)
    records = [training_records(ctx, s, friction, mass, progress=False) for s in shapes]
    if any(m.manipulator.push is None for m in model.motions):  # read from its file: fit its kernels again
        generator = torch.Generator().manual_seed(stable_seed(ctx.seed, "fit", key))
        fresh = train_pooled_model(shapes, records, ctx.settings, name=key, generator=generator)
        if not all(torch.equal(a.manipulator.m.p, b.manipulator.m.p.to(a.manipulator.m.p))
                   for a, b in zip(fresh.motions, model.motions, strict=True)):
            raise RecordFormatError(f"the pooled model {key} fitted again differs from its file: delete {path.parent}")
        model = replace(model, motions=fresh.motions)
    log.info("training the residual of %s against %s on %d shapes", key, ctx.physics.engine, len(shapes))
    residual = train_residual_model(model, shapes, records, ctx.physics, ensemble)
    residual = choose_residual_widening(residual, shapes, records, widening_pushes,
                                        torch.Generator().manual_seed(stable_seed(ctx.seed, "residual_widening", key)))
    residual.save(path)
    return saved_as(residual, _read_residual, str(path), int(ensemble))
