"""How the residual model transfers to shapes it was not trained on: the measurements behind docs/method.md's
"The residual model" (Many shapes) and the shape-transfer target of its finding.

``distance <run>``: for a run folder of the engine gap (``python -m pushtorch experiment=engine_gap``; residual
models of the cube and the cylinder, and their training pushes), (1) each training object's residual model
scores ``--pushes`` of the *other* object's training pushes, predicted from their robot starts, at every widening
``κ`` of :data:`pushtorch.evaluation.transfer.RESIDUAL_WIDENINGS` (what a leave-one-shape-out choice across the
two would choose); (2) the squared contact distance ``d²`` (:func:`pushtorch.prediction.transfer_distance`) of
each catalogue object's pushes, from the robot start its training object's model chooses at six random yaws: a
diagnosis of what a widening by contact distance could tell apart, never a choice of anything.

``novelty <run>``: for the same run, (1) each training object's residual model scores ``--pushes`` of the other
object's training pushes (and of its own, in sample) at every novelty widening ``ν`` of
:data:`pushtorch.models.residual.NOVELTY_WIDENINGS` (the same rollouts, the kernels' stds times
``sqrt(1 + ν·n)``), with the predictions' median novelty ``n``; (2) per catalogue object at six random yaws and
every action, how far the prediction's rollouts did something its training object's rollouts never did
(:func:`pushtorch.models.residual.outcome_novelty`: the squared distance, in the training outcomes' stds, from
the rollout's displacement and turn in the robot's start frame to the nearest training rollout's of that action
that the contact reaches; the median over the rollouts). (2) is a diagnosis of what a widening by novelty can tell
apart, never a choice.

``coverage <run>``: for the same run, each catalogue object's test pushes (its ground truth records, from their
robot starts) predicted again by its training object's residual model from fresh single-shot clouds (other draws
than the run's), and the share of truths inside the 50 % and 90 % regions (docs/method.md, "Likelihood score") of
the whole density and of its corrected kernels alone (:func:`pushtorch.prediction.residual.narrow_density`): what
the defensive part and the uncorrected share do to calibration (with the predictions' median uncorrected share
``ρ``, the weight on the rollouts themselves, and the novelty ``n + ξ·δ²`` that sets it), and how much a second
draw moves it (``--draw k``: the predictions' seeds moved by 1000 k; the last line counts the objects whose 90 %
coverage lies in the engine gap's band, [0.80, 0.97]).

``hedges <run>``: for the same run, each catalogue object's test pushes predicted again as ``coverage`` predicts
them (the same clouds and seeds at ``--draw k``), and the 90 % coverage and mean nll of the density hedged in five
ways from the same rollouts: as the run chose (``run``), without the uncorrected share (``tau=0``), with its rate
at 1 (``tau=1``), with a shape term added to the novelty that sets both shares (``shape``: the squared distance of
the log principal radii of gyration of the cloud's body from the nearest of its training object's bodies, in units
of :data:`SHAPE_WIDTH`), and with the defensive part spread over three widths, ``w/3``, ``w`` and ``3w`` in equal
thirds (``graded``). The last line per form counts the objects in the engine gap's band: whether another hedge
would calibrate the density, never a choice (the test pushes choose nothing).

``calibration <run>``: for the same run, each training object's models trained again from the run's pushes (as
``scale``), ``--pushes`` of its pushes per action held out in turn and predicted as test pushes are, at the run's
kernels' scale and with its hedges: the share of them inside the 90 % region, with the hedges and of the corrected
kernels alone. Set beside ``hedges``' own objects: whether held-out training pushes calibrate as the test pushes do
(what a choice of the hedges by calibration on them would rest on). Then how far off the object's centre the bumper
meets it (the object's start across the robot's heading) in the test pushes, which start from the push model's
own contact, and in the held-out training pushes, which start from the training placement's, with the coverage of
the held-out half nearer the centre and of the half farther: whether the test pushes' contacts are easier.

``disagreement <run>``: for the same run, each catalogue object's test pushes predicted again from fresh clouds by
its training object's push model and, from the same push condition, its residual model: how far the push model's
point lies from the corrected mode (the H_acc of one displacement against the other), beside each one's H_acc:
whether the two predictions' disagreement tells where the corrections do not carry (a per-prediction hedge's
signal), never a choice.

``signals <run>``: for the same run, each training object's residual model predicts ``--pushes`` of the other
object's training pushes and of each generated shape's that choose its hedges (the run's
``residual_novelty_shapes``), and, from the same push condition, its push model: per group, the share of truths
inside the density's 90 % region, the median novelty and disagreement (as ``disagreement``), and among the pushes
of low and of high novelty (below and above the median) the coverage where the two predictions agree and where
they disagree: whether the disagreement tells the held-out pushes whose corrections do not carry, where novelty
does not (a hedge's signal measured on training pushes, never on the test objects).

``scale <run>``: for the same run, each training object's residual model trained again from the run's pushes
(its push model with another seed than the run's, so that its kernels know their pushes), ``--pushes`` of its
pushes per action held out in turn and predicted as test pushes are, and the mean held-out nll at every kernels'
scale of :data:`pushtorch.evaluation.transfer.RESIDUAL_SCALES`, without the hedges (what the scale is chosen on)
and with the run's hedges (defensive part, uncorrected share, disagreement weight): where a choice of the scale
with the hedges in place would land.

``weights <run>``: for a shape-transfer run (``experiment=quickstart_transfer``), the pooled residual model's
mean correction per training shape and action (translation cm / turn rad), and for each transfer object at three
yaws the four training shapes whose kernels weigh most in its predictions (their share of the contact weight):
where each test object borrows its corrections from.

``target <run>``: for a shape-transfer run (``experiment=quickstart_transfer``), per object the H_acc of
``pushtorch_residual``, ``pushtorch_shapes`` and ``physics_from_cloud`` with the paired SE of the residual against
the better of the two, its nll and 90 % coverage. The last line is exactly ``objects=<n> residual_le_best=<k>``
(the issue's target: ≤ the better + 2 paired SE on at least 3 of 4).

    .venv/bin/python tools/residual_transfer.py distance runs/engine_gap [--pushes 15]
    .venv/bin/python tools/residual_transfer.py novelty runs/engine_gap [--pushes 15]
    .venv/bin/python tools/residual_transfer.py coverage runs/engine_gap_pybullet [--draw 0]
    .venv/bin/python tools/residual_transfer.py hedges runs/engine_gap_pybullet [--draw 0]
    .venv/bin/python tools/residual_transfer.py disagreement runs/engine_gap_pybullet
    .venv/bin/python tools/residual_transfer.py signals runs/engine_gap_pybullet [--pushes 15]
    .venv/bin/python tools/residual_transfer.py scale runs/engine_gap_pybullet [--pushes 10]
    .venv/bin/python tools/residual_transfer.py calibration runs/engine_gap_pybullet [--pushes 10]
    .venv/bin/python tools/residual_transfer.py weights runs/quickstart_transfer
    .venv/bin/python tools/residual_transfer.py target runs/quickstart_transfer
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from pushtorch import se3
from pushtorch.distribution import DefensiveMixture
from pushtorch.errors import PushtorchError
from pushtorch.evaluation.likelihood import covered, hdr_thresholds, nll
from pushtorch.evaluation.metrics import accuracy, displaced
from pushtorch.evaluation.transfer import (
    RESIDUAL_SCALES,
    RESIDUAL_WIDENINGS,
    own_held_out_pushes,
    residual_nll_grid,
)
from pushtorch.experiments.figures import FIGURE_DATA, read_figure_data
from pushtorch.models.residual import NOVELTY_WIDENINGS, defensive_share, train_residual_model
from pushtorch.models.residual_file import load_residual_model
from pushtorch.models.training import train_push_model
from pushtorch.objects import load_object
from pushtorch.objects.shapes import training_shapes
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict, transfer_distance
from pushtorch.prediction.residual import (
    defensive_factors,
    disagreeing,
    hedged_density,
    learned_point,
    narrow_density,
    novelty_factors,
    predict_residual,
    rescaled,
)
from pushtorch.sim.bodies import cloud_body
from pushtorch.sim.records import load_records

#: ``hedges``: a shape 5 % larger or smaller in one radius of gyration than every training body adds 1 to the novelty
#: (one object's bodies from its single-shot clouds differ by under 0.5 %, the catalogue's shapes by 4-30 %)
SHAPE_WIDTH = 0.05
HEDGES = ("run", "tau=0", "tau=1", "shape", "graded")

TRAINING_OF = {"cube": "cube", "prism_thin": "cube", "prism_long": "cube", "cylinder": "cylinder",
               "cylinder_wide": "cylinder", "hybrid": "cylinder"}


def _one(pattern: str) -> str:
    found = sorted(glob.glob(pattern))
    if not found:
        raise SystemExit(f"nothing matches {pattern}: is this the right run folder?")
    return found[0]


def _scored(residual, obj, run: Path, pushes: int, generator: torch.Generator, factors) -> tuple[np.ndarray, list]:
    """``pushes`` of ``obj``'s training pushes in ``run`` predicted by ``residual`` from their robot starts: each
    push's nll with the kernels' stds times each of ``factors(prediction)``, and the predictions."""
    valid = load_records(_one(f"{run}/data/{obj.name}_*"))
    valid = valid.take(valid.valid)
    rows, predictions = [], []
    for i in torch.randperm(len(valid), generator=generator)[:pushes].tolist():
        push = valid.take(torch.tensor([i]))
        start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
        robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
        cloud = capture_partial_cloud(obj, start, voxel_size=residual.settings.voxel_size)
        prediction = predict_residual(dataclasses.replace(residual, disagreement=0.0), cloud, push.action[0].float(),
                                      i, robot_start=robot)
        truth = se3.Pose.unchecked(push.object_final.p.float(), push.object_final.q.float())
        rows.append([float(nll(rescaled(prediction, f), truth, start, prediction.start, obj.symmetry)[0])
                     for f in factors(prediction)])
        predictions.append(prediction)
    return np.asarray(rows), predictions


def _per_object(models: dict, generator: torch.Generator, what: str, value) -> None:
    """Per catalogue object at six random yaws and every action, the quantiles of ``value(prediction, action)``
    under its training object's residual model."""
    for obj_name, trained in TRAINING_OF.items():
        residual, obj = models[trained], load_object(obj_name)
        values = []
        for k in range(6):
            yaw = float(torch.empty(()).uniform_(-math.pi / 4, math.pi / 4, generator=generator))
            cloud = capture_partial_cloud(obj, obj.resting_pose(yaw=yaw), voxel_size=residual.settings.voxel_size)
            for a in range(len(residual.actions)):
                values.append(float(value(predict_residual(dataclasses.replace(residual, disagreement=0.0), cloud,
                                                           residual.actions[a], 3 * k + a), a)))
        q10, median, q90 = np.quantile(values, [0.1, 0.5, 0.9])
        print(f"{obj_name:14s} ({trained}'s model) {what} median {median:.2f} (10 % {q10:.2f}, 90 % {q90:.2f})")


