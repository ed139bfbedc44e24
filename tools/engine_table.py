"""pushtorch against physics_from_cloud with the ground truth in the peer's own engine and across the engine gap.

Paper, Biasing Transferable Push Manipulation Models (the friction-biasing protocol) and Future Work (a world
that is not the simulator). Reads two friction-biasing ``results.json``: one whose world and physics peers share
an engine (``--same``, e.g. the committed pybullet run) and one whose peers roll out in another engine than the
world (``--cross``, e.g. ``world=mujoco``). Per object it prints the congruent model's H_acc and displacement
error (cm) beside ``physics_from_cloud``'s (the body the observed cloud reconstructs, rolled out from the same
model's robot start with the condition's mean parameters), averaged over the three friction conditions, and who
wins (the lower H_acc). ``oracle_physics`` is not a peer and is not compared here.

    .venv/bin/python tools/engine_table.py --same docs/results/spread/friction_biasing/results.json \\
        --cross docs/results/mujoco/friction_biasing/results.json

The last line is ``pushtorch_wins_same=<k>/<n> pushtorch_wins_cross=<k>/<n>``.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def congruent(path: Path) -> tuple[dict[str, str], dict[tuple[str, str], tuple[float, float]]]:
    """The run's engines and ``{(object, method): (H_acc, linear cm)}`` of the congruent model, averaged over
    the conditions (displacement metric)."""
    data = json.loads(path.read_text())
    engines = {k: (data.get(k) or {}).get("engine", "pybullet") for k in ("world", "physics")}
    sums: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
    for r in data["records"]:
        if r.get("metric", "displacement") != "displacement" or r.get("task") != "prediction":
            continue
        if r["method"] not in ("pushtorch", "physics_from_cloud"):
            continue
        if str(r["model"]).split(":")[-1] != str(r["condition"]).split(":")[-1]:
            continue
        entry = sums[(r["object"], r["method"])]
        entry[0] += r["hacc_mean"]
        entry[1] += r["linear_cm"]
        entry[2] += 1
    return engines, {k: (v[0] / v[2], v[1] / v[2]) for k, v in sums.items() if v[2]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--same", type=Path, required=True, help="results.json, world and peers in one engine")
    parser.add_argument("--cross", type=Path, required=True, help="results.json, peers in another engine")
    args = parser.parse_args()
    (same_engines, same), (cross_engines, cross) = congruent(args.same), congruent(args.cross)
    objects = [o for o, m in same if m == "pushtorch" and (o, "physics_from_cloud") in same and
               (o, "pushtorch") in cross and (o, "physics_from_cloud") in cross]
    label = {"same": f"truth {same_engines['world']}, peer {same_engines['physics']}",
             "cross": f"truth {cross_engines['world']}, peer {cross_engines['physics']}"}
    print(f"| object | {label['same']}: pushtorch | physics_from_cloud | wins | {label['cross']}: pushtorch |"
          " physics_from_cloud | wins |")
    print("|---|---|---|---|---|---|---|")
    wins = {"same": 0, "cross": 0}
    for o in objects:
        cells = []
        for name, table in (("same", same), ("cross", cross)):
            ours, peer = table[(o, "pushtorch")], table[(o, "physics_from_cloud")]
            winner = "pushtorch" if ours[0] < peer[0] else "physics_from_cloud"
            wins[name] += winner == "pushtorch"
            cells += [f"{ours[0]:.4f} ({ours[1]:.2f} cm)", f"{peer[0]:.4f} ({peer[1]:.2f} cm)", winner]
        print(f"| {o} | " + " | ".join(cells) + " |")
    n = len(objects)
    print(f"pushtorch_wins_same={wins['same']}/{n} pushtorch_wins_cross={wins['cross']}/{n}")


if __name__ == "__main__":
    main()
