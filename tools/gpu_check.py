"""A GPU check that travels light: prediction, batched prediction and conditioning on a CUDA device that has torch
but neither open3d nor pybullet (a lent accelerator takes 64 MiB of files; those two are 450 MB installed).

``prepare`` (here, with the full install) writes ``.devcheck/``: a paper-size model, the surface features of 24
test clouds of the cube and one of the thin prism, three observed pushes, the pure-Python dependencies and a
manifold3d wheel for Python 3.12. ``run`` (there, with ``PYTHONPATH=.``) unpacks them, replaces open3d's two
nearest-point queries (the pose verification's k-d tree and the bumper's closest points) by exact torch searches
with the same answers, and ends with ``cuda_test=<0|1> gpu_p50_s=… gpu_batched_s=… gpu_condition_3_s=…
cpu_p50_s=… …``: the library test's "a model on the GPU predicts there", the fast path's median latency from
surface features on the GPU and on that machine's CPU in the same run, the batched time per condition, and the
time to condition on three observed pushes (with the posterior's mean, which must agree), and a planner's
``predict_candidates`` on one cloud: 256 and 1,000 candidates on the GPU (256 on the CPU), in chunks of 64 and in
one chunk (``GPU_CHECK_PLAN=16,32`` for a short trial; ``GPU_CHECK_ONLY_PLAN=1``: that part alone, on the GPU
where there is one, then profiled).

    .venv/bin/python tools/gpu_check.py prepare runs/<run>/models/<a paper-size cube model>.npz
    # on the device, carrying .devcheck:  PYTHONPATH=. python3 tools/gpu_check.py run
"""

from __future__ import annotations

import math
import sys

FOLDER = ".devcheck"
PLAN_CANDIDATES = (256, 1000)  # the planner's candidate counts (issue targets: 0.5 s and 2 s on a GPU)
PURE_PYTHON = ("trimesh", "pytorch_kinematics", "arm_pytorch_utilities", "pytorch_seed")


def prepare(model_path: str) -> None:
    """Write ``.devcheck/``: the model, the test clouds' features, observed pushes and the dependencies."""
    import importlib
    import shutil
    import subprocess
    from pathlib import Path

    import torch

    from pushtorch import se3
    from pushtorch.features import compute_surface_features
    from pushtorch.models.model import load_model
    from pushtorch.objects import load_object
    from pushtorch.perception import capture_partial_cloud
    from pushtorch.sim.push import place_robot_against
    from pushtorch.sim.runner import simulate_pushes

    folder = Path(FOLDER)
    for name in PURE_PYTHON:
        source = Path(importlib.import_module(name).__file__).parent
        shutil.copytree(source, folder / "site" / name, dirs_exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
                    "--python-version", "3.12", "--platform", "manylinux_2_28_x86_64", "-d",
                    str(folder / "wheels"), "manifold3d"], check=True)
    model = load_model(model_path)
    shutil.copy(model_path, folder / "model.npz")

    def features(obj, pose) -> dict:
        cloud = capture_partial_cloud(obj, pose, voxel_size=model.settings.voxel_size)
        f = compute_surface_features(cloud, radius=model.settings.feature_radius)
        return {k: getattr(f, k) for k in ("p", "q", "r", "normal", "k1", "k2", "index")}

    cube, prism = load_object("cube"), load_object("prism_thin")
    g = torch.Generator().manual_seed(0)
    conditions = [features(cube, cube.resting_pose(yaw=(float(torch.rand(1, generator=g)) - 0.5) * math.pi / 2))
                  for _ in range(24)]
    observations = []
    for i in range(3):
        pose = cube.resting_pose(yaw=0.2 * i - 0.2)
        start = place_robot_against(cube.mesh, pose, float(se3.yaw_of(pose.q)), 0.0, 0.002)
        pushed = simulate_pushes(cube, start, pose, model.actions[i % 3], 0.5, 0.1)
        robot = pushed.robot_trajectory
        observations.append({"features": features(cube, pose), "action": model.actions[i % 3],
                             "initial": (pose.p, pose.q), "start": (start.p, start.q),
                             "final": (pushed.object_final.p[0], pushed.object_final.q[0]),
                             "robot_final": (robot.p[0, -1], robot.q[0, -1])})
    from bench_plan import candidates  # tools/ is on sys.path when a tool runs as a script

    cloud, starts, action_rows = candidates(PLAN_CANDIDATES[-1], "cpu")
    f = compute_surface_features(cloud, radius=model.settings.feature_radius)
    plan = {"features": {k: getattr(f, k) for k in ("p", "q", "r", "normal", "k1", "k2", "index")},
            "start_p": torch.stack([s.p for s in starts]), "start_q": torch.stack([s.q for s in starts]),
            "actions": torch.tensor(action_rows)}
    torch.save({"conditions": conditions, "prism": features(prism, prism.resting_pose(yaw=0.3)),
                "observations": observations, "plan": plan}, folder / "data.pt")
    print(f"wrote {folder}/: {len(conditions)} conditions, {len(observations)} observed pushes")