def _predicted(residual, cloud, action, seed: int | torch.Generator, robot, unhedged: bool = False):
    """One push predicted by ``residual`` as the run predicts it: from its push model's push condition where its
    disagreement hedge needs that model's point (``seed``, or a generator, drawn from by both); ``unhedged``: without
    the hedges, the prediction knowing the disagreement (:func:`_hedged` hedges it as the run's model)."""
    model = dataclasses.replace(residual, novelty_widening=0.0, defensive=(0.0, 0.0, 0.0), uncorrected=0.0,
                                disagreement=0.0) if unhedged else residual
    if residual.disagreement == 0:
        return predict_residual(model, cloud, action, seed, robot_start=robot)
    own = predict(residual.model, cloud, action, torch.Generator().manual_seed(seed) if isinstance(seed, int)
                  else seed, robot_start=robot)
    return predict_residual(model, cloud, action, seed, condition=own.condition,
                            learned=(own.condition.object_pose, own.final_pose))


def _models(run: Path) -> dict:
    # the corrected kernels are what this tool looks into, whatever point the models report
    return {o: dataclasses.replace(load_residual_model(_one(f"{run}/models/{o}_*_residual_vs_*.npz")),
                                   point="corrected") for o in ("cube", "cylinder")}


def distance(run: Path, pushes: int) -> None:
    models = _models(run)
    generator = torch.Generator().manual_seed(0)
    for name, other in (("cube", "cylinder"), ("cylinder", "cube")):
        residual = models[name]
        rows, _ = _scored(residual, load_object(other), run, pushes, generator,
                          lambda p: [math.sqrt(1 + k * p.contact_distance2) for k in RESIDUAL_WIDENINGS])
        mean = rows.mean(0)
        print(f"{name}'s residuals on {len(rows)} {other} pushes: held-out nll by kappa "
              + ", ".join(f"{k:g}: {v:.2f}" for k, v in zip(RESIDUAL_WIDENINGS, mean, strict=True))
              + f"; best kappa {RESIDUAL_WIDENINGS[int(mean.argmin())]:g}")
    _per_object(models, generator, "d2", lambda p, a: transfer_distance(_model_of(models, p), p.condition, a))


