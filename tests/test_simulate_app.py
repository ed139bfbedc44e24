"""The Hydra simulation app: config composition for every group, launchers, and a real tiny run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pushtorch.apps.cli import job_dir_name
from pushtorch.apps.simulate import simulate_from_config
from pushtorch.errors import InvalidParameterError, PushtorchError
from pushtorch.objects import catalogue_names
from pushtorch.sim import SimSettings, prior_from_config
from pushtorch.sim.records import load_records

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


def _compose(overrides: list[str], hydra_config: bool = False):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        return compose("simulate", overrides=overrides, return_hydra_config=hydra_config)


def test_defaults_are_the_papers_experiment_settings():
    cfg = _compose([])
    assert cfg.object.name == "cube"
    actions = cfg.actions
    assert (actions.count, list(actions.angle_range_deg), actions.speed, actions.duration) == (
        3, [-10.0, 10.0], 0.1, 4.0)
    assert cfg.samples_per_action == 500
    assert (cfg.mass.mean, cfg.mass.std, cfg.friction.mean, cfg.friction.std) == (0.5, 0.025, 0.3, 0.05)
    assert SimSettings(**OmegaConf.to_container(cfg.sim)) == SimSettings()


def test_one_object_config_per_catalogue_name_plus_mesh():
    stems = {p.stem for p in (CONF / "object").glob("*.yaml")}
    assert stems == set(catalogue_names()) | {"mesh"}
    for name in catalogue_names():
        assert _compose([f"object={name}"]).object.name == name
    mesh = _compose(["object=mesh", "object.path=/tmp/part.stl", "object.scale=0.001"]).object
    assert (mesh.name, mesh.path, mesh.scale) == ("mesh", "/tmp/part.stl", 0.001)


@pytest.mark.parametrize("group", ["friction", "mass"])
def test_every_prior_option_composes_into_a_prior(group):
    options = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
    assert {"general", "low", "medium", "high", "fixed", "paper_default"} <= set(options)
    for option in options:
        prior = prior_from_config(OmegaConf.to_container(_compose([f"{group}={option}"])[group]))
        assert prior.mean > 0


def test_run_and_sweep_directories_name_the_priors():
    cfg = _compose(["friction=low", "mass=high"], hydra_config=True)
    assert cfg.hydra.run.dir.startswith("runs/")
    assert cfg.hydra.sweep.dir.startswith("runs/multirun/")
    subdir = OmegaConf.to_container(cfg.hydra.sweep, resolve=False)["subdir"]
    # one resolver names every app's sweep jobs by what they sweep (pushtorch.apps.cli.job_dir_name)
    assert subdir == "${pushtorch.job_dir:${hydra.job.num},${hydra.sweep.dir},${hydra.overrides.task}}"
    assert job_dir_name(3, "/nonexistent", ["friction=low", "mass=high"]) == "3_friction=low,mass=high"


def test_launcher_configs_compose():
    joblib = _compose(["hydra/launcher=joblib"], hydra_config=True).hydra.launcher
    assert "JoblibLauncher" in joblib._target_
    overrides = ["hydra/launcher=slurm", "hydra.launcher.partition=cpu"]
    slurm = _compose(overrides, hydra_config=True).hydra.launcher
    assert "SlurmLauncher" in slurm._target_
    assert slurm.partition == "cpu" and slurm.timeout_min > 0 and slurm.cpus_per_task >= 1


def test_bad_settings_raise_pushtorch_errors(tmp_path):
    with pytest.raises(InvalidParameterError):
        simulate_from_config(_compose(["object=mesh", "object.path=null"]), tmp_path)
    with pytest.raises(PushtorchError):
        simulate_from_config(_compose(["samples_per_action=0"]), tmp_path)
    with pytest.raises(PushtorchError):
        simulate_from_config(_compose(["sim.time_step=-1"]), tmp_path)


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def test_real_run_writes_shards_summary_and_recording(tmp_path):
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch.apps.simulate", "object=hybrid", "friction=general", "mass=fixed",
         "samples_per_action=2", "shard_size=4", "workers=2", "rerun_pushes=2", "progress=false",
         f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["pushes"] == 6 and summary["shards"] == 2 and summary["simulated_pushes"] == 6
    records = load_records(run_dir)
    assert len(records) == 6 and set(records.object_name) == {"hybrid"}
    assert records.mass.unique().tolist() == [0.5]
    assert ((records.ground_friction >= 0.085) & (records.ground_friction <= 0.805)).all()
    assert (run_dir / "pushes.rrd").stat().st_size > 0
    assert OmegaConf.load(run_dir / "resolved_config.yaml").friction.kind == "uniform"


def test_world_mujoco_simulates_in_mujoco_and_says_so(tmp_path):
    cfg = _compose(["world=mujoco", "samples_per_action=1", "rerun_pushes=0", "progress=false", "workers=1"])
    simulate_from_config(cfg, tmp_path)
    manifest = json.loads((tmp_path / "pushes" / "manifest.json").read_text())
    assert manifest["settings"]["engine"] == "mujoco"
    records = load_records(tmp_path)
    assert len(records) == 3 and bool(records.touched.all()) and bool(records.valid.all())


def test_user_error_exits_with_one_line(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch.apps.simulate", "object=mesh", f"object.path={tmp_path / 'missing.stl'}",
         f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 2
    assert "mesh file not found" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow
def test_multirun_over_priors_with_the_joblib_launcher(tmp_path):
    sweep = tmp_path / "sweep"
    result = subprocess.run(
        [sys.executable, "-m", "pushtorch.apps.simulate", "-m", "friction=low,high", "hydra/launcher=joblib",
         "samples_per_action=1", "rerun_pushes=0", "progress=false", "workers=1", f"hydra.sweep.dir={sweep}"],
        cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    for job in ("0_low_paper_default", "1_high_paper_default"):
        records = load_records(sweep / job)
        assert len(records) == 3
    low = load_records(sweep / "0_low_paper_default").ground_friction
    high = load_records(sweep / "1_high_paper_default").ground_friction
    assert low.max() < 0.2 < 0.5 < high.min()
