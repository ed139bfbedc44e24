"""Scale-out benchmark: the same plan with the local pool and with Ray, at 1 and 2 CPUs; training memory and time.

Paper, Experimental Setup (the simulated pushes; the paper protocol simulates 189,000). For each executor the
same cube plan (the paper's training pushes) is simulated into a fresh folder with 1 and with 2 CPUs (local:
``workers``; Ray: a local instance's ``num_cpus``, started once without its dashboard before any timing, and
warmed up). Each timed run simulates ``--pushes`` pushes (sized so a run lasts about a minute here). The
records of all four runs are compared bit for bit. Then the default model is trained on 10,000 and on 100,000
pushes, each in a fresh process that reports its peak memory (max RSS) and the seconds ``train_push_model``
took, and both when its bandwidth search began (one line per size): the records are one 3,000-push run's
arrays tiled (each copy's push indices shifted, every value otherwise repeated), loaded as training loads them
(``trajectories=False``). Training places its pushes block by block
(``pushtorch.models.motion.training_blocks``), so its memory should not grow with the pushes and its time
should grow about linearly (targets: ``train_peak_mb_100k <= 2000``, ``train_s_100k <= 12 train_s_10k``).
Then ``--bandwidth-pushes`` fresh pushes per action (5,000; simulated, not tiled: a tile's copies would share a
fold) train the default model's parts and its bandwidth search, which must choose from data (held-out pushes
scored) rather than keep the configured values. Last, the whole experiment at 1 and 2 CPUs: the quickstart's
friction-biasing part alone (its configuration pinned: ``experiment=quickstart``, the other parts dropped, no
progress bars) with ``executor=ray``, in a fresh process and a fresh run folder each time, confined to the CPUs
(``sched_setaffinity``: the submitting process and its Ray instance alike) with ``executor.num_cpus`` as many;
``--experiment-repeats`` times each (3), alternating. ``experiment_scaling`` is the median wall time at 1 CPU
over the median at 2 (target >= 1.7); the serial fraction it implies (Amdahl: ``2/s - 1``) is printed beside it,
for docs/cluster.md's extrapolation, and per kind of task (from each run's log) its wall time at 1 and 2 CPUs and
the CPU time its tasks took at each: the same tasks taking longer when both CPUs are busy bounds the scaling.

    .venv/bin/python tools/bench_scale.py [--pushes 3000] [--train-pushes 10000 100000] [--skip-train]
        [--skip-scale] [--bandwidth-pushes 5000] [--skip-bandwidth] [--experiment-repeats 3]
        [--skip-experiment]

The last line is ``local_pps=<..> ray_pps=<..> local_scaling=<..> ray_scaling=<..> identical=<0|1>
train_peak_mb_100k=<..> train_s_10k=<..> train_s_100k=<..> experiment_scaling=<..> bandwidth_from_data=<0|1>``
(pushes/s at 2 CPUs; scaling = 2-CPU over 1-CPU throughput; the training values are those of the smaller and
the larger of ``--train-pushes``; ``nan`` where a part was skipped).
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch.objects import load_object
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.executors import Executor


def _plan(pushes: int, seed: int = 0):
    cube = load_object("cube")
    return cube, plan_training_pushes(cube, make_actions(3), max(1, pushes // 3), Normal(0.5, 0.025),
                                      Normal(0.3, 0.05), seed=seed)


def _timed(kind: str, cpus: int, pushes: int, folder: Path) -> float:
    cube, plan = _plan(pushes)
    executor = Executor("ray", num_cpus=cpus) if kind == "ray" else None
    started = time.perf_counter()
    run_plan(object_spec(cube), plan, folder, workers=cpus, shard_size=25, progress=False, executor=executor)
    return len(plan) / (time.perf_counter() - started)


def _bandwidth_from_data(per_action: int, folder: Path) -> int:
    """1 if the default model's bandwidth search, on ``per_action`` fresh pushes per action, scores held-out pushes
    (chooses from data), else 0; prints what it kept."""
    from pushtorch.models.bandwidth import select_bandwidths
    from pushtorch.models.settings import ModelSettings
    from pushtorch.models.training import fit_object_parts

    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), per_action, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=2)
    started = time.perf_counter()
    run_plan(object_spec(cube), plan, folder, progress=True)
    print(f"simulated {len(plan)} fresh pushes in {time.perf_counter() - started:.0f} s", flush=True)
    records = load_records(folder, trajectories=False)
    settings, generator = ModelSettings(), torch.Generator().manual_seed(0)
    _, _, motions = fit_object_parts(cube, records, settings, generator)
    started = time.perf_counter()
    _, search = select_bandwidths(settings, motions, settings.bandwidth_folds, generator)
    print(f"bandwidth search on {per_action} pushes per action: {search.held_out} held-out pushes, score "
          f"{search.score_start} -> {search.score_chosen}, {time.perf_counter() - started:.1f} s; chose "
          f"{search.chosen}", flush=True)
    if search.unseen:  # pushes of which the search kept no kernel (it subsampled): scored after it
        better = search.unseen_chosen is not None and (search.unseen_start is None
                                                       or search.unseen_chosen >= search.unseen_start)
        print(f"on {search.unseen} pushes the search never saw: held-out log-likelihood {search.unseen_start} "
              f"configured, {search.unseen_chosen} chosen (nats a push): the chosen "
              f"{'at least as good' if better else 'WORSE'}", flush=True)
    return int(search.held_out > 0 and search.score_chosen is not None)


#: The pinned experiment: the quickstart's friction-biasing part alone.
EXPERIMENT = ["experiment=quickstart", "experiment.progress=false", "executor=ray", "~experiment.parts.model_selection",
              "~experiment.parts.pose_estimation", "~experiment.parts.mass_biasing",
              "~experiment.parts.online_adaptation"]


#: A log line of tasks run on the executor: their kind, wall seconds and summed seconds of work.
_TASK_LINE = re.compile(r"\] - \d+ (?P<kind>[^\[\]]+?) as ray tasks on .*?: (?P<wall>\d+) s \((?P<work>\d+) s of work")
#: The log line of the training pushes as shards: their wall seconds (the shards' work is not summed there).
_SHARDS_LINE = re.compile(r"\] - the training pushes of \d+ models as ray shards: (?P<wall>\d+) s")


def _experiment_seconds(cpus: int, folder: Path) -> tuple[float, dict[str, tuple[float, float]]]:
    """Wall seconds of the pinned experiment in a fresh process confined to the first ``cpus`` CPUs, and per kind
    of task its wall and summed work seconds (from the run's log)."""
    allowed = sorted(os.sched_getaffinity(0))[:cpus]
    started = time.perf_counter()
    result = subprocess.run([sys.executable, "-m", "pushtorch", *EXPERIMENT, f"executor.num_cpus={cpus}",
                             f"hydra.run.dir={folder}"], capture_output=True, text=True, timeout=4 * 3600,
                            preexec_fn=lambda: os.sched_setaffinity(0, allowed))
    seconds = time.perf_counter() - started
    if result.returncode != 0:
        raise SystemExit(f"the experiment at {cpus} CPU failed: {result.stderr[-2000:]}")
    text = (folder / "pushtorch.log").read_text()
    phases = {m["kind"]: (float(m["wall"]), float(m["work"])) for m in _TASK_LINE.finditer(text)}
    if shards := _SHARDS_LINE.search(text):
        phases["training pushes as shards"] = (float(shards["wall"]), float("nan"))
    return seconds, phases


def _phase_lines(phases: dict[int, list[dict[str, tuple[float, float]]]]) -> list[str]:
    """Per kind of task found in every run: its median wall and work seconds at 1 and 2 CPUs, and the scaling the
    work's growth allows (``2 · work₁ / work₂``)."""
    import statistics

    runs = phases[1] + phases[2]
    lines = []
    for kind in sorted(set.intersection(*(set(p) for p in runs))) if runs else []:
        wall = {c: statistics.median([p[kind][0] for p in phases[c]]) for c in (1, 2)}
        work = {c: statistics.median([p[kind][1] for p in phases[c]]) for c in (1, 2)}
        line = f"  {kind}: {wall[1]:.0f} s at 1 CPU, {wall[2]:.0f} s at 2 ({wall[1] / wall[2]:.2f})"
        if work[1] == work[1]:  # the shards' line sums no work
            line += (f"; its tasks' work {work[1]:.0f} s at 1 CPU, {work[2]:.0f} s at 2 (x{work[2] / work[1]:.2f}: at "
                     f"most {2 * work[1] / work[2]:.2f} from 2 CPUs)")
        lines.append(line)
    return lines


def _experiment_scaling(repeats: int, root: Path) -> float:
    """The pinned experiment's median wall time at 1 CPU over its median at 2 (module notes). Per kind of task it
    prints how its wall time scaled and how much longer the same tasks took at 2 CPUs than at 1 (each worker compiles
    the fast path once; shared caches): work that grows with the workers bounds the scaling whatever the split."""
    import statistics

    seconds: dict[int, list[float]] = {1: [], 2: []}
    phases: dict[int, list[dict[str, tuple[float, float]]]] = {1: [], 2: []}
    for k in range(repeats):
        for cpus in (1, 2):
            wall, kinds = _experiment_seconds(cpus, root / f"experiment_{cpus}_{k}")
            seconds[cpus].append(wall)
            phases[cpus].append(kinds)
            print(f"the friction-biasing part on Ray, {cpus} CPU: {seconds[cpus][-1]:.1f} s", flush=True)
    for line in _phase_lines(phases):
        print(line, flush=True)
    scaling = statistics.median(seconds[1]) / statistics.median(seconds[2])
    print(f"experiment: medians {statistics.median(seconds[1]):.1f} s at 1 CPU, {statistics.median(seconds[2]):.1f} s"
          f" at 2; scaling {scaling:.2f}, serial fraction {2 / scaling - 1:.3f} (Amdahl)", flush=True)
    return scaling


def _train(pushes: int, base: Path) -> dict[str, float]:
    """A fresh process loads ``pushes`` tiled records and trains the default model: its max RSS (MB) and the
    seconds ``train_push_model`` took (``peak_mb``, ``seconds``), and both when the bandwidth search began, after
    the contact, position and motion models (``parts_peak_mb``, ``parts_seconds``)."""
    script = f"""
import resource, time, torch
from dataclasses import replace
import pushtorch.models.bandwidth as bandwidth
from pushtorch.objects import load_object
from pushtorch.sim import load_records
from pushtorch.sim.records import PushRecords
from pushtorch.models.training import train_push_model
one = load_records({str(base)!r}, trajectories=False)
copies = -(-{pushes} // len(one))
records = PushRecords.cat([replace(one, index=one.index + k * len(one)) for k in range(copies)])
records = records.take(torch.arange({pushes}))
cube = load_object("cube")
peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
parts = [float("nan"), float("nan")]
search = bandwidth.select_bandwidths
def select_bandwidths(*args, **kwargs):
    parts[:] = [peak(), time.perf_counter() - started]
    return search(*args, **kwargs)
bandwidth.select_bandwidths = select_bandwidths
started = time.perf_counter()
train_push_model(cube, records, generator=0)
seconds = time.perf_counter() - started
print(peak(), seconds, *parts)
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=6 * 3600)
    if result.returncode != 0:
        raise SystemExit(f"training on {pushes} pushes failed: {result.stderr[-2000:]}")
    values = [float(v) for v in result.stdout.strip().splitlines()[-1].split()]
    return dict(zip(("peak_mb", "seconds", "parts_peak_mb", "parts_seconds"), values, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pushes", type=int, default=3000, help="pushes per timed run (default 3000)")
    parser.add_argument("--train-pushes", type=int, nargs=2, default=[10_000, 100_000], metavar=("SMALL", "LARGE"),
                        help="the two training sizes (default 10000 100000)")
    parser.add_argument("--skip-train", action="store_true", help="leave out the training measurements")
    parser.add_argument("--skip-scale", action="store_true", help="leave out the executors' throughput")
    parser.add_argument("--bandwidth-pushes", type=int, default=5000,
                        help="fresh pushes per action for the bandwidth search's check (default 5000)")
    parser.add_argument("--skip-bandwidth", action="store_true", help="leave out the bandwidth search's check")
    parser.add_argument("--experiment-repeats", type=int, default=3,
                        help="runs of the experiment at each CPU count (default 3; the medians' ratio)")
    parser.add_argument("--skip-experiment", action="store_true", help="leave out the experiment's scaling")
    args = parser.parse_args()

    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); {args.pushes} pushes per timed run")
    nan = float("nan")
    rate: dict[tuple[str, int], float] = {(kind, cpus): nan for kind in ("local", "ray") for cpus in (1, 2)}
    identical = nan
    trained = {n: {"peak_mb": nan, "seconds": nan} for n in args.train_pushes}
    with tempfile.TemporaryDirectory(prefix="pushtorch-scale-") as tmp:
        root = Path(tmp)
        if not args.skip_scale:
            import ray

            for cpus in (1, 2):
                rate[("local", cpus)] = _timed("local", cpus, args.pushes, root / f"local{cpus}")
                print(f"local, {cpus} CPU: {rate[('local', cpus)]:.1f} pushes/s", flush=True)
            for cpus in (1, 2):
                ray.init(address="local", num_cpus=cpus, include_dashboard=False, log_to_driver=False)
                _timed("ray", cpus, 30, root / f"warm{cpus}")  # workers started and their worlds built
                rate[("ray", cpus)] = _timed("ray", cpus, args.pushes, root / f"ray{cpus}")
                ray.shutdown()
                print(f"ray, {cpus} CPU: {rate[('ray', cpus)]:.1f} pushes/s", flush=True)
            reference = load_records(root / "local1")
            identical = int(all(
                torch.equal(load_records(root / name).object_final.p, reference.object_final.p)
                and torch.equal(load_records(root / name).object_trajectory.q, reference.object_trajectory.q)
                for name in ("local2", "ray1", "ray2")))
        if not args.skip_train:
            cube, plan = _plan(3000, seed=1)
            run_plan(object_spec(cube), plan, root / "base", progress=False)
            for pushes in sorted(args.train_pushes):
                t = trained[pushes] = _train(pushes, root / "base")
                print(f"training the default model on {pushes} pushes: {t['seconds']:.1f} s, peak {t['peak_mb']:.0f} MB"
                      f" (contact, position and motion models: {t['parts_seconds']:.1f} s, peak"
                      f" {t['parts_peak_mb']:.0f} MB; then the bandwidth search)", flush=True)
        from_data = nan if args.skip_bandwidth else _bandwidth_from_data(args.bandwidth_pushes, root / "bandwidth")
        experiment = nan if args.skip_experiment else _experiment_scaling(args.experiment_repeats, root)
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(f"this process's peak: {own:.0f} MB")
    small, large = min(args.train_pushes), max(args.train_pushes)
    print(f"local_pps={rate[('local', 2)]:.1f} ray_pps={rate[('ray', 2)]:.1f} "
          f"local_scaling={rate[('local', 2)] / rate[('local', 1)]:.2f} "
          f"ray_scaling={rate[('ray', 2)] / rate[('ray', 1)]:.2f} identical={identical} "
          f"train_peak_mb_100k={trained[large]['peak_mb']:.0f} train_s_10k={trained[small]['seconds']:.1f} "
          f"train_s_100k={trained[large]['seconds']:.1f} experiment_scaling={experiment:.2f} "
          f"bandwidth_from_data={from_data}")

if __name__ == "__main__":
    main()
