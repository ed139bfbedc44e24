"""The residual model conditioned on observed pushes against its own unconditioned predictions, from a run's
results.json (an online-adaptation part run with ``residual: true``).

Online adaptation scores every predictor on the same pushes at each k (observed pushes); a conditioned
predictor's record holds ``vs_k0``, the mean per-push H_acc difference to its own k = 0 and its paired standard
error. Per object and condition this prints ``pushtorch_residual``'s difference at the largest k, and then

* the gate: never worse than its own k = 0 by more than 2 paired SE, in every condition;
* the target: better than its own k = 0 by more than 1 paired SE in at least 2 conditions;

with ``online`` (the library of biased models, conditioned) beside it for reference. The run, for the
quickstart's online part under its four extreme conditions at the quick model's size::

    python -m pushtorch experiment=quickstart model.samples_per_action=60 \\
        '~experiment.parts.model_selection' '~experiment.parts.pose_estimation' \\
        '~experiment.parts.friction_biasing' '~experiment.parts.mass_biasing' \\
        'experiment.parts.online_adaptation.conditions={friction:[low,high],mass:[low,high]}' \\
        +experiment.parts.online_adaptation.residual=true hydra.run.dir=runs/online_residual
    .venv/bin/python tools/online_residual_gate.py runs/online_residual

The last line is ``gate=<0|1> never_worse=<n>/<conditions> better=<n>/<conditions>``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder holding results.json")
    args = parser.parse_args()
    records = [r for r in json.loads((args.run / "results.json").read_text())["records"] if r.get("task") == "online"]
    residual = [r for r in records if r["method"] == "pushtorch_residual" and "vs_k0" in r]
    if not residual:
        raise SystemExit(f"{args.run}: no conditioned pushtorch_residual records (run the online part with "
                         "residual=true and some k > 0)")
    k = max(r["observed"] for r in residual)
    online = {(r["object"], r["condition"]): r for r in records if r["method"] == "online" and r["observed"] == k}
    never_worse = better = 0
    rows = sorted((r for r in residual if r["observed"] == k), key=lambda r: (r["object"], r["condition"]))
    for r in rows:
        diff, se = r["vs_k0"]["difference"], r["vs_k0"]["se"]
        never_worse += diff <= 2 * se
        better += diff < -se
        other = online.get((r["object"], r["condition"]), {}).get("vs_k0", {})
        online_diff, online_se = other.get("difference", float("nan")), other.get("se", float("nan"))
        print(f"{r['object']} {r['condition']} k={k} n={r['n']}: residual H_acc {r['hacc_mean']:.4f}, "
              f"k={k} − k=0 {diff:+.4f} (paired SE {se:.4f}); online {online_diff:+.4f} (SE {online_se:.4f})")
    print(f"gate={int(never_worse == len(rows))} never_worse={never_worse}/{len(rows)} better={better}/{len(rows)}")


if __name__ == "__main__":
    main()
