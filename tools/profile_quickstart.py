"""Where the quickstart's time goes: wall time per part and stage, and the top functions, under cProfile.

Runs the quickstart (``python -m pushtorch``, ``experiment=quickstart``) in this process under cProfile, in a fresh
run folder (``hydra.run.dir=<out>/run``; progress bars off: ``experiment.progress=false``), and prints the CPU
(``/proc/cpuinfo`` model name, usable cores, torch threads, load averages), a table part × stage (seconds), the
total wall time and CPU time (this process, its children), torch.compile's share, each stage function's calls and
cumulative time, and the top functions by cumulative and by own time.

Stages (:data:`RULES` lists their functions): simulate (training pushes), train, observe (clouds, surface
features), predict, condition (online adaptation), peers (physics baselines and peers), truth (ground-truth
pushes), score, record (recording, report, figures), other. Times are exclusive: a moment counts once, for the
innermost stage function running, but inside train, peers, truth and record all stays theirs (a re-prediction
for the recording is record). Rows (startup) (imports, Hydra, context) and (suite) (after each part: blueprint,
results.json, report, figures) lie outside the parts. The timers wrap the stage functions: in ``quickstart.prof``
each stage function's caller is this tool's ``_timed_call`` (``print_callees`` still shows what they call).

Worker processes: ``run_plan`` simulates a plan of one shard or more (training pushes; ground truth of 4 shards
or more) in forked workers, one per usable core (``experiment.workers=0``), which run unprofiled; the parent's
profile shows that time as waiting (``imap_unordered``, ``lock.acquire``) and their CPU time is the children's.
Absolute times include cProfile's overhead (``--no-profile``: stage timers only) and the machine's other load.

    .venv/bin/python tools/profile_quickstart.py [--parts friction_biasing,online_adaptation] [--out DIR]
        [--tree WORKTREE] [--top 25] [--no-profile] [-- hydra overrides ...]

``--tree`` profiles another checkout (a ``git worktree``): the tool runs itself again with that tree on
``PYTHONPATH``, the editable install's import hook dropped by a ``sitecustomize`` and ``pushtorch/conf -> ../conf``
linked inside the tree (as ``tools/compare_revisions.py`` does), and stops if ``pushtorch`` or ``pushtorch.conf``
come from elsewhere. ``--out`` (default: a new temporary folder) keeps the run and ``quickstart.prof``.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import os
import pstats
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

STAGES = ("simulate", "train", "observe", "predict", "condition", "peers", "truth", "score", "record", "other")
STICKY = {"train", "peers", "truth", "record"}  # what runs inside them stays theirs
#: The modules whose ``run_part`` runs a part of the suite.
PARTS = ("model_selection", "pose_estimation", "biasing", "online_adaptation", "shape_transfer")
RULES = {  # stage: {pushtorch module (or "new|old" where a refactor moved it): its functions (or Class.method)}
    "simulate": {"experiments.training": "training_records", "sim.runner": "run_plan"},
    "train": {"models.training": "train_push_model", "models.pooled": "train_pooled_model fit_shape_parts",
              "evaluation.transfer": "choose_widening", "models.bandwidth": "select_bandwidths",
              "experiments.pose_estimation": "_position_model"},
    "observe": {"experiments.prediction_sets|experiments.evaluation": "observe", "perception": "capture_partial_cloud",
                "features": "compute_surface_features"},
    "predict": {"prediction.forward|prediction.predict": "predict predict_many",
                "models.push_condition|prediction.conditions": "estimate_pose",
                "experiments.online_adaptation": "_Group.predicted",
                "evaluation.likelihood": "motion_product_density mean_motion_density",
                "evaluation.baselines": "mean_motion_prediction nearest_push_prediction"},
    "condition": {"models.library": "ModelLibrary.condition_on", "models.model": "PushModel.condition_on"},
    "peers": {"evaluation.baselines": "oracle_physics_prediction physics_from_cloud_prediction "
                                      "physics_ensemble_prediction fit_cloud_physics",
              "evaluation.likelihood": "ensemble_density", "experiments.online_adaptation": "_Group.cloud_physics"},
    "truth": {"experiments.scoring|experiments.evaluation": "simulate_truth", "sim.runner": "simulate_pushes"},
    "score": {"experiments.scoring|experiments.evaluation": "likelihood_scores compare_displacement compare summarise",
              "evaluation.metrics": "accuracy", "experiments.online_adaptation": "_Scores.add _condition_records"},
    "record": {"experiments.recording": "log_examples", "experiments.training": "_log_training",
               "experiments.pose_estimation": "_log_pose_example", "viz.online": "log_online_adaptation",
               "experiments.suite": "_log_part", "experiments.report": "write_outputs", "viz.core": "open_recording"},
}
SITECUSTOMIZE = """import sys  # written by tools/profile_quickstart.py: drop the editable install's import hook
sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable___pushtorch")]
sys.path[:] = [p for p in sys.path if not (isinstance(p, str) and p.startswith("__editable__.pushtorch"))]
"""


class Clock:
    """Exclusive wall time per (part, stage): each moment is charged to the stage on top of the stack."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, str], float] = defaultdict(float)
        self.part, self.stack, self.parts = "(startup)", ["other"], []
        self.last = time.perf_counter()

    def _charge(self) -> None:
        now = time.perf_counter()
        self.seconds[(self.part, self.stack[-1])] += now - self.last
        self.last = now

    def wrap(self, fn, stage: str | None):
        """``fn`` timed as ``stage``; ``None``: a part's ``run_part`` (its ``part["name"]`` names the part)."""
        @functools.wraps(fn)
        def _timed_call(*args, **kwargs):
            self._charge()
            saved = (self.part, self.stack)
            if stage is None:
                self.part, self.stack = str(dict(args[1]).get("name", fn.__module__)), ["other"]
                self.parts.append(self.part)
            else:
                self.stack = [*self.stack, self.stack[-1] if self.stack[-1] in STICKY else stage]
            try:
                return fn(*args, **kwargs)
            finally:
                self._charge()
                self.part, self.stack = ("(suite)", saved[1]) if stage is None else saved
        return _timed_call


