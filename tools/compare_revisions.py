"""Do two git revisions of this repository give bit-identical results? Proof that a refactor changed nothing.

Each revision is checked out into its own temporary ``git worktree`` (the caller's working tree, index and
branch are untouched; the worktrees are removed at the end) and run with this same interpreter, importing
that worktree's ``pushtorch`` and configs alone:

* ``PYTHONPATH`` is the worktree, and the processes run in it (``python -m`` puts the current folder first);
* the editable install of the checkout in ``.venv`` is switched off in every process of the run (a
  ``sitecustomize`` on ``PYTHONPATH`` drops its import hook), since that hook would otherwise supply
  ``pushtorch.conf`` (the package-dir mapping of ``pyproject.toml``: ``conf/``) and any module the revision
  lacks from the caller's checkout, uncommitted edits included;
* each such mapping is recreated inside the worktree as a symlink (``pushtorch/conf -> ../conf``), as the
  wheel lays it out, and a probe process checks where ``pushtorch`` and ``pushtorch.conf`` come from.

In each revision it produces

1. the quickstart's ``results.json`` (``python -m pushtorch`` with the run folder given, progress bars off,
   ``PYTHONHASHSEED=0``);
2. a small cube model (pybullet pushes per action, ``--pushes-per-action``, small settings) saved to a file,
   and
3. predictions with it: a few conditions by ``predict`` with ``method="fast"`` and ``"dense"`` and by
   ``predict_many`` batched; final poses, annealed log-probabilities, candidates, robot starts, and each
   density's ``log_prob`` at the training pushes' outcomes moved to the condition's start, around the fast
   prediction of the condition and around its own mode, saved to an ``.npz``.

Items 2 and 3 come from one driver script, written to the output folder and run by both revisions. It uses
only the public API (``load_object``, ``plan_training_pushes``, ``run_plan``, ``load_records``,
``train_push_model``, ``capture_partial_cloud``, ``predict``, ``predict_many`` …), found on ``pushtorch``
or in the modules that have held them, and it fails if any ``pushtorch`` module it loaded lies outside its
worktree.

Then it compares, bit for bit: ``results.json``'s ``records`` (run metadata such as the config, the engines it
names, overrides and wall time is not compared) and ``model_bandwidths``; the model files' arrays and their
headers (less the per-array digests); the predictions' arrays. One line per item, ``identical`` or
``DIFFERENT: <where, max abs diff>``, then ``identical=<0|1> records=<n> model_arrays=<n> predictions=<n>``.
Exit status 0: identical; 1: different; 2: a revision could not be checked out or run (its log is named).

    .venv/bin/python tools/compare_revisions.py REV_A REV_B [--out runs/compare] [--pushes-per-action 30]
        [--conditions 4] [--no-quickstart]

The output folder keeps each revision's run (``A/``, ``B/``: the quickstart's run folder, model, predictions,
logs); a rerun replaces them. The revisions run one after the other; on 2 cores shared with other work each
quickstart took 12-23 minutes and each driver run under 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

#: results.json keys that describe the run rather than its results (never compared).
RUN_METADATA = ("experiment", "world", "physics", "config", "overrides", "wall_s")
#: record keys that would carry run metadata if a revision added them (none do today): never compared.
RECORD_METADATA = frozenset({"wall_s", "seconds", "time", "time_s", "timestamp", "date", "started", "finished",
                             "host", "hostname", "path", "run_dir", "version", "pushtorch_version"})
#: model-file header fields not compared: the per-array digests (the arrays are compared themselves).
HEADER_IGNORED = frozenset({"sha256"})
#: header fields that would carry paths or times if a format added them: never compared.
HEADER_METADATA = frozenset({"path", "source", "created", "saved", "time", "timestamp", "host", "hostname"})
#: written to the output folder: marks it as this tool's, so a rerun may replace its contents.
MARKER = ".compare_revisions"

SITECUSTOMIZE = '''"""Written by tools/compare_revisions.py: imports come from the revision's worktree alone.