def _test_pushes(run: Path, obj, voxel_size: float):
    """``obj``'s test pushes in ``run`` (its ground truth records): each ``(index, cloud, action, robot start,
    start, truth)``, the single-shot cloud drawn afresh at the push's start."""
    records = load_records(_one(f"{run}/truth/*_{obj.name}_paper_default_paper_default*"))
    for i in torch.nonzero(records.valid).reshape(-1).tolist():
        push = records.take(torch.tensor([i]))
        start, robot, truth = _poses(push)
        cloud = capture_partial_cloud(obj, start, voxel_size=voxel_size)
        yield i, cloud, push.action[0].float(), robot, start, truth


def _poses(push) -> tuple[se3.Pose, se3.Pose, se3.Pose]:
    """One push's (records of one) object start, robot start and true final pose, float32."""
    start = se3.Pose.unchecked(push.object_initial.p[0].float(), push.object_initial.q[0].float())
    robot = se3.Pose.unchecked(push.robot_start.p[0].float(), push.robot_start.q[0].float())
    return start, robot, se3.Pose.unchecked(push.object_final.p.float(), push.object_final.q.float())


def _scored_regions(density, prediction, obj, start, truth, seed: int) -> tuple[torch.Tensor, float]:
    """``(L,)`` float64 whether the truth lies inside each of the density's regions (50 % and 90 %: docs/method.md,
    "Likelihood score"; thresholds from draws seeded ``seed``), and its nll."""
    regions = hdr_thresholds(density, generator=torch.Generator().manual_seed(seed), symmetry=obj.symmetry,
                             plane=prediction.start)
    scored = nll(density, truth, start, prediction.start, obj.symmetry)
    return covered(scored, regions).reshape(-1).double(), float(scored.reshape(-1)[0])

