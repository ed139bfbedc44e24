"""A planner's throughput: one cloud × many candidate pushes, batched (``predict_candidates``) against one by one.

Paper, Motion Model (the product of experts each candidate push anneals) and §Conclusions (a model is there to
choose a push). A cube model at the paper's prediction sizes, trained on ``--pushes`` simulated pushes per action
(cached in ``runs/bench_plan/``), predicts ``--candidates`` candidates of one single-shot cloud of the cube at a
20° yaw: robot starts against its visible face, shifted laterally across it, the three actions in turn. The one
by one baseline is ``predict`` per candidate from the cloud's precomputed ``SurfaceFeatures`` and the same given
start (features do not count as a gain); the batched call is ``predict_candidates`` (the pose estimate and the
environment contacts once; products of experts annealed in chunks of ``--chunk``). Each runs in a fresh process
that reports its peak memory over its memory before the call. Then ``--observations`` observed pushes (pybullet
pushes of the cube at random yaws, each with its cloud) condition the model at once, and a warm ``predict`` is
timed (median of 10).

``predict_candidates`` draws each candidate's numbers from a counter-based stream keyed by the candidate itself, so
its result does not depend on the chunking: the first ``--contract`` candidates are predicted again in chunks of
one and the largest difference is printed against the contract (1e-4 m and 1e-4 rad), and a goal is scored under
their densities (the first ``log_prob``, which makes each density's importance-sampled normaliser). ``predict`` per
candidate draws from a ``torch.Generator``, another stream: the distance between the two is printed too.

    .venv/bin/python tools/bench_plan.py [--candidates 256] [--chunk 64] [--pushes 100] [--observations 100]

The last line is ``one_by_one_s=<..> batched_s=<..> speedup=<..> peak_mb_over_base=<..> condition_per_obs_s=<..>
predict_p50_s=<..> device=<cpu|cuda>``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from bench_predict import cpu_name, paper_size_model  # tools/ is on sys.path when a tool runs as a script

from pushtorch import se3
from pushtorch.models.conditioning import Observation
from pushtorch.models.model import load_model
from pushtorch.models.push_condition import features_for
from pushtorch.objects import load_object
from pushtorch.perception import capture_partial_cloud
from pushtorch.prediction import predict
from pushtorch.sim.push import place_robot_against
from pushtorch.sim.runner import simulate_pushes

FOLDER = Path("runs/bench_plan")


def candidates(count: int, device: str):
    """The cube's cloud at a 20° yaw and ``count`` (start, action) candidates against its visible face."""
    cube = load_object("cube")
    pose = cube.resting_pose(yaw=math.radians(20.0))
    base = place_robot_against(cube.mesh, pose)
    shifts = torch.linspace(-0.06, 0.06, count)
    starts = [se3.compose(base, se3.from_xy_yaw(0.0, float(s), 0.0)) for s in shifts]
    return capture_partial_cloud(cube, pose), starts, [k % 3 for k in range(count)]


_CHILD = """
import json, resource, sys, time, torch
sys.path.insert(0, {tools!r})
from bench_plan import candidates
from pushtorch.models.model import load_model
from pushtorch.models.push_condition import features_for
from pushtorch.prediction import predict, predict_candidates
model = load_model({model!r}, map_location={device!r})
cloud, starts, actions = candidates({count}, {device!r})
features = features_for(cloud, model.settings, model.position)
peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
def now():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
predict(model, features, model.actions[0], torch.Generator().manual_seed(0), robot_start=starts[0])  # warm
base = now()
started = time.perf_counter()
if {batched}:
    result = predict_candidates(model, features, starts, model.actions[torch.tensor(actions)], seed=0,
                                chunk_size={chunk})
    finals = [p.final_pose.p.tolist() if p is not None else None for p in result.predictions]
else:
    finals = [predict(model, features, model.actions[a], torch.Generator().manual_seed(i), robot_start=s
                      ).final_pose.p.tolist() for i, (s, a) in enumerate(zip(starts, actions))]
seconds = time.perf_counter() - started
out = {{"seconds": seconds, "peak_over_base": peak() - base, "finals": finals}}
if {batched}:  # the contract: the first candidates again, one by one (chunks of 1), after the measurement
    k = min({contract}, len(starts))
    alone = predict_candidates(model, features, starts[:k], model.actions[torch.tensor(actions[:k])], seed=0,
                               chunk_size=1)
    pairs = [(a, b) for a, b in zip(result.predictions[:k], alone.predictions) if a is not None and b is not None]
    out["contract_m"] = max(float((a.final_pose.p - b.final_pose.p).norm()) for a, b in pairs)
    out["contract_rad"] = max(2 * float(torch.acos((a.final_pose.q * b.final_pose.q).sum().abs().clamp(max=1.0)))
                              for a, b in pairs)
    out["contract_count"] = len(pairs)
    goal = alone.density.mode[0]  # scoring a goal: the first log_prob computes every density's normaliser
    started = time.perf_counter()
    alone.log_prob(goal)
    out["score_s"] = time.perf_counter() - started
print(json.dumps(out))
"""