The editable install of the caller's checkout would supply pushtorch.conf and any module the revision lacks
from that checkout; its import hook is dropped from every process of the run."""
import sys

sys.meta_path[:] = [f for f in sys.meta_path if not getattr(f, "__module__", "").startswith("__editable___pushtorch")]
sys.path[:] = [p for p in sys.path if not (isinstance(p, str) and p.startswith("__editable__.pushtorch"))]
'''

PROBE = """
import json, pushtorch, pushtorch.conf
print(json.dumps({"pushtorch": pushtorch.__file__, "conf": pushtorch.conf.__file__}))
"""

DRIVER = r'''"""Written by tools/compare_revisions.py and run by each revision: train a small model, predict, save.

    python driver.py OUT_DIR WORKTREE PUSHES_PER_ACTION CONDITIONS
"""
import importlib
import json
import math
import os
import sys
import time
import types
from dataclasses import fields
from pathlib import Path

import numpy as np
import torch

OUT, ROOT = Path(sys.argv[1]), os.path.realpath(sys.argv[2])
PER_ACTION, CONDITIONS = int(sys.argv[3]), int(sys.argv[4])
SETTINGS = dict(voxel_size=0.008, feature_radius=0.02, query_kernels=400, anneal_candidates=60, anneal_steps=20,
                environment_samples=20, environment_kernels=400, manipulator_kernels=60)


def api(name, *modules):
    """``name`` from ``pushtorch`` or the first of ``modules`` that has it (modules move between revisions)."""
    for where in ("pushtorch", *modules):
        try:
            value = getattr(importlib.import_module(where), name)
        except (ImportError, AttributeError):
            continue
        if not isinstance(value, types.ModuleType):
            return value
    raise ImportError(f"{name} is in none of pushtorch, {', '.join(modules)}")


load_object = api("load_object", "pushtorch.objects")
make_actions = api("make_actions", "pushtorch.sim.push")
Uniform = api("Uniform", "pushtorch.sim.priors")
plan_training_pushes = api("plan_training_pushes", "pushtorch.sim.plan")
object_spec = api("object_spec", "pushtorch.sim.settings", "pushtorch.sim.world")
run_plan = api("run_plan", "pushtorch.sim.runner")
load_records = api("load_records", "pushtorch.sim.records")
ModelSettings = api("ModelSettings", "pushtorch.models.library", "pushtorch.models.settings")
train_push_model = api("train_push_model", "pushtorch.models.library", "pushtorch.models")
load_model = api("load_model", "pushtorch.models.library", "pushtorch.models")
capture_partial_cloud = api("capture_partial_cloud", "pushtorch.perception")
predict = api("predict", "pushtorch.predict", "pushtorch.prediction")
predict_many = api("predict_many", "pushtorch.predict", "pushtorch.prediction")

seconds = {}
start = time.perf_counter()
obj = load_object("cube")
plan = plan_training_pushes(obj, make_actions(3, (-10.0, 10.0), 0.1), PER_ACTION, Uniform(0.1, 1.0),
                            Uniform(0.15, 0.35), seed=3)
run_plan(object_spec(obj), plan, OUT / "pushes", workers=1, shard_size=50, progress=False)
records = load_records(OUT / "pushes")
seconds["simulate"] = time.perf_counter() - start

start = time.perf_counter()
known = {f.name for f in fields(ModelSettings)}
settings = ModelSettings(**{k: v for k, v in SETTINGS.items() if k in known})
model = train_push_model(obj, records, settings, generator=0)
model_path = model.save(OUT / "model.npz")
model = load_model(model_path)
seconds["train"] = time.perf_counter() - start

arrays, missing = {}, []


def put(key, value, *path):
    """``arrays[key]`` = ``value.<path>`` as numpy; a missing attribute is listed (its key is then absent)."""
    try:
        for name in path:
            value = getattr(value, name)
    except AttributeError:
        missing.append(key)
        return
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    arrays[key] = np.asarray(value)


def yaw_quaternion(angle):
    return torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)], dtype=torch.float64)


def quaternion_product(a, b):
    w1, x1, y1, z1 = a.unbind(-1)
    w2, x2, y2, z2 = b.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


OUTCOMES = torch.cat([records.object_final.p, records.object_final.q], -1).double()[::3]


def outcomes_at(x, y, yaw):
    """The training pushes' final poses (every third) as if pushed from the rest pose at (x, y, yaw): the
    same query poses in every revision, where the model's kernels are."""
    c, s = math.cos(yaw), math.sin(yaw)
    p = OUTCOMES[:, :3]
    p = torch.stack([c * p[:, 0] - s * p[:, 1] + x, s * p[:, 0] + c * p[:, 1] + y, p[:, 2]], -1)
    return torch.cat([p, quaternion_product(yaw_quaternion(yaw).expand(len(p), 4), OUTCOMES[:, 3:])], -1)