def coverage(run: Path, draw: int) -> None:
    models = _models(run)
    in_band = 0
    for obj_name, trained in TRAINING_OF.items():
        residual, obj = models[trained], load_object(obj_name)
        inside: dict[str, list] = {"density": [], "corrected kernels alone": []}
        uncorrected = []
        for i, cloud, action, robot, start, truth in _test_pushes(run, obj, residual.settings.voxel_size):
            prediction = _predicted(residual, cloud, action, i + 1000 * draw, robot)
            uncorrected.append([prediction.uncorrected_share, prediction.outcome_novelty])
            for label, density in zip(inside, (prediction.density, narrow_density(prediction)), strict=True):
                inside[label].append(_scored_regions(density, prediction, obj, start, truth, i)[0])
        shares = {label: torch.stack(rows).mean(0).tolist() for label, rows in inside.items()}
        in_band += 0.80 <= shares["density"][1] <= 0.97
        print(f"{obj_name:14s} ({trained}'s model, {len(inside['density'])} pushes) 50 % / 90 % coverage: "
              + "; ".join(f"{label} {v[0]:.2f} / {v[1]:.2f}" for label, v in shares.items())
              + "; uncorrected share and the novelty it takes, medians {:.3f}, {:.2f}".format(
                  *np.median(uncorrected, axis=0)), flush=True)
    print(f"draw={draw} coverage_ok={in_band} of {len(TRAINING_OF)} (the density's 90 % coverage in [0.80, 0.97])")


def _radii(points: torch.Tensor, estimate: se3.Pose) -> np.ndarray:
    """``(3,)`` the log principal radii of gyration (m) of the body that ``points`` build (:func:`cloud_body`): the
    body's size and proportions, whatever its heading."""
    body, _ = cloud_body(points, estimate)
    inertia = np.asarray(body.mesh.moment_inertia) / body.mesh.mass
    return 0.5 * np.log(np.sort(np.linalg.eigvalsh(inertia)))