def _child(model_path: Path, count: int, batched: bool, chunk: int, device: str, contract: int = 0) -> dict:
    script = _CHILD.format(tools=str(Path(__file__).parent), model=str(model_path), device=device, count=count,
                           batched=batched, chunk=chunk, contract=contract)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=3 * 3600)
    if result.returncode != 0:
        raise SystemExit(f"the {'batched' if batched else 'one-by-one'} run failed: {result.stderr[-2000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def observations(count: int, model) -> list[Observation]:
    """``count`` observed pybullet pushes of the cube (yaw uniform in ±0.2 rad, friction 0.3, mass 0.5), each with its
    cloud, robot start and the robot's final pose."""
    cube = load_object("cube")
    generator = torch.Generator().manual_seed(1)
    out = []
    for k in range(count):
        yaw = float(torch.empty(()).uniform_(-0.2, 0.2, generator=generator))
        pose = cube.resting_pose(yaw=yaw)
        start = place_robot_against(cube.mesh, pose)
        action = model.actions[k % 3]
        records = simulate_pushes(cube, start, pose, action, 0.5, 0.3)
        final = se3.Pose(records.object_final.p[0], records.object_final.q[0])
        robot_final = se3.Pose(records.robot_trajectory.p[0, -1], records.robot_trajectory.q[0, -1])
        out.append(Observation(capture_partial_cloud(cube, pose), action, pose, final, start, robot_final))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidates", type=int, default=256)
    parser.add_argument("--chunk", type=int, default=64, help="candidates annealed together (default 64)")
    parser.add_argument("--pushes", type=int, default=100, help="training pushes per action (default 100)")
    parser.add_argument("--observations", type=int, default=100)
    parser.add_argument("--contract", type=int, default=32,
                        help="candidates whose batched prediction is checked against chunks of 1 (default 32)")
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); device {device}; {args.candidates} candidates")
    FOLDER.mkdir(parents=True, exist_ok=True)
    paper_size_model("cube", args.pushes, FOLDER)
    model_path = FOLDER / f"cube_{args.pushes}.npz"
    one = _child(model_path, args.candidates, False, args.chunk, device)
    print(f"one by one: {one['seconds']:.1f} s", flush=True)
    batched = _child(model_path, args.candidates, True, args.chunk, device, args.contract)
    print(f"batched: {batched['seconds']:.1f} s, peak {batched['peak_over_base']:.0f} MB over its base", flush=True)
    gaps = [math.dist(a, b) for a, b in zip(one["finals"], batched["finals"], strict=True) if a and b]
    print(f"batched against predict per candidate (another random stream): median "
          f"{statistics.median(gaps) * 1000:.2f} mm, largest {max(gaps) * 1000:.2f} mm over {len(gaps)} candidates")
    holds = batched["contract_m"] <= 1e-4 and batched["contract_rad"] <= 1e-4
    print(f"contract (chunks of {args.chunk} against chunks of 1, {batched['contract_count']} candidates): largest "
          f"{batched['contract_m']:.2e} m, {batched['contract_rad']:.2e} rad: {'holds' if holds else 'FAILS'}")
    print(f"scoring a goal under those {batched['contract_count']} candidates' densities (the first log_prob, each "
          f"density's normaliser made): {batched['score_s']:.1f} s")
    model = load_model(model_path, map_location=device)
    observed = observations(args.observations, model)
    started = time.perf_counter()
    posterior = model.condition_on(observed).physics_posterior
    per_obs = (time.perf_counter() - started) / len(observed)
    print(f"observations accepted {posterior.observed}, left out {posterior.rejected}")
    cloud, starts, _ = candidates(1, device)
    features = features_for(cloud, model.settings, model.position)
    times = []
    for k in range(11):
        started = time.perf_counter()
        predict(model, features, model.actions[1], torch.Generator().manual_seed(k), robot_start=starts[0])
        times.append(time.perf_counter() - started)
    p50 = statistics.median(times[1:])
    print(f"conditioning on {len(observed)} observations: {per_obs * len(observed):.1f} s; warm predict {p50:.3f} s")
    print(f"one_by_one_s={one['seconds']:.2f} batched_s={batched['seconds']:.2f} "
          f"speedup={one['seconds'] / batched['seconds']:.2f} peak_mb_over_base={batched['peak_over_base']:.0f} "
          f"condition_per_obs_s={per_obs:.3f} predict_p50_s={p50:.3f} device={device}")


if __name__ == "__main__":
    main()