def instrument(clock: Clock) -> list[tuple[str, str, object]]:
    """Wrap every stage function and each part kind's ``run_part`` wherever pushtorch's modules hold them;
    returns ``(stage, name, original)`` of those found (a name a revision lacks is skipped)."""
    import importlib

    targets = [(None, f"pushtorch.experiments.{m}:run_part") for m in PARTS]
    targets += [(stage, f"pushtorch.{module}:{name}") for stage, table in RULES.items()
                for module, names in table.items() for name in names.split()]
    found = []
    for stage, target in targets:
        modules, _, attr = target.partition(":")
        *path, leaf = attr.split(".")
        for module_name in modules.replace("|", "|pushtorch.").split("|"):
            try:
                owner = importlib.import_module(module_name)
                for name in path:
                    owner = getattr(owner, name)
                original = getattr(owner, leaf)
                break
            except (ImportError, AttributeError):
                continue
        else:
            print(f"note: {target} not found in this revision; not timed", flush=True)
            continue
        target = f"{module_name}:{attr}"
        wrapped = clock.wrap(original, stage)
        setattr(owner, leaf, wrapped)
        if not path:  # the function's other names: `from module import name` in any loaded pushtorch module
            for module in [m for n, m in list(sys.modules.items()) if n.split(".")[0] == "pushtorch"]:
                for key, value in list(vars(module).items()):
                    if value is original:
                        setattr(module, key, wrapped)
        found.append((stage or "part", target, original))
    return found


def where(key: tuple[str, int, str]) -> str:
    """A profile entry as ``file:line(function)``, paths shortened to the package."""
    filename, line, name = key
    if filename == "~":
        return name
    stdlib = f"/python{sys.version_info[0]}.{sys.version_info[1]}/"
    for marker, prefix in (("site-packages/", ""), ("/pushtorch/", "pushtorch/"), (stdlib, "")):
        if marker in filename:
            filename = prefix + filename.split(marker, 1)[1]
            break
    return f"{filename}:{line}({name})"


