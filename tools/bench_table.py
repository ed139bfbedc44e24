"""Training from a push table against training from simulated records of the same size: time and peak memory.

Paper, Experimental Setup (the paper protocol's 189,000 simulated pushes; a lab's log can be as long). A cube run
of ``--base`` pushes is simulated once; its records are tiled to ``--pushes`` (each copy's push indices shifted,
every value otherwise repeated, as ``tools/bench_scale.py`` tiles them) and written as a push table whose rows
all share one cloud file, with the cube's mesh. Then two fresh processes each report their peak memory (max RSS)
and the seconds from the start of reading to the end of ``train_push_model``: one loads the run and tiles it
(the reference: training from simulated records), the other reads and checks the table
(``pushtorch.read_push_table``) and trains on the object its mesh builds. Targets: ``table_peak_mb <= 2000`` and
``table_over_records <= 1.5``.

    .venv/bin/python tools/bench_table.py [--pushes 100000] [--base 3000] [--table-only]

The last line is ``table_peak_mb=<..> records_peak_mb=<..> table_s=<..> records_s=<..> table_over_records=<..>``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from bench_predict import cpu_name  # tools/ is on sys.path when a tool runs as a script

from pushtorch.objects import load_object
from pushtorch.sim import Normal, load_records, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.records import PushRecords
from pushtorch.sim.tables import export_run_table, write_push_table

_TILE = """
from dataclasses import replace
from pushtorch.sim.records import PushRecords
def tiled(one, pushes):
    copies = -(-pushes // len(one))
    records = PushRecords.cat([replace(one, index=one.index + k * len(one)) for k in range(copies)])
    return records.take(torch.arange(pushes))
"""

_RECORDS = """
from pushtorch.objects import load_object
from pushtorch.sim import load_records
records = tiled(load_records({base!r}, trajectories=False), {pushes})
obj = load_object("cube")
"""

_TABLE = """
from pushtorch import make_actions, read_push_table
table = read_push_table({table!r}, make_actions(3), 4.0)
records, obj = table.records, table.object("cube")
"""


def _child(body: str) -> tuple[float, float]:
    script = ("import resource, time, torch\n" + _TILE + "started = time.perf_counter()\n" + body
              + "from pushtorch.models.training import train_push_model\n"
              + "train_push_model(obj, records, generator=0)\n"
              + "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, time.perf_counter() - started)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=6 * 3600)
    if result.returncode != 0:
        raise SystemExit(f"training failed: {result.stderr[-2000:]}")
    peak, seconds = (float(v) for v in result.stdout.strip().splitlines()[-1].split())
    return peak, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pushes", type=int, default=100_000, help="rows of the table (default 100000)")
    parser.add_argument("--base", type=int, default=3000, help="pushes simulated and tiled (default 3000)")
    parser.add_argument("--table-only", action="store_true",
                        help="only the table's run (its peak and time; the reference's figures are nan)")
    args = parser.parse_args()
    print(f"CPU: {cpu_name()} ({os.cpu_count()} logical CPUs); {args.pushes} pushes tiled from {args.base}")
    cube = load_object("cube")
    with tempfile.TemporaryDirectory(prefix="pushtorch-table-") as tmp:
        root = Path(tmp)
        plan = plan_training_pushes(cube, make_actions(3), max(1, args.base // 3), Normal(0.5, 0.025),
                                    Normal(0.3, 0.05), seed=1)
        run_plan(object_spec(cube), plan, root / "base", progress=False)
        export_run_table(root / "base", cube, "p3dx", 4.0)  # the mesh and the shared cloud
        one = load_records(root / "base", dtype=torch.float64, trajectories=False)
        copies = -(-args.pushes // len(one))
        records = PushRecords.cat([dataclasses.replace(one, index=one.index + k * len(one)) for k in range(copies)])
        records = records.take(torch.arange(args.pushes))
        table = write_push_table(root / "base" / "big.parquet", records, "p3dx", 4.0, {"cube": "meshes/cube.ply"},
                                 ["clouds/start_0.npz"] * len(records))
        print(f"table: {table.stat().st_size / 1e6:.1f} MB on disk", flush=True)
        records_peak = records_s = float("nan")
        if not args.table_only:
            records_peak, records_s = _child(_RECORDS.format(base=str(root / "base"), pushes=args.pushes))
            print(f"from simulated records: {records_s:.1f} s, peak {records_peak:.0f} MB", flush=True)
        table_peak, table_s = _child(_TABLE.format(table=str(table)))
        print(f"from the table: {table_s:.1f} s, peak {table_peak:.0f} MB", flush=True)
    print(f"table_peak_mb={table_peak:.0f} records_peak_mb={records_peak:.0f} table_s={table_s:.1f} "
          f"records_s={records_s:.1f} table_over_records={table_s / records_s:.2f}")


if __name__ == "__main__":
    main()
