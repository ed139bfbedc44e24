"""Sweeps a researcher can read: job folders named by what was swept, one run per folder, one tidy table.

Real runs only: a joblib sweep of two training priors at the tiny model's size, then
``python -m pushtorch.apps.collect`` on its folder, read back as CSV.
"""

from __future__ import annotations

import csv
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from pushtorch.apps.cli import _claimed, job_dir_name
from pushtorch.errors import PushtorchError


@pytest.fixture(scope="module")
def prior_sweep(tmp_path_factory) -> Path:
    """The README's sweep, as written but for its sizes: two friction priors, joblib, from outside the checkout."""
    cwd = tmp_path_factory.mktemp("sweep")
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch", "-m", "experiment=friction_biasing", "model.friction=low,high",
         "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "experiment.workers=1", "model=tiny",
         "experiment.objects=[cube]", "experiment.test_conditions=1", "experiment.truth_samples=1",
         "experiment.progress=false"],
        cwd=cwd, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    (sweep,) = (cwd / "runs" / "multirun").glob("*/*")
    return sweep


def test_sweep_jobs_are_named_by_the_swept_value(prior_sweep: Path):
    jobs = sorted(p.name for p in prior_sweep.iterdir() if p.is_dir())
    assert jobs == ["0_model.friction=low", "1_model.friction=high"]
    for job in jobs:
        assert (prior_sweep / job / "results.json").is_file()
        assert "name: pushtorch\n" in (prior_sweep / job / ".hydra" / "hydra.yaml").read_text()


def test_collect_writes_one_row_per_job_and_record_with_the_swept_value(prior_sweep: Path, tmp_path: Path):
    import json

    result = subprocess.run([sys.executable, "-m", "pushtorch.apps.collect", str(prior_sweep), "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    with open(tmp_path / "collected.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    expected = sum(len(json.loads((job / "results.json").read_text())["records"])
                   for job in prior_sweep.iterdir() if job.is_dir())
    assert len(rows) == expected > 0
    assert {r["model.friction"] for r in rows} == {"low", "high"}
    assert all(r["job"].endswith(f"model.friction={r['model.friction']}") for r in rows)
    assert all(r["model"] == f"friction:{r['model.friction']}" for r in rows)  # the record agrees with its job
    markdown = (tmp_path / "collected.md").read_text().splitlines()
    assert markdown[0].startswith("| job | experiment | model.friction | ") and "| override:model |" in markdown[0]
    assert len(markdown) == expected + 2 and {r["override:model"] for r in rows} == {"tiny"}
    assert (tmp_path / "collected_friction_biasing.png").stat().st_size > 5_000


def test_collect_refuses_a_folder_without_results(tmp_path: Path):
    result = subprocess.run([sys.executable, "-m", "pushtorch.apps.collect", str(tmp_path)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2
    assert "holds no results.json" in result.stderr and "Traceback" not in result.stderr


def test_job_folder_names_are_single_safe_names(tmp_path: Path):
    (tmp_path / "multirun.yaml").write_text(
        "hydra:\n  overrides:\n    task: [experiment=mass_biasing, 'object.path=a/b.stl,c/d.stl', seed=3]\n")
    name = job_dir_name(1, tmp_path, ["experiment=mass_biasing", "object.path=c/d.stl", "seed=3"])
    assert name == "1_object.path=c_d.stl"  # only the swept key, and no '/' to nest folders
    unswept = job_dir_name(0, tmp_path / "absent", ["seed=3", "experiment.workers=1", "x=" + "y" * 300])
    assert "experiment.workers" not in unswept and len(unswept) == 120
    assert unswept != job_dir_name(0, tmp_path / "absent", ["seed=3", "x=" + "y" * 299 + "z"])


def test_a_run_folder_is_used_by_one_live_process_at_a_time(tmp_path: Path):
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from pathlib import Path
            from pushtorch.apps.cli import _claimed
            with _claimed(Path({str(tmp_path)!r})):
                print("held", flush=True)
                time.sleep(60)
        """)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(PushtorchError, match="in use by pid"):
            with _claimed(tmp_path):
                pass
    finally:
        holder.kill()
        holder.wait()
    with _claimed(tmp_path):  # the lock went with the process: a killed run's folder can be resumed
        pass