def _without_open3d() -> None:
    """Exact torch stand-ins for open3d's nearest-point queries (same answers, no k-d tree or BVH)."""
    import numpy as np
    import torch

    import pushtorch.models.contact as contact
    import pushtorch.models.position as position

    def nearest(search, points):
        flat = points.reshape(-1, 3).to(search)
        best = torch.cat([torch.cdist(chunk, search).amin(-1) for chunk in flat.split(4096)])
        return best.to(points).reshape(points.shape[:-1])

    def closest_on_triangles(mesh, points):
        """Ericson's closest point on a triangle, every point against every triangle (the bumper: 12)."""
        tri = torch.as_tensor(np.asarray(mesh.vertices)[np.asarray(mesh.faces)], dtype=torch.float64)
        p = points.detach().double().cpu().unsqueeze(1)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        ab, ac = b - a, c - a
        d1, d2 = (ab * (p - a)).sum(-1), (ac * (p - a)).sum(-1)
        d3, d4 = (ab * (p - b)).sum(-1), (ac * (p - b)).sum(-1)
        d5, d6 = (ab * (p - c)).sum(-1), (ac * (p - c)).sum(-1)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

        def safe(x):
            return x.where(x.abs() > 1e-300, torch.ones_like(x))

        total = safe(va + vb + vc)
        out = a + ab * (vb / total).unsqueeze(-1) + ac * (vc / total).unsqueeze(-1)  # inside the face
        regions = [  # later regions win, as the early returns of the scalar algorithm
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             b + (c - b) * ((d4 - d3) / safe(d4 - d3 + d5 - d6))[..., None]),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / safe(d2 - d6))[..., None]),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / safe(d1 - d3))[..., None]),
            ((d6 >= 0) & (d5 <= d6), c.expand_as(out)),
            ((d3 >= 0) & (d4 <= d3), b.expand_as(out)),
            ((d1 <= 0) & (d2 <= 0), a.expand_as(out)),
        ]
        for mask, value in regions:
            out = torch.where(mask[..., None], value, out)
        best = (out - p).norm(dim=-1).argmin(-1)
        closest = out[torch.arange(len(best)), best].to(points)
        return closest, (closest - points).norm(dim=-1)

    position._nearest_model_search = lambda points: points.detach()
    position._nearest_distances = nearest
    contact.closest_points_on_mesh = closest_on_triangles


def _plan(out: dict, name: str, model, plan: dict, device: str, features, synchronise, profile: bool = False
          ) -> None:
    """``predict_candidates`` on one cloud's features: 256 and 1,000 candidates, in chunks of 64 and in one chunk;
    ``profile``: the first count once more under cProfile (its 40 largest cumulative times printed)."""
    import cProfile
    import pstats
    import time

    from pushtorch import se3
    from pushtorch.prediction import predict_candidates

    f = features(plan["features"], device)
    starts = se3.Pose(plan["start_p"].to(device), plan["start_q"].to(device))
    actions = model.actions[plan["actions"].to(model.actions.device)]
    predict_candidates(model, f, starts.take(slice(0, 8)), actions[:8], chunk_size=8)  # warm-up
    import os

    counts = tuple(int(c) for c in os.environ.get("GPU_CHECK_PLAN", ",".join(map(str, PLAN_CANDIDATES))).split(","))
    counts = counts if name == "gpu" else counts[:1]
    for count in counts:
        for chunk in (64, count):
            synchronise(device)
            started = time.perf_counter()
            result = predict_candidates(model, f, starts.take(slice(0, count)), actions[:count], chunk_size=chunk)
            synchronise(device)
            out[f"{name}_plan_{count}_chunk_{chunk}_s"] = round(time.perf_counter() - started, 3)
        out[f"{name}_plan_{count}_valid"] = int(result.valid.sum())
    if profile:
        profiler = cProfile.Profile()
        profiler.enable()
        predict_candidates(model, f, starts.take(slice(0, counts[0])), actions[:counts[0]], chunk_size=counts[0])
        synchronise(device)
        profiler.disable()
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(40)
        pstats.Stats(profiler).sort_stats("tottime").print_stats(25)


