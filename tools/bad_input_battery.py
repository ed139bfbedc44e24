"""A battery of bad inputs against pushtorch's command-line apps, each outcome classified.

Issue 21 asks that every bad input end in a clear error: one line on stderr naming the problem, exit status 2,
no traceback and no half-made run folder. The maintainers keep their own battery; this one is ours. It runs
each case the way a new user would (``python -m <app> <overrides...>`` in a fresh empty folder, without any
``HYDRA_*`` variable, with a timeout) against real fixtures it makes once at the start (a tiny simulation run
and a model trained from it, then copies of them made bad: a missing shard, a tampered shard, a flipped byte,
a truncated file, junk; meshes with two disjoint parts, two boxes 5 cm apart, a cube written in millimetres, a NaN
vertex, no bytes at all). Every case is an
input the apps must refuse, so each outcome is one of

    clear error   exit status 2, exactly one non-empty stderr line, no "Traceback"
    traceback     "Traceback" in the output, or any other non-zero exit (Hydra's own multi-line errors too)
    silent        exit status 0: the bad input was accepted
    hang          still running at the timeout (the process group is killed)

and the table also says whether the case left a folder (``runs/``, Hydra's ``outputs/``) in its working folder.
The last lines give the counts ("N clear errors, N raw tracebacks, N silent results, N hangs"), the CPU and
the wall time; then, for every case that is not a clear error, the last 15 lines of its stderr. The exit
status is 1 if any case is not a clear error.

Run it from the repository (about 3-5 minutes on 2 cores, longer for every hang)::

    .venv/bin/python tools/bad_input_battery.py                 # every case, 2 at a time
    .venv/bin/python tools/bad_input_battery.py --only mesh     # the cases whose id or category has "mesh"
    .venv/bin/python tools/bad_input_battery.py --list          # the cases, without running them
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch.apps.cli import RUN_LOCK
from pushtorch.io import lock_file

PYTHON = sys.executable
#: Overrides that keep a simulation small if a case is (wrongly) accepted.
SIM_SMALL = ["samples_per_action=2", "workers=1", "rerun_pushes=0", "progress=false"]
#: Overrides that keep a prediction small if a case is (wrongly) accepted.
PRED_SMALL = ["truth_samples=0", "recording=false"]
#: Overrides that keep training small if a case is (wrongly) accepted.
TRAIN_SMALL = ["model=tiny", "recording=false"]

OUTCOMES = ("clear error", "traceback", "silent", "hang")


@dataclass(frozen=True)
class Fixtures:
    """Paths of the fixtures (real files made by :func:`make_fixtures`)."""

    root: Path

    def __getattr__(self, name: str) -> Path:  # every fixture is a path under root
        layout = {
            "sim": "sim", "train": "train", "model": "train/model.npz",
            "sim_missing_shard": "sim_missing_shard", "sim_tampered": "sim_tampered",
            "model_flipped": "bad_models/flipped/model.npz", "model_truncated": "bad_models/truncated/model.npz",
            "model_junk": "bad_models/junk/model.npz", "model_missing": "bad_models/nowhere/model.npz",
            "mesh_two_cubes": "meshes/two_cubes.obj", "mesh_nan": "meshes/nan_vertex.obj",
            "mesh_empty": "meshes/part.stl", "mesh_garbage": "meshes/garbage.obj",
            "mesh_missing": "meshes/no_such_part.stl", "mesh_dir": "meshes",
            "mesh_apart": "meshes/boxes_50mm_apart.obj", "mesh_mm": "meshes/cube_mm.obj",
            "empty_dir": "empty", "a_file": "a_file.txt", "nowhere": "nowhere",
            "locked": "locked", "junk_results": "junk_results", "min_results": "min_results",
        }
        if name not in layout:
            raise AttributeError(name)
        return self.root / layout[name]


@dataclass(frozen=True)
class Case:
    """One bad input: ``python -m <module> <args...>``; ``expect`` is text the error line should hold."""

    id: str
    category: str
    module: str
    args: list[str]
    expect: str | None = None


@dataclass
class Result:
    case: Case
    outcome: str
    code: int | None
    stdout: str
    stderr: str
    seconds: float
    made: list[str] = field(default_factory=list)

    @property
    def lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.strip()]


def cases(fx: Fixtures) -> list[Case]:
    """Every case of the battery, in categories: configs, meshes, model files, records, folders."""
    m, sim, train, pred = "pushtorch", "pushtorch.apps.simulate", "pushtorch.apps.train", "pushtorch.apps.predict"
    model = f"models=[{fx.model}]"
    data = f"data={fx.sim}"
    out: list[Case] = []

    def add(id_: str, category: str, module: str, args: list[str], expect: str | None = None) -> None:
        out.append(Case(id_, category, module, args, expect))

    # configs: the main app (its default experiment, quickstart, would run for minutes if accepted)
    add("main-seed-abc", "configs", m, ["seed=abc"], "seed")
    add("main-seed-1e20", "configs", m, ["seed=1e20"], "seed")
    add("main-seed-neg", "configs", m, ["seed=-1"], "seed")
    add("main-position-frames-2.5", "configs", m, ["model.settings.position_frames=2.5"], "position_frames")
    add("main-duration-1e9", "configs", m, ["experiment.actions.duration=1e9"], "duration")
    add("main-experiment-name-common", "configs", m, ["experiment.name=common"], "common")
    add("main-experiment-name-nope", "configs", m, ["experiment.name=nope"], "nope")
    add("main-experiment-group-nope", "configs", m, ["experiment=nope"], "nope")
    add("main-progress-maybe", "configs", m, ["experiment.progress=maybe"], "progress")
    add("main-model-friction-nonsense", "configs", m, ["model.friction=nonsense"], "nonsense")
    add("main-biasing-friction-nonsense", "configs", m,
        ["experiment=friction_biasing", "model.friction=nonsense", "model=tiny"], "nonsense")
    add("main-test-conditions-0", "configs", m, ["experiment=model_selection", "experiment.test_conditions=0"],
        "test_conditions")
    add("main-typo-sed", "configs", m, ["sed=1"], "sed")
    add("main-test-placement-lateral-0.5", "configs", m, ["test_placement=spread", "test_placement.lateral_jitter=0.5"],
        "lateral_jitter")
    add("main-test-placement-group-nope", "configs", m, ["test_placement=nope"], "nope")
    add("main-model-group-huge", "configs", m, ["model=huge"], "huge")
    add("main-sweep-one-bad", "configs", m, ["-m", "seed=1,abc", "model=tiny"], "abc")
    # configs: simulate
    add("sim-samples-abc", "configs", sim, ["samples_per_action=abc", "workers=1", "rerun_pushes=0"],
        "samples_per_action")
    add("sim-samples-huge", "configs", sim, ["samples_per_action=100000", "actions.count=100",
                                             "actions.duration=60", "workers=1", "rerun_pushes=0"], "memory")
    add("sim-scale-abc", "configs", sim, ["object.scale=abc", *SIM_SMALL], "object.scale")
    add("sim-scale-0", "configs", sim, ["object.scale=0", *SIM_SMALL], "object.scale")
    add("sim-friction-value-abc", "configs", sim, ["friction=fixed", "friction.value=abc", *SIM_SMALL],
        "friction.value")
    add("sim-friction-std-neg", "configs", sim, ["friction=low", "friction.std=-1", *SIM_SMALL], "friction")
    add("sim-friction-group-slippery", "configs", sim, ["friction=slippery", *SIM_SMALL], "slippery")
    add("sim-duration-1e9", "configs", sim, ["actions.duration=1e9"], "duration")
    add("sim-duration-1e5", "configs", sim, ["actions.duration=1e5"], "duration")
    add("sim-count-0", "configs", sim, ["actions.count=0", *SIM_SMALL], "actions.count")
    add("sim-speed-neg", "configs", sim, ["actions.speed=-1", *SIM_SMALL], "actions.speed")
    add("sim-angle-range-reversed", "configs", sim, ["actions.angle_range_deg=[10,-10]", *SIM_SMALL],
        "angle_range_deg")
    add("sim-time-step-abc", "configs", sim, ["sim.time_step=abc", *SIM_SMALL], "time_step")
    add("sim-workers-neg", "configs", sim, ["workers=-3", "samples_per_action=2", "rerun_pushes=0"], "workers")
    add("sim-shard-size-0", "configs", sim, ["shard_size=0", *SIM_SMALL], "shard_size")
    add("sim-mesh-no-path", "configs", sim, ["object=mesh", *SIM_SMALL], "object.path")
    add("sim-cube-named-sphere", "configs", sim, ["object=cube", "object.name=sphere", *SIM_SMALL], "sphere")
    add("sim-start-method-thread", "configs", sim, ["start_method=thread", *SIM_SMALL], "start_method")
    add("sim-sweep-one-bad", "configs", sim, ["-m", "seed=0,abc", *SIM_SMALL], "abc")
    # configs: predict (a real model, so only the bad value can be the problem)
    add("pred-no-models", "configs", pred, [*PRED_SMALL], "models")
    add("pred-models-empty", "configs", pred, ["models=[]", *PRED_SMALL], "models")
    add("pred-x-1e9", "configs", pred, [model, "x=1e9", *PRED_SMALL], "x")
    add("pred-y-60", "configs", pred, [model, "y=60", *PRED_SMALL], "y")
    add("pred-yaw-abc", "configs", pred, [model, "yaw_deg=abc", *PRED_SMALL], "yaw_deg")
    add("pred-actions-neg", "configs", pred, [model, "actions=[0,-1]", *PRED_SMALL], "actions")
    add("pred-actions-7", "configs", pred, [model, "actions=[7]", *PRED_SMALL], "7")
    add("pred-truth-samples-neg", "configs", pred, [model, "truth_samples=-1", "recording=false"],
        "truth_samples")
    # configs: train (the fixture run is real data, so only the bad value can be the problem)
    add("train-no-data", "configs", train, [*TRAIN_SMALL], "data")
    add("train-allow-partial-yes", "configs", train, [data, "allow_partial=yes", *TRAIN_SMALL], "allow_partial")
    add("train-name-slash", "configs", train, [data, "name=a/b", *TRAIN_SMALL], "name")
    add("train-wrong-object", "configs", train, [data, "object=cylinder", *TRAIN_SMALL], "cylinder")
    # meshes (simulate loads the object first; small sizes in case a mesh is wrongly accepted)
    for id_, path, expect in (("mesh-two-disjoint-cubes", fx.mesh_two_cubes, "two_cubes"),
                              ("mesh-nan-vertex", fx.mesh_nan, "nan_vertex"),
                              ("mesh-empty-stl", fx.mesh_empty, "part.stl"),
                              ("mesh-garbage-obj", fx.mesh_garbage, "garbage.obj"),
                              ("mesh-missing-path", fx.mesh_missing, "no_such_part"),
                              ("mesh-directory", fx.mesh_dir, "meshes"),
                              ("mesh-boxes-50mm-apart", fx.mesh_apart, "50.0 mm apart"),
                              ("mesh-millimetres-at-scale-1", fx.mesh_mm, "object.scale=0.001")):
        add(id_, "meshes", sim, ["object=mesh", f"object.path={path}", *SIM_SMALL], expect)
    add("mesh-up-x", "meshes", sim, ["object=mesh", f"object.path={fx.mesh_mm}", "object.scale=0.001", "object.up=x",
                                     *SIM_SMALL], "object.up")
    add("mesh-predict-two-cubes", "meshes", pred,
        [model, "object=mesh", f"object.path={fx.mesh_two_cubes}", *PRED_SMALL], "two_cubes")
    # model files
    add("model-flipped-byte", "model files", pred, [f"models=[{fx.model_flipped}]", *PRED_SMALL], "model.npz")
    add("model-truncated", "model files", pred, [f"models=[{fx.model_truncated}]", *PRED_SMALL], "model.npz")
    add("model-junk-text", "model files", pred, [f"models=[{fx.model_junk}]", *PRED_SMALL], "model.npz")
    add("model-missing", "model files", pred, [f"models=[{fx.model_missing}]", *PRED_SMALL], "nowhere")
    add("model-is-folder", "model files", pred, [f"models=[{fx.train}]", *PRED_SMALL], "train")
    add("model-is-shard", "model files", pred, [f"models=[{fx.sim}/pushes/shard-000000.npz]", *PRED_SMALL],
        "shard-000000")
    add("model-given-as-train-data", "model files", train, [f"data={fx.model}", *TRAIN_SMALL], "model.npz")
    # push records
    add("rec-missing-shard", "records", train, [f"data={fx.sim_missing_shard}", *TRAIN_SMALL],
        "pushtorch.apps.simulate")
    add("rec-tampered-shard", "records", train, [f"data={fx.sim_tampered}", *TRAIN_SMALL], "shard-000001")
    add("rec-empty-folder", "records", train, [f"data={fx.empty_dir}", *TRAIN_SMALL], "empty")
    add("rec-not-a-run", "records", train, [f"data={fx.train}", *TRAIN_SMALL], "train")
    add("rec-data-is-file", "records", train, [f"data={fx.a_file}", *TRAIN_SMALL], "a_file")
    add("rec-data-missing", "records", train, [f"data={fx.nowhere}", *TRAIN_SMALL], "nowhere")
    # folders
    add("folder-run-dir-under-file", "folders", sim, [f"hydra.run.dir={fx.a_file}/run", *SIM_SMALL], "a_file")
    add("folder-run-dir-is-file", "folders", sim, [f"hydra.run.dir={fx.a_file}", *SIM_SMALL], "a_file")
    add("folder-sweep-dir-under-file", "folders", sim,
        ["-m", "seed=0,1", f"hydra.sweep.dir={fx.a_file}/sweep", *SIM_SMALL], "a_file")
    add("folder-run-dir-locked", "folders", train, [data, f"hydra.run.dir={fx.locked}", *TRAIN_SMALL], "in use")
    add("collect-no-folder", "folders", "pushtorch.apps.collect", [], "folders")
    add("collect-missing-folder", "folders", "pushtorch.apps.collect", [str(fx.nowhere)], "nowhere")
    add("collect-empty-folder", "folders", "pushtorch.apps.collect", [str(fx.empty_dir)], "results.json")
    add("collect-junk-results", "folders", "pushtorch.apps.collect", [str(fx.junk_results)], "results.json")
    add("collect-out-under-file", "folders", "pushtorch.apps.collect",
        [str(fx.min_results), "--out", f"{fx.a_file}/out"], "a_file")
    return out


# ---------------------------------------------------------------------------------------------------- fixtures

def _env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("HYDRA_")}


def _fixture_run(argv: list[str], cwd: Path, what: str) -> None:
    proc = subprocess.run([PYTHON, "-m", *argv], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=600)
    if proc.returncode != 0:
        sys.stderr.write(f"fixture {what} failed (exit {proc.returncode}): {' '.join(argv)}\n{proc.stderr[-3000:]}\n")
        raise SystemExit(3)


def _cube(centre: tuple[float, float, float], half: float, first: int) -> tuple[list[str], list[str]]:
    """OBJ vertex and face lines of an axis-aligned cube (faces 1-based from ``first``, outward normals)."""
    cx, cy, cz = centre
    vertices = [f"v {cx + sx * half:.6f} {cy + sy * half:.6f} {cz + sz * half:.6f}"
                for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    # vertex k = 4*ix + 2*iy + iz (0-based), quads as two triangles each, counter-clockwise seen from outside
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    for a, b, c, d in quads:
        faces.append(f"f {first + a} {first + b} {first + c}")
        faces.append(f"f {first + a} {first + c} {first + d}")
    return vertices, faces


def make_fixtures(root: Path) -> tuple[Fixtures, object]:
    """Make every fixture under ``root``; returns them and the open handle that keeps ``locked`` locked."""
    fx = Fixtures(root)
    work = root / "fixture_cwd"
    work.mkdir(parents=True)
    _fixture_run(["pushtorch.apps.simulate", *SIM_SMALL, "shard_size=2", f"hydra.run.dir={fx.sim}"], work, "simulate")
    shards = sorted((fx.sim / "pushes").glob("shard-*.json"))
    if len(shards) != 3 or not (fx.sim / "pushes" / "manifest.json").is_file():
        sys.stderr.write(f"fixture simulate: expected 3 shards and a manifest, found {[p.name for p in shards]}\n")
        raise SystemExit(3)
    _fixture_run(["pushtorch.apps.train", f"data={fx.sim}", f"hydra.run.dir={fx.train}", *TRAIN_SMALL], work, "train")
    if not fx.model.is_file():
        sys.stderr.write(f"fixture train: no {fx.model}\n")
        raise SystemExit(3)
    # a run with one shard's files gone (an interrupted or half-copied run), and one with a shard tampered with
    shutil.copytree(fx.sim, fx.sim_missing_shard)
    for suffix in (".json", ".npz"):
        (fx.sim_missing_shard / "pushes" / f"shard-000001{suffix}").unlink()
    shutil.copytree(fx.sim, fx.sim_tampered)
    shard = fx.sim_tampered / "pushes" / "shard-000001.npz"
    raw = bytearray(shard.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    shard.write_bytes(bytes(raw))
    # model files made bad
    good = fx.model.read_bytes()
    for path in (fx.model_flipped, fx.model_truncated, fx.model_junk):
        path.parent.mkdir(parents=True)
    flipped = bytearray(good)
    flipped[len(flipped) // 2] ^= 0x01
    fx.model_flipped.write_bytes(bytes(flipped))
    fx.model_truncated.write_bytes(good[: len(good) // 2])
    fx.model_junk.write_text("this is not a model, just some notes saved under the wrong name\n")
    # meshes
    fx.mesh_dir.mkdir()
    v1, f1 = _cube((0.0, 0.0, 0.05), 0.05, 1)
    v2, f2 = _cube((0.3, 0.0, 0.05), 0.05, 9)
    fx.mesh_two_cubes.write_text("# two disjoint cubes, 0.1 m, 0.2 m apart\n" + "\n".join(v1 + v2 + f1 + f2) + "\n")
    v, f = _cube((0.0, 0.0, 0.05), 0.05, 1)
    v[3] = "v nan 0.05 0.1"
    fx.mesh_nan.write_text("# a cube with one NaN vertex\n" + "\n".join(v + f) + "\n")
    v1, f1 = _cube((0.0, 0.0, 0.05), 0.05, 1)
    v2, f2 = _cube((0.15, 0.0, 0.05), 0.05, 9)
    fx.mesh_apart.write_text("# two 0.1 m cubes, 5 cm apart\n" + "\n".join(v1 + v2 + f1 + f2) + "\n")
    v, f = _cube((0.0, 0.0, 100.0), 100.0, 1)
    fx.mesh_mm.write_text("# a 0.2 m cube written in millimetres\n" + "\n".join(v + f) + "\n")
    fx.mesh_empty.write_bytes(b"")
    fx.mesh_garbage.write_text("hello, this is not a mesh\nv 1 2\nf 1 2 3 4 5\n")
    # folders and files
    fx.empty_dir.mkdir()
    fx.a_file.write_text("a regular file\n")
    fx.junk_results.mkdir()
    (fx.junk_results / "results.json").write_text("{not json")
    fx.min_results.mkdir()
    (fx.min_results / "results.json").write_text('{"experiment": "quickstart", "overrides": [], "records": []}\n')
    fx.locked.mkdir()
    handle = contextlib.ExitStack()  # the run folder's lock, held (with its heartbeat) for the whole battery
    handle.enter_context(lock_file(fx.locked / RUN_LOCK, wait=False))
    return fx, handle


# ---------------------------------------------------------------------------------------------------- running

def classify(code: int | None, stdout: str, stderr: str) -> str:
    if code is None:
        return "hang"
    if "Traceback" in stdout or "Traceback" in stderr:
        return "traceback"
    if code == 0:
        return "silent"
    if code == 2 and len([line for line in stderr.splitlines() if line.strip()]) == 1:
        return "clear error"
    return "traceback"


def run_case(case: Case, cwd: Path, timeout: float) -> Result:
    cwd.mkdir(parents=True)
    start = time.perf_counter()
    proc = subprocess.Popen([PYTHON, "-m", case.module, *case.args], cwd=cwd, env=_env(), text=True,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=timeout)
        code: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the case's own process group (its simulation workers too)
        except ProcessLookupError:
            pass
        stdout, stderr = proc.communicate()
        code = None
    seconds = time.perf_counter() - start
    # a run folder left behind (an empty output root such as runs/ is not one)
    made = sorted(str(p.relative_to(cwd)) for p in cwd.glob("*/*"))
    return Result(case, classify(code, stdout, stderr), code, stdout, stderr, seconds, made)


def _cell(text: str, limit: int = 140) -> str:
    text = text.strip()
    if len(text) > limit:
        text = text[: limit - 1] + "…"
    return text.replace("|", "\\|")


def report(results: list[Result], wall: float) -> None:
    print()
    print("| id | category | outcome | exit | first stderr line | folder made |")
    print("|---|---|---|---:|---|---|")
    for r in results:
        first = r.lines[0] if r.lines else ""
        code = "timeout" if r.code is None else str(r.code)
        made = ", ".join(f"{name}/" for name in r.made) or "no"
        print(f"| {r.case.id} | {r.case.category} | {r.outcome} | {code} | {_cell(first)} | {made} |")
    counts = {o: sum(r.outcome == o for r in results) for o in OUTCOMES}
    print()
    print("| outcome | cases |")
    print("|---|---:|")
    for outcome in OUTCOMES:
        print(f"| {outcome} | {counts[outcome]} |")
    print()
    print(f"{counts['clear error']} clear errors, {counts['traceback']} raw tracebacks, {counts['silent']} silent "
          f"results, {counts['hang']} hangs (of {len(results)} cases); "
          f"{sum(bool(r.made) for r in results)} left a folder in their working folder")
    if counts["traceback"]:
        python = sum(r.outcome == "traceback" and "Traceback" in r.stdout + r.stderr for r in results)
        print(f"of the {counts['traceback']} raw tracebacks, {python} print a Python traceback; the others exit "
              "with another status or print more than one stderr line")
    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs)")
    print(f"wall time: {wall:.1f} s")
    missing = [r for r in results if r.outcome == "clear error" and r.case.expect
               and r.case.expect.lower() not in r.stderr.lower()]
    if missing:
        print()
        print("Clear errors that do not mention what the case expected:")
        for r in missing:
            print(f"- {r.case.id}: expected {r.case.expect!r} in: {_cell(r.lines[0], 300)}")
    bad = [r for r in results if r.outcome != "clear error"]
    if bad:
        print()
        print("## Cases that are not clear errors (last 15 stderr lines each)")
        for r in bad:
            code = "timeout" if r.code is None else r.code
            print()
            print(f"### {r.case.id} ({r.outcome}, exit {code}, {r.seconds:.1f} s)")
            print(f"`python -m {r.case.module} {' '.join(r.case.args)}`")
            print("```")
            tail = r.stderr.rstrip("\n").splitlines()[-15:]
            print("\n".join(tail) if tail else "(stderr empty; last stdout lines:)\n"
                  + "\n".join(r.stdout.rstrip("\n").splitlines()[-15:]))
            print("```")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default=None, help="run only the cases whose id or category holds this text")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds per case before it is a hang")
    parser.add_argument("--workers", type=int, default=2, help="cases run at once")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (fixtures, case folders)")
    args = parser.parse_args(argv)

    def chosen(fx: Fixtures) -> list[Case]:
        return [c for c in cases(fx) if args.only is None or args.only in c.id or args.only in c.category]

    if args.list:
        for c in chosen(Fixtures(Path("<fixtures>"))):
            print(f"{c.id:32} {c.category:12} python -m {c.module} {' '.join(c.args)}")
        return 0
    start = time.perf_counter()
    root = Path(tempfile.mkdtemp(prefix="pushtorch-battery-"))
    handle = None
    try:
        print(f"fixtures in {root} ...", flush=True)
        fx, handle = make_fixtures(root)
        selected = chosen(fx)
        if not selected:
            print(f"no case matches --only {args.only!r}", file=sys.stderr)
            return 2
        ids = [c.id for c in selected]
        if len(set(ids)) != len(ids):
            raise SystemExit("duplicate case ids")
        print(f"fixtures ready ({time.perf_counter() - start:.1f} s); {len(selected)} cases, "
              f"{args.workers} at a time, timeout {args.timeout:g} s", flush=True)
        results: dict[str, Result] = {}
        with concurrent.futures.ThreadPoolExecutor(max_workers=args.workers) as pool:
            futures = {pool.submit(run_case, c, root / "cases" / c.id, args.timeout): c for c in selected}
            for k, future in enumerate(concurrent.futures.as_completed(futures), 1):
                r = future.result()
                results[r.case.id] = r
                print(f"[{k:3}/{len(selected)}] {r.case.id:32} {r.outcome:12} exit "
                      f"{'timeout' if r.code is None else r.code:>7}  {r.seconds:6.1f} s", flush=True)
        ordered = [results[c.id] for c in selected]
        report(ordered, time.perf_counter() - start)
        return 0 if all(r.outcome == "clear error" for r in ordered) else 1
    finally:
        if handle is not None:
            handle.close()
        if args.keep:
            print(f"kept {root}")
        else:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
