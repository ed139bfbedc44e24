"""Write the small push table shipped with the tests (``tests/data/lab_table``): the format a lab's pushes come in.

Paper, Experimental Setup (the paper's training pushes, here 12 per action of an object outside the catalogue).
A generated prism (``random_shape(21, "polygon")``, renamed ``lab_prism``) is pushed in pybullet at the paper's
default priors; the table keeps only what a tracker gives: the required columns, each push's cloud file (one
single-shot cloud shared by every row, since every push starts the object at the same place), the mesh, and
``mass`` / ``ground_friction`` (a lab that weighed its object and measured its friction). The validity flags
are left out, so reading it infers them (``pushtorch.sim.tables.infer_flags``).

    .venv/bin/python tools/make_lab_table.py [--out tests/data/lab_table]
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
from pathlib import Path

import pyarrow.parquet as pq

from pushtorch.objects.shapes import random_shape
from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes, run_plan
from pushtorch.sim.tables import POSES, export_run_table

KEEP = ("object_name", "action_index", "speed", "yaw_rate", "mass", "ground_friction", "cloud",
        *(f"{pose}_{axis}" for pose in POSES for axis in ("x", "y", "z", "qw", "qx", "qy", "qz")))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="tests/data/lab_table", help="the table's folder (replaced)")
    out = Path(parser.parse_args().out)
    obj = dataclasses.replace(random_shape(21, "polygon"), name="lab_prism")
    plan = plan_training_pushes(obj, make_actions(3), 12, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        run_plan(object_spec(obj), plan, Path(tmp) / "pushes", workers=1, progress=False)
        table_path = export_run_table(Path(tmp) / "pushes", obj, "p3dx", 4.0)
        table = pq.read_table(table_path)
        table = table.select(list(KEEP))  # metadata (robot, pusher, duration, meshes) is kept
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        pq.write_table(table, out / "pushes.parquet")
        shutil.copytree(table_path.parent / "meshes", out / "meshes")
        shutil.copytree(table_path.parent / "clouds", out / "clouds")
    print(f"{out}: {table.num_rows} pushes of {obj.name}, columns {', '.join(table.column_names)}")


if __name__ == "__main__":
    main()