SHIFTS = [(0.0, 0.0, 0.0), (0.002, 0.0, 0.0), (-0.005, 0.0, 0.0), (0.0, 0.002, 0.0), (0.0, -0.005, 0.0),
          (0.0, 0.0, 0.02), (0.0, 0.0, -0.05), (0.003, -0.003, 0.03)]


def near(mode):
    """Poses around ``mode`` (7,): shifted in x, y and turned about the vertical."""
    mode = mode.double().reshape(7)
    out = []
    for dx, dy, dyaw in SHIFTS:
        p = mode[:3] + torch.tensor([dx, dy, 0.0], dtype=torch.float64)
        out.append(torch.cat([p, quaternion_product(yaw_quaternion(dyaw), mode[3:])]))
    return torch.stack(out)


put("pushes.object_final_p", records, "object_final", "p")
put("pushes.object_final_q", records, "object_final", "q")
clouds, STARTS = [], [(0.02 * k, -0.01 * k, 0.35 * k) for k in range(CONDITIONS)]
for k in range(CONDITIONS):
    pose = obj.resting_pose(*STARTS[k])
    clouds.append(capture_partial_cloud(obj, pose, generator=torch.Generator().manual_seed(k)))
actions = torch.stack([model.actions[k % len(model.actions)] for k in range(CONDITIONS)])

runs = {}
for method in ("fast", "dense"):
    start = time.perf_counter()
    runs[method] = [predict(model, cloud, actions[k], generator=torch.Generator().manual_seed(100 + k),
                            method=method) for k, cloud in enumerate(clouds)]
    seconds[method] = time.perf_counter() - start
start = time.perf_counter()
runs["batched"] = predict_many(model, clouds, actions, seed=200, method="fast", batch_size=CONDITIONS)
seconds["batched"] = time.perf_counter() - start

start = time.perf_counter()
for name, predictions in runs.items():
    for k, prediction in enumerate(predictions):
        key = f"{name}.{k}."
        put(key + "final_p", prediction, "final_pose", "p")
        put(key + "final_q", prediction, "final_pose", "q")
        put(key + "log_prob", prediction, "log_prob")
        put(key + "candidates_p", prediction, "candidates", "p")
        put(key + "candidates_q", prediction, "candidates", "q")
        put(key + "candidate_log_prob", prediction, "candidate_log_prob")
        put(key + "robot_start_p", prediction, "condition", "robot_start", "p")
        put(key + "robot_start_q", prediction, "condition", "robot_start", "q")
        # the density at the outcomes moved to the start (mostly beyond the kernels' cut-offs: -inf), around
        # the fast prediction of this condition (the same poses for every method) and around its own mode
        density = prediction.density
        queries = [outcomes_at(*STARTS[k]), near(runs["fast"][k].density.mode), near(density.mode)]
        values = density.log_prob(torch.cat(queries).to(density.mode.dtype))
        for part, value in zip(("outcomes", "near_fast", "near_mode"), values.split([len(q) for q in queries])):
            put(f"{key}density_{part}", value)
np.savez(OUT / "predictions.npz", **arrays)
seconds["densities"] = time.perf_counter() - start

outside = []
for name, module in list(sys.modules.items()):
    if name == "pushtorch" or name.startswith("pushtorch."):
        places = [getattr(module, "__file__", None)] + list(getattr(module, "__path__", None) or [])
        outside += [f"{name}: {p}" for p in places
                    if p and os.path.isabs(p) and not os.path.realpath(p).startswith(ROOT + os.sep)]
pushtorch = sys.modules["pushtorch"]
(OUT / "driver.json").write_text(json.dumps(
    {"pushtorch": pushtorch.__file__, "outside_worktree": outside, "missing": missing,
     "settings_dropped": sorted(set(SETTINGS) - known), "seconds": seconds}, indent=1))
if outside:
    sys.exit("pushtorch modules loaded from outside the worktree: " + "; ".join(outside))
