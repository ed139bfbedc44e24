"""Reproduce the paper's four experiments at their full protocol, one run directory each, with wall times.

Paper, Experimental Results: model selection (50 conditions x 3 actions x 4 samples), pose estimation
(100 runs per object), friction and mass biasing (4 models x 3 conditions x 6 objects, 100 conditions x
3 actions x 3 samples, 24,000 training pushes over both), and online adaptation (the paper's future work, on the
biasing experiments' models, linked from their folders when they ran first), trained with the default placements
(``protocol=spread``) or the paper's single one (``--protocol paper``). Each experiment runs as
``python -m pushtorch experiment=<name> hydra.run.dir=<out>/<name> [overrides]``, so a killed run resumes
when this script is started again with the same ``--out`` (every step is cached in its run directory).

    .venv/bin/python tools/reproduce_paper.py --out runs/paper
    .venv/bin/python tools/reproduce_paper.py --out runs/paper_protocol --protocol paper
    .venv/bin/python tools/reproduce_paper.py --out runs/paper --only pose_estimation
    .venv/bin/python tools/reproduce_paper.py --out runs/paper_mujoco --world mujoco --only friction_biasing
    .venv/bin/python tools/reproduce_paper.py --out runs/scaled -- ++experiment.test_conditions=5

Overrides after ``--`` go to every experiment; ``++key=value`` sets a key even where an experiment does
not have it (pose estimation has no ``test_conditions``), ``key=value`` requires it everywhere.

Writes ``<out>/timings.json`` (wall seconds per experiment) and prints each experiment's summary.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

EXPERIMENTS = ("model_selection", "pose_estimation", "friction_biasing", "mass_biasing", "online_adaptation")
#: Experiments that reuse the models (and their training pushes) of earlier ones in the same ``--out``.
REUSES = {"online_adaptation": ("friction_biasing", "mass_biasing")}
ROOT = Path(__file__).resolve().parents[1]


def reproduce(out: Path, only: list[str], overrides: list[str],
              python: str = sys.executable) -> dict[str, float]:
    """Run the experiments in ``only`` in order; returns their wall times (s) and writes ``timings.json``.

    Raises:
        SystemExit: an unknown experiment name, or an experiment that fails (its exit status).
    """
    unknown = sorted(set(only) - set(EXPERIMENTS))
    if unknown:
        raise SystemExit(f"unknown experiment(s) {', '.join(unknown)}; choose from {', '.join(EXPERIMENTS)}")
    out.mkdir(parents=True, exist_ok=True)
    timings_path = out / "timings.json"
    timings = json.loads(timings_path.read_text()) if timings_path.is_file() else {}
    for name in only:
        for earlier in REUSES.get(name, ()):  # the same models, not trained twice: linked, never moved
            for kind in ("models", "data"):
                source = out / earlier / kind
                for path in sorted(source.rglob("*")) if source.is_dir() else []:
                    target = out / name / kind / path.relative_to(source)
                    if path.is_dir():
                        target.mkdir(parents=True, exist_ok=True)
                    elif not target.exists():
                        target.parent.mkdir(parents=True, exist_ok=True)
                        target.hardlink_to(path)
        command = [python, "-m", "pushtorch", f"experiment={name}", f"hydra.run.dir={out / name}", *overrides]
        print("$", " ".join(command), flush=True)
        start = time.perf_counter()
        result = subprocess.run(command, cwd=ROOT)
        if result.returncode != 0:
            raise SystemExit(result.returncode)
        timings[name] = round(time.perf_counter() - start, 1)
        timings_path.write_text(json.dumps(timings, indent=1))
        print(f"{name}: {timings[name] / 60:.1f} min", flush=True)
    return timings


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/paper"), help="base run directory")
    parser.add_argument("--only", default=",".join(EXPERIMENTS),
                        help=f"comma-separated subset of {','.join(EXPERIMENTS)}")
    parser.add_argument("--protocol", choices=("spread", "paper"), default="spread",
                        help="training placements (conf/protocol): spread (the default model) or paper (the "
                             "paper's single placement)")
    parser.add_argument("--world", choices=("pybullet", "mujoco"), default="pybullet",
                        help="conf/world: where training pushes and ground truth run (mujoco: the physics peers "
                             "stay in pybullet, across the gap)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every experiment (after --)")
    args = parser.parse_args(argv)
    timings = reproduce(args.out.resolve(), [s for s in args.only.split(",") if s],
                        [f"protocol={args.protocol}", f"world={args.world}", *args.overrides])
    print(json.dumps(timings, indent=1))


if __name__ == "__main__":
    main()