def _hedged(prediction, residual, form: str, shape_d2: float):
    """``prediction`` (made without hedges) hedged as ``residual`` hedges it, or in one of the other ``HEDGES``."""
    p = disagreeing(prediction, residual.disagreement)
    novelty = p.outcome_novelty + (shape_d2 / SHAPE_WIDTH**2 if form == "shape" else 0.0)
    p = dataclasses.replace(p, outcome_novelty=novelty)
    rate = {"tau=0": 0.0, "tau=1": 1.0}.get(form, residual.uncorrected)
    factors = novelty_factors(p, residual.novelty_widening)
    eps = defensive_share(residual.defensive, novelty)
    if form != "graded" or eps == 0:
        return hedged_density(p, factors, residual.defensive, rate)
    w = residual.defensive[2]  # the defensive part spread over w/3, w and 3w in equal shares

    def part(f):  # the corrected kernels and the uncorrected share, without a defensive part
        return hedged_density(p, f, (0.0, 0.0, 0.0), rate)

    wide = part(defensive_factors(p, factors, w / 3))
    for k, width in enumerate((w, 3 * w), 2):  # each new width takes 1/k of the k so far
        wide = DefensiveMixture(wide, part(defensive_factors(p, factors, width)), 1.0 / k)
    return DefensiveMixture(part(factors), wide, eps)


def hedges(run: Path, draw: int) -> None:
    models = _models(run)
    bodies = {}
    for name in models:
        records = load_records(_one(f"{run}/data/{name}_*"))
        starts = [_poses(records.take(torch.tensor([i])))[0] for i in torch.nonzero(records.valid).reshape(-1)[:12]]
        obj = load_object(name)
        bodies[name] = np.stack([_radii(capture_partial_cloud(obj, s, voxel_size=models[name].settings.voxel_size)
                                        .points, s) for s in starts])
    table = {form: [] for form in HEDGES}
    for obj_name, trained in TRAINING_OF.items():
        residual, obj = models[trained], load_object(obj_name)
        rows = {form: [] for form in HEDGES}
        for i, cloud, action, robot, start, truth in _test_pushes(run, obj, residual.settings.voxel_size):
            prediction = _predicted(residual, cloud, action, i + 1000 * draw, robot, unhedged=True)
            d2 = float(((bodies[trained] - _radii(cloud.points, prediction.condition.object_pose)) ** 2).sum(1).min())
            for form in HEDGES:
                inside, scored = _scored_regions(_hedged(prediction, residual, form, d2), prediction, obj, start,
                                                 truth, i)
                rows[form].append([float(inside[1]), scored])
        for form in HEDGES:
            table[form].append(np.asarray(rows[form]).mean(0))
        print(f"{obj_name:14s} ({trained}'s model, {len(rows['run'])} pushes) shape distance {d2:.3f} (last push)",
              flush=True)
    print("form     " + " ".join(f"{o:>13s}" for o in TRAINING_OF) + "  (90 % coverage / mean nll)")
    for form, cells in table.items():
        band = sum(0.80 <= c[0] <= 0.97 for c in cells)
        print(f"{form:8s} " + " ".join(f"{c[0]:6.2f} /{c[1]:6.1f}" for c in cells) + f"  in band {band} of 6")


def _apart(own, corrected, obj, start, truth) -> list[float]:
    """H_acc of the push model's prediction ``own`` against the residual's corrected mode (``corrected``, made from
    the same push condition), and of each against ``truth``: each a displacement from the body's start applied to
    the true ``start``."""
    learned = learned_point((own.condition.object_pose, own.final_pose), corrected.start)
    as_learned, as_corrected = (displaced(corrected.start, point, start) for point in (learned, corrected.final_pose))
    return [float(accuracy(moved, against, obj).hacc) for moved, against in
            ((as_learned, as_corrected), (as_corrected, truth), (as_learned, truth))]


def _hedge_shapes(run: Path) -> list:
    """The generated shapes whose pushes chose the run's hedges (its parts' ``residual_novelty_shapes``)."""
    parts = OmegaConf.load(run / "resolved_config.yaml").experiment.parts
    specs = {str(part.residual_novelty_shapes) for part in parts.values() if part.get("residual_novelty_shapes")}
    if len(specs) != 1:
        raise SystemExit(f"{run} names {len(specs)} sets of shapes for its hedges, not one")
    return training_shapes(specs.pop())