print(json.dumps({"arrays": len(arrays), "missing": missing, "seconds": {k: round(v, 1) for k, v in seconds.items()}}))
'''


class RunFailed(Exception):
    """A revision could not be checked out or run."""


def git(repo: Path, *args: str) -> str:
    done = subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True)
    if done.returncode != 0:
        raise RunFailed(f"git {' '.join(args)}: {done.stderr.strip()}")
    return done.stdout.strip()


def link_package_dirs(worktree: Path) -> list[str]:
    """Symlink each ``[tool.setuptools.package-dir]`` mapping of the revision (``"pushtorch.conf" = "conf"``)
    into its package folder, as the wheel lays it out, so ``PYTHONPATH`` alone finds it."""
    pyproject = worktree / "pyproject.toml"
    if not pyproject.exists():
        return []
    mapping = tomllib.loads(pyproject.read_text()).get("tool", {}).get("setuptools", {}).get("package-dir", {})
    linked = []
    for package, folder in mapping.items():
        if not package:  # "" = "src": the packages' root, which PYTHONPATH must then name
            raise RunFailed(f"{pyproject}: package-dir maps the root to {folder!r}; not supported")
        place = worktree.joinpath(*package.split("."))
        if place.exists() or not (worktree / folder).is_dir():
            continue
        place.symlink_to(os.path.relpath(worktree / folder, place.parent), target_is_directory=True)
        linked.append(f"{package} -> {folder}")
    return linked


def run_logged(command: list[str], cwd: Path, env: dict[str, str], log: Path, what: str) -> float:
    start = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run(command, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-15:])
        raise RunFailed(f"{what} exited with status {done.returncode} (log: {log}):\n{tail}")
    return time.perf_counter() - start


def run_revision(label: str, worktree: Path, shim: Path, out: Path, driver: Path, args) -> dict[str, float]:
    """Run the quickstart and the driver in ``worktree``; outputs in ``out``."""
    env = dict(os.environ)
    env.update(PYTHONPATH=f"{worktree}{os.pathsep}{shim}", PYTHONHASHSEED="0", TQDM_DISABLE="1")
    env.pop("PYTHONSTARTUP", None)
    linked = link_package_dirs(worktree)
    probe = subprocess.run([sys.executable, "-c", PROBE], cwd=worktree, env=env, capture_output=True, text=True)
    if probe.returncode != 0:
        raise RunFailed(f"[{label}] importing pushtorch failed:\n{probe.stderr.strip()}")
    found = json.loads(probe.stdout.strip().splitlines()[-1])
    for what, place in found.items():
        if not os.path.realpath(place).startswith(f"{os.path.realpath(worktree)}{os.sep}"):
            raise RunFailed(f"[{label}] {what} comes from {place}, not from the worktree {worktree}")
    print(f"[{label}] pushtorch: {found['pushtorch']}; pushtorch.conf: {found['conf']}"
          + (f" (linked {', '.join(linked)})" if linked else ""), flush=True)
    seconds: dict[str, float] = {}
    if not args.no_quickstart:
        seconds["quickstart"] = run_logged(
            [sys.executable, "-m", "pushtorch", f"hydra.run.dir={out / 'quickstart'}", "experiment.progress=false"],
            worktree, env, out / "quickstart.log", f"[{label}] the quickstart")
        print(f"[{label}] quickstart: {seconds['quickstart']:.0f} s", flush=True)
    seconds["driver"] = run_logged(
        [sys.executable, str(driver), str(out), str(worktree), str(args.pushes_per_action), str(args.conditions)],
        worktree, env, out / "driver.log", f"[{label}] the driver")
    print(f"[{label}] model and predictions: {seconds['driver']:.0f} s", flush=True)
    return seconds


# --- comparison ------------------------------------------------------------------------------------------


def _abs_diff(a: Any, b: Any) -> float:
    """|a - b| for two numbers (inf where exactly one is NaN or the infinities differ), else NaN."""
    if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, int | float) or not isinstance(b, int | float):
        return math.nan
    if math.isnan(a) or math.isnan(b):
        return 0.0 if math.isnan(a) and math.isnan(b) else math.inf
    if a == b:
        return 0.0
    return math.inf if math.isinf(a) or math.isinf(b) else abs(a - b)


def same_value(a: Any, b: Any) -> bool:
    """Equal, floats bit for bit (so 0.0 and -0.0 differ, NaN equals NaN of the same bits)."""
    if isinstance(a, float) and isinstance(b, float):
        return struct.pack("<d", a) == struct.pack("<d", b)
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_value(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def _record_name(record: dict) -> str:
    return " ".join(f"{k}={record[k]}" for k in ("task", "object", "method", "model", "condition", "metric")
                    if record.get(k) is not None)


def compare_records(a: list[dict], b: list[dict]) -> str:
    """``identical`` or the first differing record and key, how many differ and the largest difference."""
    if len(a) != len(b):
        return f"DIFFERENT: {len(a)} records against {len(b)}"
    first, differing, largest = None, 0, 0.0
    for i, (ra, rb) in enumerate(zip(a, b, strict=True)):
        keys = sorted((set(ra) | set(rb)) - RECORD_METADATA)
        bad = [k for k in keys if k not in ra or k not in rb or not same_value(ra[k], rb[k])]
        if not bad:
            continue
        differing += 1
        for k in bad:
            d = _abs_diff(ra.get(k), rb.get(k))
            largest = max(largest, d) if not math.isnan(d) else largest
        if first is None:
            k = bad[0]
            first = (f"record {i} ({_record_name(ra)}) key {k}: {ra.get(k, '<absent>')!r} vs "
                     f"{rb.get(k, '<absent>')!r}" + (f", abs diff {_abs_diff(ra[k], rb[k]):.3g}"
                                                      if k in ra and k in rb and not math.isnan(
                                                          _abs_diff(ra[k], rb[k])) else ""))
    if first is None:
        return "identical"
    return f"DIFFERENT: {differing} of {len(a)} records differ, first {first}; max abs diff {largest:.3g}"


def _array_diff(a: np.ndarray, b: np.ndarray) -> float:
    """The largest |a - b| of two same-shape numeric arrays (NaN against NaN: 0; a lone NaN or inf: inf)."""
    if a.dtype.kind not in "biuf" or b.dtype.kind not in "biuf":
        return math.nan
    x, y = a.astype(np.float64), b.astype(np.float64)
    both_nan = np.isnan(x) & np.isnan(y)
    with np.errstate(invalid="ignore", over="ignore"):
        d = np.where((x == y) | both_nan, 0.0, np.abs(x - y))
    d = np.where(np.isnan(d), np.inf, d)
    return float(d.max()) if d.size else 0.0


def compare_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> str:
    """``identical`` (same names, dtypes, shapes and bytes) or which arrays differ and by how much."""
    only = sorted(set(a) ^ set(b))
    if only:
        return "DIFFERENT: arrays in one only: " + ", ".join(
            f"{k} ({'A' if k in a else 'B'})" for k in only[:8]) + (" …" if len(only) > 8 else "")
    bad: list[tuple[str, str, float]] = []
    for k in sorted(a):
        x, y = a[k], b[k]
        if x.dtype != y.dtype or x.shape != y.shape:
            bad.append((k, f"{x.dtype}{list(x.shape)} vs {y.dtype}{list(y.shape)}", math.inf))
        elif x.tobytes() != y.tobytes():
            d = _array_diff(x, y)
            bad.append((k, f"max abs diff {d:.3g}" if not math.isnan(d) else "non-numeric", d))
    if not bad:
        return "identical"
    worst = max(bad, key=lambda item: -1.0 if math.isnan(item[2]) else item[2])
    return (f"DIFFERENT: {len(bad)} of {len(a)} arrays differ, first {bad[0][0]} ({bad[0][1]}); "
            f"largest {worst[0]} ({worst[1]})")


def load_results(path: Path) -> dict[str, Any]:
    payload = json.loads(path.read_text())
    return {k: v for k, v in payload.items() if k not in RUN_METADATA}


def load_model_file(path: Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """A model file's header (less digests, paths and times) and its arrays."""
    with np.load(path, allow_pickle=False) as archive:
        arrays = {k: archive[k] for k in archive.files}
    header: dict[str, Any] = {}
    if "__header__" in arrays:
        header = json.loads(arrays.pop("__header__").tobytes().decode())
        header = {k: v for k, v in header.items() if k not in HEADER_IGNORED | HEADER_METADATA}
    return header, arrays


def compare_headers(a: dict[str, Any], b: dict[str, Any]) -> str:
    bad = sorted(k for k in set(a) | set(b) if k not in a or k not in b or not same_value(a[k], b[k]))
    if not bad:
        return "identical"
    k = bad[0]
    return f"DIFFERENT: fields {', '.join(bad)}; first {k}: {a.get(k, '<absent>')!r} vs {b.get(k, '<absent>')!r}"


def compare(out_a: Path, out_b: Path, with_quickstart: bool) -> tuple[bool, dict[str, int]]:
    """Print one line per item; return whether all are identical and how many of each were compared."""
    lines: list[tuple[str, str]] = []
    counts = {"records": 0, "model_arrays": 0, "predictions": 0}
    if with_quickstart:
        ra, rb = (load_results(out / "quickstart" / "results.json") for out in (out_a, out_b))
        counts["records"] = len(ra.get("records", []))
        lines.append((f"results.json records ({counts['records']})",
                      compare_records(ra.get("records", []), rb.get("records", []))))
        rest = sorted((set(ra) | set(rb)) - {"records"})
        for key in rest:
            lines.append((f"results.json {key}", "identical" if key in ra and key in rb and same_value(ra[key], rb[key])
                          else "DIFFERENT: " + ("absent in " + ("A" if key not in ra else "B")
                                                if key not in ra or key not in rb else "values differ")))
    ha, ma = load_model_file(out_a / "model.npz")
    hb, mb = load_model_file(out_b / "model.npz")
    counts["model_arrays"] = len(ma)
    lines.append(("model header", compare_headers(ha, hb)))
    lines.append((f"model arrays ({len(ma)})", compare_arrays(ma, mb)))
    with np.load(out_a / "predictions.npz") as pa, np.load(out_b / "predictions.npz") as pb:
        qa, qb = {k: pa[k] for k in pa.files}, {k: pb[k] for k in pb.files}
    counts["predictions"] = len(qa)
    lines.append((f"predictions ({len(qa)})", compare_arrays(qa, qb)))
    for name, verdict in lines:
        print(f"{name}: {verdict}")
    return all(verdict == "identical" for _, verdict in lines), counts


# --- main --------------------------------------------------------------------------------------------------


def prepare_out(out: Path) -> None:
    """Create ``out``, or empty this tool's earlier run in it (refusing a non-empty folder not its own)."""
    if out.exists() and any(out.iterdir()) and not (out / MARKER).exists():
        raise RunFailed(f"{out} is not empty and not an earlier output of this tool; choose another --out")
    for name in ("A", "B"):
        shutil.rmtree(out / name, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("output folder of tools/compare_revisions.py\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rev_a")
    parser.add_argument("rev_b")
    parser.add_argument("--out", type=Path, default=Path("runs/compare"), help="output folder (default: %(default)s)")
    parser.add_argument("--pushes-per-action", type=int, default=30, help="the driver's training pushes per action")
    parser.add_argument("--conditions", type=int, default=4, help="conditions the driver predicts per method")
    parser.add_argument("--no-quickstart", action="store_true", help="only the model and predictions")
    args = parser.parse_args(argv)

    repo = Path(git(Path(__file__).resolve().parent, "rev-parse", "--show-toplevel"))
    out = args.out.resolve()
    tmp = Path(tempfile.mkdtemp(prefix="compare_revisions_"))
    worktrees: list[Path] = []
    start = time.perf_counter()
    try:
        prepare_out(out)
        driver = out / "driver.py"
        driver.write_text(DRIVER)
        shim = tmp / "shim"
        shim.mkdir()
        (shim / "sitecustomize.py").write_text(SITECUSTOMIZE)
        # both resolved before anything runs: a commit made meanwhile must not move HEAD between the two
        commits = [git(repo, "rev-parse", "--verify", f"{rev}^{{commit}}") for rev in (args.rev_a, args.rev_b)]
        seconds = {}
        for label, rev, commit in zip(("A", "B"), (args.rev_a, args.rev_b), commits, strict=True):
            worktree = tmp / label
            git(repo, "worktree", "add", "--detach", str(worktree), commit)
            worktrees.append(worktree)
            print(f"[{label}] {rev} = {commit[:12]} {git(repo, 'log', '-1', '--format=%s', commit)[:80]}", flush=True)
            (out / label).mkdir()
            seconds[label] = run_revision(label, worktree, shim, out / label, driver, args)
        same, counts = compare(out / "A", out / "B", not args.no_quickstart)
    except RunFailed as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        for worktree in worktrees:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=repo, capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"wall time {time.perf_counter() - start:.0f} s ("
          + "; ".join(f"{k}: " + ", ".join(f"{s} {v:.0f} s" for s, v in t.items()) for k, t in seconds.items())
          + f"); outputs in {out}")
    print(f"identical={int(same)} records={counts['records']} model_arrays={counts['model_arrays']} "
          f"predictions={counts['predictions']}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