def run() -> None:
    """The check (on the device); prints the summary line."""
    import glob
    import json
    import os
    import platform
    import statistics
    import time
    import zipfile

    sys.path.insert(0, f"{FOLDER}/site")
    for wheel in glob.glob(f"{FOLDER}/wheels/*.whl"):
        zipfile.ZipFile(wheel).extractall(f"{FOLDER}/site")
    import torch

    _without_open3d()
    from pushtorch import se3
    from pushtorch.features import SurfaceFeatures
    from pushtorch.models.conditioning import Observation
    from pushtorch.models.model import load_model
    from pushtorch.prediction import predict, predict_many

    cuda = torch.cuda.is_available()
    print("torch", torch.__version__, torch.cuda.get_device_name(0) if cuda else "no cuda", platform.processor(),
          os.cpu_count(), flush=True)
    count = int(os.environ.get("GPU_CHECK_CONDITIONS", "24"))
    data = torch.load(f"{FOLDER}/data.pt")
    base = load_model(f"{FOLDER}/model.npz")

    def features(d, device):
        return SurfaceFeatures(**{k: v.to(device) for k, v in d.items()})

    def synchronise(device):
        if device == "cuda":
            torch.cuda.synchronize()

    out: dict[str, float] = {}
    runs = [("cpu", base, "cpu")]
    if cuda:  # the library test: a model moved to the GPU predicts there
        gpu = base.to(device="cuda")
        p = predict(gpu, features(data["prism"], "cuda"), base.actions[1], generator=0)
        ok = p.final_pose.p.device.type == "cuda" and bool(torch.isfinite(p.final_pose.p).all())
        out["cuda_test"] = int(ok and bool(torch.isfinite(p.density.log_prob(p.density.mode)).all()))
        runs.insert(0, ("gpu", gpu, "cuda"))
    if os.environ.get("GPU_CHECK_ONLY_PLAN"):  # the planner's part alone, on the first device (profiled)
        name, model, device = runs[0]
        _plan(out, name, model, data["plan"], device, features, synchronise, profile=True)
        print(" ".join(f"{k}={v}" for k, v in out.items()))
        return
    for name, model, device in runs:
        conditions = [features(c, device) for c in data["conditions"][:count]]
        predict(model, conditions[0], base.actions[0], generator=0)  # warm-up (compilation)
        times = []
        for i, c in enumerate(conditions):
            synchronise(device)
            start = time.perf_counter()
            predict(model, c, base.actions[i % 3], generator=i)
            synchronise(device)
            times.append(time.perf_counter() - start)
        out[f"{name}_p50_s"] = round(statistics.median(times), 4)
        start = time.perf_counter()
        predict_many(model, conditions, base.actions[0], batch_size=len(conditions))
        synchronise(device)
        out[f"{name}_batched_s"] = round((time.perf_counter() - start) / len(conditions), 4)
        observed = [Observation(features(o["features"], device), o["action"], se3.Pose(*o["initial"]),
                                se3.Pose(*o["final"]), se3.Pose(*o["start"]), se3.Pose(*o["robot_final"]))
                    for o in data["observations"]]
        start = time.perf_counter()
        adapted = model.condition_on(observed)
        out[f"{name}_condition_3_s"] = round(time.perf_counter() - start, 3)
        out[f"{name}_mu_mean"] = round(adapted.posterior().mu_mean, 4)
        r = predict(adapted, conditions[0], base.actions[0], generator=0)
        out[f"{name}_conditioned_finite"] = int(bool(torch.isfinite(r.final_pose.p).all()))
        _plan(out, name, model, data["plan"], device, features, synchronise)
    print(json.dumps(out))
    print(" ".join(f"{k}={v}" for k, v in out.items()))


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in ("prepare", "run") or (sys.argv[1] == "prepare" and len(sys.argv) < 3):
        raise SystemExit("usage: gpu_check.py prepare <model.npz> | gpu_check.py run")
    if sys.argv[1] == "prepare":
        prepare(sys.argv[2])
    else:
        run()
