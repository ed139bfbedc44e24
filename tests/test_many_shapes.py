"""One model from many shapes: training entries that never reach the held-out seeds, the pooled model's kernels
and file, the kernel budget, the widening, the physics ensemble, and coverage on densities whose regions are
known."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pytorch_kinematics import transforms as pkt

from pushtorch import se3
from pushtorch.errors import InvalidParameterError
from pushtorch.evaluation.baselines import physics_ensemble_prediction
from pushtorch.evaluation.likelihood import covered, ensemble_density, hdr_thresholds, nll, point_density
from pushtorch.evaluation.transfer import choose_widening
from pushtorch.experiments.prediction_sets import observe
from pushtorch.models.model import load_model
from pushtorch.models.motion import contact_distances, nearest_in_contact
from pushtorch.models.pooled import fit_shape_parts, train_pooled_model
from pushtorch.models.settings import ModelSettings
from pushtorch.objects import Symmetry, load_object
from pushtorch.objects.shapes import (
    HELD_OUT_FIRST_SEED,
    SHAPE_KINDS,
    held_out_shapes,
    random_shape,
    resolve_training_objects,
    training_shape_seeds,
)
from pushtorch.prediction import predict, transfer_bandwidth
from pushtorch.sim import Fixed, Uniform, make_actions, plan_training_pushes
from pushtorch.sim.runner import simulate_pushes

SMALL = ModelSettings(query_kernels=300, anneal_candidates=60, anneal_steps=12, environment_samples=20,
                      environment_kernels=200, manipulator_kernels=10, voxel_size=0.008, feature_radius=0.02,
                      bandwidth_folds=0)


@given(kind=st.sampled_from(("mixed", *SHAPE_KINDS)), count=st.integers(1, 1200), first=st.integers(0, 1200))
def test_training_entries_never_reach_a_held_out_seed(kind, count, first):
    spec = f"shapes:{kind}:{count}:{first}"
    if first + count > HELD_OUT_FIRST_SEED:
        with pytest.raises(InvalidParameterError, match="held-out"):
            training_shape_seeds(spec)
        return
    seeds = training_shape_seeds(spec)
    assert len(seeds) == count and max(s for s, _ in seeds) < HELD_OUT_FIRST_SEED
    assert all(k in SHAPE_KINDS for _, k in seeds)
    assert {k for _, k in seeds} <= ({kind} if kind != "mixed" else set(SHAPE_KINDS))


@pytest.mark.parametrize("spec", ["shapes:torus:3", "shapes:box", "shapes:box:0", "shapes:box:x", "shape:box:3",
                                  "shapes:box:3:-1", "shapes:mixed:2:999"])
def test_malformed_training_entries_are_refused_by_name(spec):
    with pytest.raises(InvalidParameterError, match=spec.split(":")[0] if spec != "shapes:torus:3" else "torus"):
        resolve_training_objects([spec])


def test_training_objects_mix_catalogue_and_generated_and_refuse_a_repeat():
    objects = resolve_training_objects(["cube", "shapes:box:2:7"])
    assert [o.name for o in objects] == ["cube", "box_7", "box_8"]
    held_out = {s.name for s in held_out_shapes(9)}
    assert not held_out & {o.name for o in objects}
    with pytest.raises(InvalidParameterError, match="more than once"):
        resolve_training_objects(["shapes:box:1:7", "shapes:box:1:7"])


@pytest.fixture(scope="module")
def shapes_and_records(tmp_path_factory):
    """Three generated training shapes and a few real pybullet pushes of each (every action)."""
    from pushtorch.sim import object_spec
    from pushtorch.sim.records import load_records
    from pushtorch.sim.runner import run_plan
    from pushtorch.sim.settings import SimSettings

    shapes = [random_shape(1, "polygon"), random_shape(2, "superellipse"), random_shape(3, "box")]
    records = []
    for shape in shapes:
        plan = plan_training_pushes(shape, make_actions(3), 6, Fixed(0.5), Uniform(0.2, 0.6), seed=3)
        folder = tmp_path_factory.mktemp(shape.name)
        run_plan(object_spec(shape), plan, folder, SimSettings(), workers=1, progress=False)
        records.append(load_records(folder, trajectories=False))
    return shapes, records


@pytest.mark.slow  # 15-17 s; the tiny quickstart's shape-transfer part trains, saves and reads a pooled model
def test_a_pooled_model_holds_every_shapes_kernels_and_round_trips(shapes_and_records, tmp_path):
    shapes, records = shapes_and_records
    parts = fit_shape_parts(shapes, records, SMALL, 0)
    model = train_pooled_model(shapes, records, SMALL, name="pool", generator=0, parts=parts)
    for a, motion in enumerate(model.motions):
        assert len(motion.manipulator) == sum(len(p[3][a].manipulator) for p in parts)
        assert len(motion.environment) == sum(len(p[3][a].environment) for p in parts)
        # pushes renumbered: no two shapes' pushes share an index
        pushes = [torch.unique(p[3][a].manipulator.push).numel() for p in parts]
        assert torch.unique(motion.manipulator.push).numel() == sum(pushes)
    assert model.meta["pooled"] == [s.name for s in shapes]
    widened = choose_widening(model, shapes, records, parts, pushes_per_shape=2,
                              generator=torch.Generator().manual_seed(0), scales=(1.0, 3.0), widenings=(0.0, 0.1))
    chosen = widened.meta["widening"]
    assert chosen["pushes"] > 0 and len(chosen["nll"]) == 4 and all(math.isfinite(v) for v in chosen["nll"])
    assert (widened.settings.transfer_scale, widened.settings.transfer_widening) == tuple(
        chosen["chosen"].values())
    assert widened.configured_settings == SMALL
    path = widened.save(tmp_path / "pool.npz")
    loaded = load_model(path)
    assert loaded.settings == widened.settings and loaded.meta == widened.meta
    for a, b in zip(widened.motions, loaded.motions, strict=True):
        assert torch.equal(a.manipulator.m.p, b.manipulator.m.p) and torch.equal(a.environment.g, b.environment.g)
    cloud, _ = observe(load_object("hybrid"), load_object("hybrid").resting_pose(), SMALL)
    before = predict(widened, cloud, make_actions(3)[0], torch.Generator().manual_seed(5))
    after = predict(loaded, cloud, make_actions(3)[0], torch.Generator().manual_seed(5))
    assert torch.equal(before.final_pose.p, after.final_pose.p)


def test_the_kernel_budget_keeps_the_kernels_nearest_in_contact(shapes_and_records):
    shapes, records = shapes_and_records
    model = train_pooled_model(shapes, records, SMALL, generator=0)
    cloud, _ = observe(load_object("prism_long"), load_object("prism_long").resting_pose(), SMALL)
    condition = predict(model, cloud, make_actions(3)[1], torch.Generator().manual_seed(2)).condition
    kernels, args = model.motions[1].manipulator, (condition.robot_start, model.settings.contact_bandwidth,
                                                   condition.contact_patch)
    d2 = contact_distances(condition.manipulator_frame, kernels, *args).amin(0)
    kept = nearest_in_contact(condition.manipulator_frame, kernels, *args, count=5)
    kept_d2 = contact_distances(condition.manipulator_frame, kept, *args).amin(0)
    assert len(kept) == 5 and kept_d2.max() <= d2.sort().values[5] + 1e-5
    assert nearest_in_contact(condition.manipulator_frame, kernels, *args, count=len(kernels)) is kernels
    # a model that widens: its motion kernels grow with the contact's distance, never shrink
    base = transfer_bandwidth(model, condition, 1)
    from dataclasses import replace

    wide = replace(model, settings=replace(model.settings, transfer_scale=1.5, transfer_widening=0.2))
    scale = transfer_bandwidth(wide, condition, 1).p_std / base.p_std
    nearest = float(d2.min())
    assert scale == pytest.approx(math.sqrt(1.5**2 + 0.2 * nearest), rel=1e-4)


def test_the_physics_ensemble_rolls_the_prior_out_on_the_clouds_body():
    prism = load_object("prism_thin")
    pose = prism.resting_pose(yaw=0.2)
    cloud, features = observe(prism, pose, SMALL)
    from pushtorch.sim import place_robot_against

    start = place_robot_against(prism.mesh, pose, gap=0.002)
    action = make_actions(3)[2]
    generator = torch.Generator().manual_seed(0)
    body_start, fixed = physics_ensemble_prediction(features.p, pose, start, action, Fixed(0.3), Fixed(0.5), 3,
                                                    generator)
    assert fixed.batch_shape == (3,) and torch.allclose(fixed.p, fixed.p[:1].expand(3, 3), atol=1e-4)
    _, spread = physics_ensemble_prediction(features.p, pose, start, action, Uniform(0.05, 0.95),
                                            Uniform(0.1, 5.0), 6, generator)
    assert float(spread.p[:, :2].std(0).norm()) > 1e-3  # the prior's friction and mass move the outcome
    truth = simulate_pushes(prism, start.to(torch.float64), pose.to(torch.float64), action.double(), 0.5, 0.3)
    moved = float((truth.object_final.p[0, :2] - pose.p[:2].double()).norm())
    assert moved > 0.1 and float((body_start.p[:2] - pose.p[:2]).norm()) < 0.05
    density = ensemble_density(spread, 0.01, 0.05)
    assert torch.isfinite(density.log_prob(spread.vector())).all()
    with pytest.raises(InvalidParameterError, match="at least one rollout"):
        physics_ensemble_prediction(features.p, pose, start, action, Fixed(0.3), Fixed(0.5), 0, generator)


@settings(max_examples=6, deadline=None)
@given(p_std=st.floats(0.005, 0.05), rot_std=st.floats(0.02, 0.3), seed=st.integers(0, 2**16))
def test_coverage_of_a_density_is_its_own_level_on_its_own_draws(p_std, rot_std, seed):
    """Truths drawn from the density itself fall inside its α region a share α of the time (within 4 binomial
    standard errors plus the threshold's own sampling error), and a truth at the centre is inside every region,
    one far away inside none."""
    generator = torch.Generator().manual_seed(seed)
    centres = se3.Pose.unchecked(torch.randn(3, 3, generator=generator) * 0.05,
                                 torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(3, 4))
    density = ensemble_density(centres, p_std, rot_std)
    thresholds = hdr_thresholds(density, (0.5, 0.9), samples=2000, generator=generator)
    assert thresholds[0] > thresholds[1]
    truths = density.sample((2000,), torch.Generator().manual_seed(seed + 1))
    inside = covered(-density.log_prob(truths), thresholds).double().mean(0)
    for level, share in zip((0.5, 0.9), inside.tolist(), strict=True):
        se = math.sqrt(level * (1 - level) / 2000)
        assert abs(share - level) < 4 * se + 0.02, (level, share)
    one = point_density(centres.take(0), p_std, rot_std)
    t = hdr_thresholds(one, (0.5, 0.9), samples=500, generator=generator)
    at_centre = -one.log_prob(centres.take(0).vector().reshape(1, 7))
    far = -one.log_prob((centres.take(0).vector() + torch.tensor([1.0, 0, 0, 0, 0, 0, 0])).reshape(1, 7))
    assert covered(at_centre, t).all() and not covered(far, t).any()


@settings(max_examples=4, deadline=None)
@given(p_std=st.floats(0.005, 0.05), rot_std=st.floats(0.1, 0.4), seed=st.integers(0, 2**16),
       continuous=st.booleans())
def test_coverage_of_a_symmetric_object_is_its_own_level_when_draws_are_scored_as_truths(p_std, rot_std, seed,
                                                                                         continuous):
    """A symmetric object's truths are scored by their nearest symmetric copy; its regions' draws scored the same
    way keep the coverage of truths drawn from the density at its level, where draws scored as they are would
    put nearly every truth inside the 90 % region (a surface of revolution's turn never counting against it)."""
    generator = torch.Generator().manual_seed(seed)
    centres = se3.Pose.unchecked(torch.randn(2, 3, generator=generator) * 0.05,
                                 torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(2, 4))
    density = ensemble_density(centres, p_std, rot_std)
    half_turn = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    symmetry = Symmetry(half_turn[:1], continuous_z=True) if continuous else Symmetry(half_turn)
    same = se3.identity(dtype=torch.float64)
    truths = se3.Pose.from_vector(density.sample((1000,), torch.Generator().manual_seed(seed + 1)).double())
    scores = nll(density, truths, same, same, symmetry)
    fair = hdr_thresholds(density, (0.5, 0.9), samples=1000, generator=torch.Generator().manual_seed(seed + 2),
                          symmetry=symmetry)
    # the draws' nearest copies are those nll's full scan finds (the same draws, scored by it)
    draws = se3.Pose.from_vector(density.sample((1000,), torch.Generator().manual_seed(seed + 2)).double())
    scanned = torch.quantile(-nll(density, draws, same, same, symmetry), torch.tensor([0.5, 0.1], dtype=torch.float64))
    torch.testing.assert_close(fair, scanned, rtol=0, atol=0.05)
    inside = covered(scores, fair).double().mean(0)
    for level, share in zip((0.5, 0.9), inside.tolist(), strict=True):
        se = math.sqrt(level * (1 - level) / 1000)
        assert abs(share - level) < 4 * se + 0.03, (level, share)
    if continuous:  # the same draws scored as they are: lower thresholds, more truths inside than the level
        generous = hdr_thresholds(density, (0.5, 0.9), samples=1000, generator=torch.Generator().manual_seed(seed + 2))
        assert bool((generous < fair - 0.1).all())
        assert bool((covered(scores, generous).double().mean(0) > inside).all())


@settings(max_examples=5, deadline=None)
@given(p_std=st.floats(0.005, 0.05), rot_std=st.floats(0.02, 0.3), height=st.floats(0.0, 0.2),
       tilt=st.floats(0.0, 0.3), seed=st.integers(0, 2**16))
def test_coverage_of_planar_truths_is_their_level_when_draws_are_moved_onto_the_starts_plane(p_std, rot_std, height,
                                                                                            tilt, seed):
    """Pushed objects end on the table: truths drawn from the density and moved onto the estimated start's plane
    (its height and tilt) fall inside its α region a share α of the time when the region's draws are moved there
    too; scored in all seven dimensions, the draws' spread in height, roll and pitch puts far more of them
    inside."""
    generator = torch.Generator().manual_seed(seed)
    start = se3.Pose.unchecked(torch.tensor([0.0, 0.0, height]),
                               pkt.axis_angle_to_quaternion(torch.tensor([tilt, 0.0, 0.0])))
    turns = se3.Pose.unchecked(torch.cat([torch.randn(3, 2, generator=generator) * 0.05, torch.zeros(3, 1)], -1),
                               se3.yaw_quaternion(torch.randn(3, generator=generator)))
    density = ensemble_density(se3.compose(turns, start), p_std, rot_std)  # kernels on the start's plane
    drawn = density.sample((1000,), torch.Generator().manual_seed(seed + 1))
    truths = se3.onto_plane_of(se3.Pose.unchecked(drawn[:, :3], drawn[:, 3:]), start)
    same = se3.identity(dtype=torch.float64)
    scores = nll(density, se3.Pose.unchecked(truths.p.double(), truths.q.double()), same, same,
                 Symmetry(torch.tensor([[1.0, 0.0, 0.0, 0.0]])))
    assert torch.allclose(truths.p[:, 2], torch.full((1000,), height))
    fair = hdr_thresholds(density, (0.5, 0.9), samples=1000, generator=torch.Generator().manual_seed(seed + 2),
                          plane=start)
    inside = covered(scores, fair).double().mean(0)
    for level, share in zip((0.5, 0.9), inside.tolist(), strict=True):
        se = math.sqrt(level * (1 - level) / 1000)
        assert abs(share - level) < 4 * se + 0.03, (level, share)
    seven = hdr_thresholds(density, (0.5, 0.9), samples=1000, generator=torch.Generator().manual_seed(seed + 2))
    assert bool((covered(scores, seven).double().mean(0) > inside + 0.05).all())


def test_coverage_refuses_levels_outside_zero_one():
    density = point_density(se3.identity(), 0.01, 0.05)
    with pytest.raises(InvalidParameterError, match="levels"):
        hdr_thresholds(density, (0.5, 1.0))


def test_a_shape_without_one_actions_pushes_pools_with_the_rest(shapes_and_records):
    """A shape whose every push of an action was invalid adds nothing to that action, and the pool keeps it."""
    from pushtorch.models.pooled import pool_parts

    shapes, records = shapes_and_records
    parts = fit_shape_parts(shapes, records, SMALL, 0)
    name, contact, position, motions = parts[0]
    short = [(name, contact, position, motions[:2])] + parts[1:]
    _, _, pooled = pool_parts(short, SMALL, 0)
    assert len(pooled) == 3
    assert len(pooled[2].manipulator) == sum(len(p[3][2].manipulator) for p in parts[1:])
    assert len(pooled[0].manipulator) == sum(len(p[3][0].manipulator) for p in parts)