def print_top(stats: pstats.Stats, column: int, title: str, top: int) -> None:
    mine = os.path.abspath(__file__)
    rows = [(k, v) for k, v in stats.stats.items() if os.path.abspath(k[0]) != mine]
    rows.sort(key=lambda kv: kv[1][column], reverse=True)
    print(f"\n{title}\n{'calls':>16} {'own s':>8} {'cum s':>8}  function")
    for key, (cc, nc, tt, ct, _) in rows[:top]:
        calls = f"{nc}/{cc}" if nc != cc else str(nc)
        print(f"{calls:>16} {tt:8.1f} {ct:8.1f}  {where(key)}")


def report(clock: Clock, stats: pstats.Stats | None, found, wall: float, cpu: tuple, load: tuple, top: int) -> None:
    import torch

    info = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    name = next((line.split(":", 1)[1].strip() for line in info.splitlines() if line.startswith("model name")), "?")
    print(f"\nCPU: {name} ({os.cpu_count()} logical CPUs, {len(os.sched_getaffinity(0))} usable); torch threads: "
          f"{torch.get_num_threads()} intra-op, {torch.get_num_interop_threads()} inter-op; load average "
          f"{load[0]:.2f} at start, {os.getloadavg()[0]:.2f} at end (others' work inflates every time here)")
    rows = [*clock.parts, "(startup)", "(suite)"]
    print(f"\nwall time per part and stage (s; exclusive, see the docstring)\n{'part':<20}"
          + "".join(f"{s:>10}" for s in STAGES) + f"{'total':>10}")
    for row in [*rows, "total"]:
        values = [sum(v for (p, s), v in clock.seconds.items() if s == stage and (row == "total" or p == row))
                  for stage in STAGES]
        print(f"{row:<20}" + "".join(f"{v:10.1f}" for v in values) + f"{sum(values):10.1f}")
    user, system, child_user, child_system = cpu
    print(f"\ntotal wall time {wall:.1f} s; CPU time: this process {user + system:.1f} s, its child processes "
          f"(simulation workers, Inductor's C++ compiler) {child_user + child_system:.1f} s")
    print("workers: run_plan simulates plans of >= 1 shard (training pushes; ground truth of >= 4 shards) in forked "
          "worker processes (experiment.workers=0: one per usable core); this single-process profile shows their "
          "time as the parent waiting (imap_unordered / lock.acquire), inside the stage that ran the plan")
    if stats is None:
        return
    dynamo = [v[3] for k, v in stats.stats.items() if k[0].endswith("_dynamo/convert_frame.py") and k[2] == "_compile"]
    print(f"torch.compile (Dynamo _compile, cumulative, inside the stages above): {max(dynamo, default=0.0):.1f} s")
    print(f"\nstage functions (cProfile, cumulative; nested calls overlap)\n{'stage':<10}{'calls':>8}{'cum s':>9}  "
          "function")
    for stage, target, original in found:
        code = getattr(original, "__code__", None)
        entry = stats.stats.get((code.co_filename, code.co_firstlineno, code.co_name)) if code else None
        if entry:
            print(f"{stage:<10}{entry[1]:>8}{entry[3]:9.1f}  {target}")
    print_top(stats, 3, f"top {top} functions by cumulative time", top)
    print_top(stats, 2, f"top {top} functions by own (total) time", top)