def signals(run: Path, pushes: int) -> None:
    models = _models(run)
    generator = torch.Generator().manual_seed(1)
    rows, groups = [], []
    for name, saved in models.items():
        plain = dataclasses.replace(saved, novelty_widening=0.0, defensive=(0.0, 0.0, 0.0), uncorrected=0.0,
                                    disagreement=0.0)
        for obj in [load_object(o) for o in models if o != name] + _hedge_shapes(run):
            records = load_records(_one(f"{run}/data/{obj.name}_*"))
            valid = records.take(records.valid)
            for k in torch.randperm(len(valid), generator=generator)[:pushes].tolist():
                push = valid.take(torch.tensor([k]))
                start, robot, truth = _poses(push)
                cloud = capture_partial_cloud(obj, start, voxel_size=saved.settings.voxel_size)
                try:
                    own = predict(saved.model, cloud, push.action[0].float(), torch.Generator().manual_seed(k),
                                  robot_start=robot)
                    corrected = predict_residual(plain, cloud, push.action[0].float(), k, condition=own.condition,
                                                 learned=(own.condition.object_pose, own.final_pose))
                except PushtorchError:
                    continue
                inside, _ = _scored_regions(_hedged(corrected, saved, "run", 0.0), corrected, obj, start, truth, k)
                rows.append([float(inside[1]), corrected.outcome_novelty] + _apart(own, corrected, obj, start, truth))
                groups.append(f"{name}'s model on {obj.name}")
    table = np.asarray(rows)
    inside, novel, apart = table[:, 0], table[:, 1], table[:, 2]
    for group in dict.fromkeys(groups):
        mine = np.asarray(groups) == group
        print(f"{group:36s} {int(mine.sum())} pushes: 90 % coverage {inside[mine].mean():.2f}, median novelty "
              f"{np.median(novel[mine]):.2f}, disagreement {np.median(apart[mine]):.3f}; H_acc corrected mode "
              f"{table[mine, 3].mean():.3f}, push model {table[mine, 4].mean():.3f}")
    for label, low in (("low", novel <= np.median(novel)), ("high", novel > np.median(novel))):
        near = apart[low] <= np.median(apart[low])
        print(f"novelty {label:4s} ({int(low.sum())} pushes): 90 % coverage {inside[low][near].mean():.2f} where the "
              f"two agree (disagreement <= {np.median(apart[low]):.3f}), {inside[low][~near].mean():.2f} where they "
              "disagree")


def disagreement(run: Path) -> None:
    models = _models(run)
    for obj_name, trained in TRAINING_OF.items():
        residual, obj = models[trained], load_object(obj_name)
        rows = []
        for i, cloud, action, robot, start, truth in _test_pushes(run, obj, residual.settings.voxel_size):
            own = predict(residual.model, cloud, action, torch.Generator().manual_seed(i), robot_start=robot)
            corrected = predict_residual(residual, cloud, action, i, condition=own.condition,
                                         learned=(own.condition.object_pose, own.final_pose))
            rows.append(_apart(own, corrected, obj, start, truth))
        table = np.asarray(rows)
        print(f"{obj_name:14s} ({trained}'s model, {len(rows)} pushes) disagreement median {np.median(table[:, 0]):.3f}"
              f" mean {table[:, 0].mean():.3f}; H_acc corrected mode {table[:, 1].mean():.3f}, push model "
              f"{table[:, 2].mean():.3f}", flush=True)


def _own_held_out(run: Path, name: str, saved, pushes: int, as_run: bool):
    """``pushes`` per action of the run's training pushes of ``name`` held out in turn of its models trained again
    from them (its push model with another seed than the run's, so that its kernels know their pushes), each
    predicted as a test push is: yields ``(object, prediction, start, truth, push)``. With ``as_run`` the residual
    kernels take the run's model's scaled stds and pairing width (its hedges are the caller's); without, they are
    as trained."""
    obj = load_object(name)
    records = load_records(_one(f"{run}/data/{name}_*"))
    model = train_push_model(obj, records, saved.model.settings, name=name, generator=torch.Generator().manual_seed(0))
    residual = dataclasses.replace(train_residual_model(model, obj, records, saved.sim, saved.ensemble),
                                   point="corrected")
    if as_run:
        residual = dataclasses.replace(residual, bandwidth=saved.bandwidth, outcome_width=saved.outcome_width)
    generator = torch.Generator().manual_seed(0)
    for p, held_out, (cloud, action, robot, start, truth) in own_held_out_pushes(residual, obj, records, pushes,
                                                                                  generator):
        if held_out is None:  # its push gave every kernel of its action
            continue
        try:
            prediction = _predicted(dataclasses.replace(held_out, disagreement=saved.disagreement), cloud, action,
                                    generator, robot, unhedged=True)
        except PushtorchError:  # it cannot be predicted from there
            continue
        yield obj, prediction, start, truth, p


