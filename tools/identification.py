"""How much three observed pushes tell the online method about friction and mass, from runs' results.json.

For each run folder (a quickstart or an online-adaptation run): the world and physics engines, the seed, and per
object and condition of the online part, the library's posterior mean of μ (friction conditions) or of log m
(mass conditions) before any observed push (k = 0) and after the most (k = max), the truth's value, and whether
the distance to the truth at least halved (``identified``). Then the separability of adjacent mass conditions among
those run (docs/experiments.md: the gap between two conditions' mean outcomes over their pooled spread, from the
run's cached outcomes) and the count of runs in which the cube's friction:low posterior was identified.

    .venv/bin/python tools/identification.py runs/qs_seed0 runs/qs_seed1 ...

Each line ends ``identified=<0|1>``; the last line is ``friction_low_identified=<n>/<runs>``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

from pushtorch.experiments.online_adaptation import LEVELS, separability


def _value(record: dict, bias: str) -> float:
    return float(record["mu_mean"] if bias == "friction" else record["log_mass_mean"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders holding results.json")
    args = parser.parse_args()
    identified_low, counted = 0, 0
    for run in args.runs:
        results = json.loads((run / "results.json").read_text())
        seed = results.get("config", {}).get("seed")
        engines = f"world={results['world']['engine']} physics={results['physics']['engine']}"
        online = [r for r in results["records"] if r.get("task") == "online" and r["method"] == "online"]
        if not online:
            print(f"{run}: no online records")
            continue
        for obj in sorted({r["object"] for r in online}):
            for condition in sorted({r["condition"] for r in online if r["object"] == obj}):
                bias = condition.split(":")[0]
                rows = sorted((r for r in online if r["object"] == obj and r["condition"] == condition),
                              key=lambda r: r["observed"])
                first, last = rows[0], rows[-1]
                truth = first["mu_true"] if bias == "friction" else math.log(first["mass_true"])
                before, after = abs(_value(first, bias) - truth), abs(_value(last, bias) - truth)
                ok = after <= 0.5 * before
                name = "mu" if bias == "friction" else "log_m"
                print(f"{run.name} seed={seed} {engines} {obj} {condition}: {name} k={first['observed']} "
                      f"{_value(first, bias):.3f} k={last['observed']} {_value(last, bias):.3f} truth {truth:.3f} "
                      f"identified={int(ok)}")
                if obj == "cube" and condition == "friction:low":
                    counted += 1
                    identified_low += int(ok)
        for obj in sorted({r["object"] for r in online}):  # from the scored outcomes the run cached
            outcomes = {}
            for level in LEVELS:
                path = next(iter(sorted((run / "online").glob(f"*_{obj}_mass_{level}.json"))), None)
                if path is not None:
                    outcomes[level] = torch.tensor(json.loads(path.read_text())["outcomes"], dtype=torch.float64)
            present = [level for level in LEVELS if level in outcomes]
            for a, b in zip(present, present[1:], strict=False):
                value, gap_cm = separability(outcomes[a], outcomes[b])
                print(f"{run.name} seed={seed} {obj} mass {a}|{b}: separability {value:.2f} (mean gap {gap_cm:.2f} cm)")
    print(f"friction_low_identified={identified_low}/{counted}")


if __name__ == "__main__":
    main()
