"""Shared test settings: deterministic hypothesis profile sized for a 2-core CI, and the small trained models
several test modules predict with."""

import os

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci", max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.register_profile("dev", max_examples=200, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def pytest_configure(config):
    """Under pytest-xdist, each test process's torch gets its share of the cores (one thread each with two
    workers on two cores): every worker running torch on every core oversubscribes them, and OpenMP threads that
    wait for a busy core cost far more than the parallelism gains. Processes a test starts choose their own."""
    workers = int(getattr(config, "workerinput", {}).get("workercount", 0))
    if workers > 1:
        import torch

        from pushtorch.parallel import available_cores

        torch.set_num_threads(max(1, available_cores() // workers))


@pytest.fixture(scope="session")
def small_model(tmp_path_factory):
    """``small_model(name)``: a model of a catalogue object trained on 8 real pybullet pushes per action at small
    prediction sizes (seconds per prediction), trained once per test process and object."""
    import torch

    from pushtorch.models.settings import ModelSettings
    from pushtorch.models.training import train_push_model
    from pushtorch.objects import load_object
    from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan

    settings = ModelSettings(query_kernels=400, anneal_candidates=60, anneal_steps=15, position_frames=800,
                             environment_kernels=300, manipulator_kernels=40)
    models = {}

    def make(name: str):
        if name not in models:
            obj = load_object(name)
            plan = plan_training_pushes(obj, make_actions(3), 8, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
            folder = tmp_path_factory.mktemp(f"{name}_pushes")
            run_plan(object_spec(obj), plan, folder, workers=2, progress=False)
            models[name] = train_push_model(obj, load_records(folder), settings,
                                            generator=torch.Generator().manual_seed(0))
        return models[name]

    return make


@pytest.fixture(scope="session")
def cube_pushes_of(tmp_path_factory):
    """``cube_pushes_of(per_action, seed)``: the cube and its real pybullet pushes (3 actions, mass N(0.5, 0.025),
    friction N(0.3, 0.05)), simulated once per test process and size."""
    from pushtorch.objects import load_object
    from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan

    runs = {}

    def make(per_action: int, seed: int):
        if (per_action, seed) not in runs:
            cube = load_object("cube")
            plan = plan_training_pushes(cube, make_actions(3), per_action, Normal(0.5, 0.025), Normal(0.3, 0.05),
                                        seed=seed)
            folder = tmp_path_factory.mktemp(f"cube_pushes_{per_action}_{seed}")
            run_plan(object_spec(cube), plan, folder, workers=1, progress=False)
            runs[(per_action, seed)] = (cube, load_records(folder))
        return runs[(per_action, seed)]

    return make


@pytest.fixture(scope="session")
def small_settings():
    """A small model's settings, for the tests of models trained on a few real pushes (the residual model's)."""
    from pushtorch.models.settings import ModelSettings

    return ModelSettings(query_kernels=400, anneal_candidates=60, anneal_steps=15, position_frames=800,
                         environment_kernels=300, manipulator_kernels=40)


@pytest.fixture(scope="session")
def small_cube_residual(cube_pushes_of, small_settings):
    """``(cube, records, model, residual)``: the cube's pybullet pushes (6 per action), a small model trained on
    them (``small_settings``) and its residual model against pybullet (4 rollouts), trained once per process."""
    import torch

    from pushtorch.models.residual import train_residual_model
    from pushtorch.models.training import train_push_model
    from pushtorch.sim.settings import SimSettings

    cube, records = cube_pushes_of(6, 1)
    model = train_push_model(cube, records, small_settings, generator=torch.Generator().manual_seed(0))
    return cube, records, model, train_residual_model(model, cube, records, SimSettings(), ensemble=4)


@pytest.fixture(scope="session")
def rotated_surface_gap():
    """``gap(mesh, q, n=1500)``: the largest distance (m) from ``n`` surface samples of ``mesh`` rotated by the wxyz
    quaternion ``q`` to the unrotated surface (open3d's exact point-to-triangle distance; sample seed 3, not the
    seed symmetry detection samples with). 0 when ``q`` is a symmetry of the mesh."""
    import numpy as np
    import open3d as o3d
    import torch
    import trimesh
    from pytorch_kinematics import transforms as pkt

    def gap(mesh, q, n: int = 1500) -> float:
        points, _ = trimesh.sample.sample_surface(mesh, n, seed=3)
        rotated = pkt.quaternion_apply(torch.as_tensor(q).double(), torch.as_tensor(points)).numpy()
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        return float(scene.compute_distance(o3d.core.Tensor(np.asarray(rotated, np.float32))).numpy().max())

    return gap