def scale(run: Path, pushes: int) -> None:
    models = _models(run)
    grid = list(RESIDUAL_SCALES)
    for name, saved in models.items():
        rows = [[residual_nll_grid(disagreeing(prediction, xi), truth, start, obj, grid, [part], [rate]).numpy()
                 for part, rate, xi in (((0.0, 0.0, 0.0), 0.0, 0.0),
                                        (saved.defensive, saved.uncorrected, saved.disagreement))]
                for obj, prediction, start, truth, _ in _own_held_out(run, name, saved, pushes, False)]
        table = np.asarray(rows).mean(0)
        for label, nlls in zip(("without the hedges", "with the run's hedges"), table, strict=True):
            print(f"{name:9s} {len(rows)} held-out pushes, {label}: held-out nll by scale "
                  + ", ".join(f"{f:g}: {v:.2f}" for f, v in zip(grid, nlls, strict=True))
                  + f"; best {grid[int(nlls.argmin())]:g}", flush=True)
        print(f"{name:9s} the run's choice: scale {saved.meta['scale']['chosen']:g}, defensive part "
              f"{tuple(saved.defensive)}, uncorrected rate {saved.uncorrected:g}, disagreement weight "
              f"{saved.disagreement:g}")


def calibration(run: Path, pushes: int) -> None:
    models = _models(run)
    for name, saved in models.items():
        rows = []
        for obj, prediction, start, truth, p in _own_held_out(run, name, saved, pushes, True):
            rows.append([float(_scored_regions(density, prediction, obj, start, truth, p)[0][1])
                         for density in (_hedged(prediction, saved, "run", 0.0), prediction.density)]
                        + [prediction.outcome_novelty, _offset(prediction.condition.robot_start, start)])
        table = np.asarray(rows)
        print(f"{name:9s} {len(rows)} held-out training pushes: 90 % coverage {table[:, 0].mean():.2f} with the run's "
              f"hedges, {table[:, 1].mean():.2f} of the corrected kernels alone; median novelty "
              f"{np.median(table[:, 2]):.3f}", flush=True)
        truths = load_records(_one(f"{run}/truth/*_{name}_paper_default_paper_default*"))
        tests = np.asarray([_offset(robot, start) for start, robot, _ in (
            _poses(truths.take(torch.tensor([i]))) for i in torch.nonzero(truths.valid).reshape(-1).tolist())])
        near = table[:, 3] <= np.median(table[:, 3])
        print(f"{name:9s} the bumper's lateral offset from the object's centre: test pushes median "
              f"{100 * np.median(tests):.1f} cm (90 % under {100 * np.quantile(tests, 0.9):.1f}), held-out training "
              f"pushes median {100 * np.median(table[:, 3]):.1f} cm; 90 % coverage with the run's hedges "
              f"{table[near, 0].mean():.2f} of the {int(near.sum())} held-out pushes nearer the centre than that, "
              f"{table[~near, 0].mean():.2f} of the {int((~near).sum())} farther", flush=True)


def _offset(robot: se3.Pose, start: se3.Pose) -> float:
    """How far off centre the bumper meets the object: the object's start position across the robot's heading, in
    the robot's start frame (m, absolute)."""
    return abs(float(se3.relative(robot.to(torch.float64), start.to(torch.float64)).p[..., 1]))


def _model_of(models: dict, prediction):
    """The push model inside the residual model that made ``prediction``."""
    return next(m.model for m in models.values() if m.name == prediction.model_name)


def novelty(run: Path, pushes: int) -> None:
    models = _models(run)
    generator = torch.Generator().manual_seed(0)
    for name, other in (("cube", "cylinder"), ("cylinder", "cube"), ("cube", "cube"), ("cylinder", "cylinder")):
        rows, predictions = _scored(models[name], load_object(other), run, pushes, generator,
                                    lambda p: [novelty_factors(p, v) for v in NOVELTY_WIDENINGS])
        mean = rows.mean(0)
        print(f"{name}'s residuals on {len(rows)} {other} training pushes (own pushes in-sample): nll by nu "
              + ", ".join(f"{v:g}: {x:.2f}" for v, x in zip(NOVELTY_WIDENINGS, mean, strict=True))
              + f"; novelty median {np.median([p.outcome_novelty for p in predictions]):.2f}")
    _per_object(models, generator, "outcome d2", lambda p, a: p.outcome_novelty)