def in_tree(args, argv: list[str]) -> int:
    """Run this tool again with ``args.tree``'s pushtorch alone on the path (see the docstring)."""
    tree = args.tree.resolve()
    shim = args.out / "shim"
    shim.mkdir(parents=True, exist_ok=True)
    (shim / "sitecustomize.py").write_text(SITECUSTOMIZE)
    link = tree / "pushtorch" / "conf"
    if not link.exists() and (tree / "conf").is_dir():
        link.symlink_to("../conf", target_is_directory=True)
        print(f"linked {link} -> ../conf", flush=True)
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{shim}", "PROFILE_QUICKSTART_TREE": str(tree)}
    env.pop("PYTHONSTARTUP", None)
    return subprocess.run([sys.executable, os.path.abspath(__file__), *argv], cwd=tree, env=env).returncode


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, overrides = (argv[: argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", help="comma-separated quickstart parts to run (default: all)")
    parser.add_argument("--out", type=Path, help="folder for the run and quickstart.prof (default: a new temp folder)")
    parser.add_argument("--tree", type=Path, help="profile the pushtorch of this checkout (a git worktree)")
    parser.add_argument("--top", type=int, default=25, help="functions listed by cumulative and by own time")
    parser.add_argument("--no-profile", action="store_true", help="stage timers only, without cProfile")
    args = parser.parse_args(ours)
    args.out = (args.out or Path(tempfile.mkdtemp(prefix="profile_quickstart_"))).resolve()
    if args.tree and os.environ.get("PROFILE_QUICKSTART_TREE") != str(args.tree.resolve()):
        return in_tree(args, [*ours, "--out", str(args.out), "--", *overrides])
    run_dir = args.out / "run"
    if run_dir.exists() and any(run_dir.iterdir()):
        parser.error(f"{run_dir} holds an earlier run (its caches would be reused): give a fresh --out")
    start, cpu0, load = time.perf_counter(), os.times(), os.getloadavg()
    clock = Clock()
    import pushtorch.conf
    from omegaconf import OmegaConf

    import pushtorch
    from pushtorch.apps import experiment

    tree = os.environ.get("PROFILE_QUICKSTART_TREE")
    for place in (pushtorch.__file__, pushtorch.conf.__file__):
        if tree and not os.path.realpath(place).startswith(os.path.realpath(tree) + os.sep):
            sys.exit(f"error: {place} is not inside {tree}")
    print(f"pushtorch: {pushtorch.__file__}; pushtorch.conf: {pushtorch.conf.__file__}", flush=True)
    known = list(OmegaConf.load(Path(pushtorch.conf.__file__).parent / "experiment" / "quickstart.yaml")
                 .experiment.parts.keys())
    chosen = known if not args.parts else [p.strip() for p in args.parts.split(",") if p.strip()]
    if set(chosen) - set(known):
        parser.error(f"unknown parts {sorted(set(chosen) - set(known))}; the quickstart's: {', '.join(known)}")
    dropped = [f"~experiment.parts.{p}" for p in known if p not in chosen]
    found = instrument(clock)
    os.environ.setdefault("TQDM_DISABLE", "1")
    os.register_at_fork(after_in_child=lambda: sys.setprofile(None))  # forked workers run unprofiled
    sys.argv = ["pushtorch", f"hydra.run.dir={run_dir}", "experiment.progress=false", *dropped, *overrides]
    print("running:", " ".join(sys.argv), flush=True)
    profiler, status = None if args.no_profile else cProfile.Profile(), 0
    try:
        if profiler:
            profiler.enable()
        experiment.main()
    except SystemExit as exc:
        status = exc.code if isinstance(exc.code, int) else 1
    finally:
        if profiler:
            profiler.disable()
    wall, cpu1 = time.perf_counter() - start, os.times()
    clock._charge()
    if profiler:
        profiler.dump_stats(args.out / "quickstart.prof")
    stats = pstats.Stats(profiler) if profiler else None
    cpu = tuple(b - a for a, b in zip(cpu0[:4], cpu1[:4], strict=True))
    if status:
        print(f"\nWARNING: the quickstart exited with status {status}; the profile covers what ran")
    report(clock, stats, found, wall, cpu, load, args.top)
    print(f"\nrun folder {run_dir}" + ("" if not profiler else f"; profile {args.out / 'quickstart.prof'}"))
    return int(status)


if __name__ == "__main__":
    sys.exit(main())