def weights(run: Path) -> None:
    residual = dataclasses.replace(load_residual_model(_one(f"{run}/models/shapes_*_residual_vs_*.npz")),
                                   point="corrected")
    if residual.shapes is None:
        raise SystemExit(f"{run}'s shapes residual model is not a pooled one")
    names = residual.shape_names
    for a, (kernels, of) in enumerate(zip(residual.residuals, residual.shapes, strict=True)):
        cells = []
        for s, name in enumerate(names):
            mine = of == s
            if bool(mine.any()):
                slide = float(kernels.p[mine][:, :2].norm(dim=-1).mean()) * 100
                turn = float(se3.yaw_of(kernels.q[mine]).abs().mean())
                cells.append(f"{name} {slide:.1f}/{turn:.2f}")
        print(f"action {a} mean correction (cm/rad): " + ", ".join(cells))
    for obj_name in ("prism_thin", "prism_long", "cylinder_wide", "hybrid"):
        obj = load_object(obj_name)
        for k, yaw in enumerate((-0.4, 0.0, 0.4)):
            cloud = capture_partial_cloud(obj, obj.resting_pose(yaw=yaw), voxel_size=residual.settings.voxel_size)
            for a in range(len(residual.actions)):
                prediction = predict_residual(residual, cloud, residual.actions[a], 3 * k + a)
                share = prediction.residual_weights.exp()
                by_shape = sorted(((float(share[residual.shapes[a] == s].sum()), n) for s, n in enumerate(names)),
                                  reverse=True)[:4]
                print(f"{obj_name:14s} yaw {yaw:+.1f} action {a}: d2 {prediction.contact_distance2:.2f}; "
                      + ", ".join(f"{n} {w:.2f}" for w, n in by_shape))


def target(run: Path) -> None:
    records = [r for r in json.loads((run / "results.json").read_text())["records"]
               if r.get("metric") == "displacement" and r.get("task") == "transfer"]
    samples: dict[tuple[str, str], list[np.ndarray]] = {}
    for e in read_figure_data(run / FIGURE_DATA)["hacc_samples"]:
        samples.setdefault((e["object"], e["method"]), []).append(np.asarray(e["hacc"], dtype=np.float64).reshape(-1))
    held, objects = 0, sorted({r["object"] for r in records if r["method"] == "pushtorch_residual"})
    for obj in objects:
        h = {m: np.concatenate(samples[(obj, m)]) for m in ("pushtorch_residual", "pushtorch_shapes",
                                                             "physics_from_cloud")}
        best = min(("pushtorch_shapes", "physics_from_cloud"), key=lambda m: h[m].mean())
        diff = h["pushtorch_residual"] - h[best]
        se = float(diff.std(ddof=1) / math.sqrt(len(diff)))
        ok = h["pushtorch_residual"].mean() <= h[best].mean() + 2 * se
        held += ok
        mine = [r for r in records if r["object"] == obj and r["method"] == "pushtorch_residual"]
        nll_mean = np.mean([r["nll_mean"] for r in mine])
        coverage = np.mean([r["coverage_90"] for r in mine])
        print(f"{obj:14s} residual {h['pushtorch_residual'].mean():.3f}  shapes {h['pushtorch_shapes'].mean():.3f}  "
              f"physics {h['physics_from_cloud'].mean():.3f}  paired SE vs {best} {se:.4f}  nll {nll_mean:.1f}  "
              f"cov90 {coverage:.2f}  n={len(diff)}  {'held' if ok else 'not held'}")
    print(f"objects={len(objects)} residual_le_best={held}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("distance", "novelty", "coverage", "hedges", "calibration", "disagreement",
                                         "signals", "scale", "weights", "target"))
    parser.add_argument("run", type=Path)
    parser.add_argument("--pushes", type=int, default=15)
    parser.add_argument("--draw", type=int, default=0,
                        help="coverage, hedges: which draw of the predictions (their seeds)")
    args = parser.parse_args()
    if args.what == "distance":
        distance(args.run, args.pushes)
    elif args.what in ("novelty", "scale", "calibration", "signals"):
        {"novelty": novelty, "scale": scale, "calibration": calibration, "signals": signals}[args.what](args.run,
                                                                                                       args.pushes)
    elif args.what in ("coverage", "hedges"):
        (coverage if args.what == "coverage" else hedges)(args.run, args.draw)
    elif args.what == "disagreement":
        disagreement(args.run)
    else:
        (weights if args.what == "weights" else target)(args.run)


if __name__ == "__main__":
    main()
