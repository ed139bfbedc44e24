"""Push records: shard round trips, loading without pickle, tamper detection, kill-and-resume."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from pushtorch.apps.simulate import simulate_from_config
from pushtorch.errors import RecordFormatError
from pushtorch.objects import load_object
from pushtorch.sim import (
    Normal,
    PushRecords,
    PushWorld,
    SimSettings,
    load_records,
    make_actions,
    object_spec,
    plan_training_pushes,
    read_shard,
    run_plan,
    write_shard,
)
from pushtorch.sim.shards import ARRAYS, complete_shards
from pushtorch.sim.worker import simulate_arrays

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


@pytest.fixture(scope="module")
def arrays() -> dict[str, np.ndarray]:
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 1, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=5)
    with PushWorld(object_spec(cube)) as world:
        return simulate_arrays(world, plan.arrays(), "cube", plan.seed, plan.duration)


def test_shard_round_trip_and_loader(tmp_path, arrays):
    write_shard(tmp_path, 0, arrays)
    back = read_shard(tmp_path / "shard-000000.json")
    assert set(back) == set(ARRAYS)
    for name in ARRAYS:
        assert np.array_equal(back[name], arrays[name]), name
    records = load_records(tmp_path)
    n, t = 3, len(arrays["time"])
    assert len(records) == n and records.object_name == ("cube",) * n
    assert records.object_trajectory.p.shape == (n, t, 3) and records.robot_trajectory.q.shape == (n, t, 4)
    assert records.object_final.p.dtype == torch.float32 and records.index.dtype == torch.int64
    assert records.valid.all()
    assert torch.allclose(records.action, make_actions(3))
    # subsets and concatenation keep every field aligned
    both = PushRecords.cat([records.take(torch.tensor([2])), records.take(slice(0, 2))])
    assert both.index.tolist() == [2, 0, 1] and both.object_name == ("cube",) * 3
    assert torch.equal(both.object_final.p[0], records.object_final.p[2])
    assert load_records(tmp_path, dtype=torch.float64).object_final.p.dtype == torch.float64


def test_shards_load_without_pickle(tmp_path, arrays):
    write_shard(tmp_path, 0, arrays)
    with np.load(tmp_path / "shard-000000.npz", allow_pickle=False) as archive:
        for name in archive.files:
            assert archive[name].dtype != object
    manifest = json.loads((tmp_path / "shard-000000.json").read_text())
    assert manifest["format"] == "pushtorch.push_records" and manifest["count"] == 3


def _rehash(folder: Path, stem: str = "shard-000000") -> None:
    import hashlib

    manifest = json.loads((folder / f"{stem}.json").read_text())
    manifest["sha256"] = hashlib.sha256((folder / f"{stem}.npz").read_bytes()).hexdigest()
    (folder / f"{stem}.json").write_text(json.dumps(manifest))


def test_a_shard_that_would_need_pickle_is_refused(tmp_path, arrays):
    write_shard(tmp_path, 0, arrays)
    evil = dict(arrays)
    evil["object_name"] = np.array([{"payload": 1}] * 3, dtype=object)
    np.savez(tmp_path / "shard-000000.npz", **evil)  # pickles the object array
    _rehash(tmp_path)  # even with a matching hash, the loader must not unpickle
    with pytest.raises(RecordFormatError, match="pickle"):
        read_shard(tmp_path / "shard-000000.json")


def test_tampered_truncated_or_foreign_shards_are_refused(tmp_path, arrays):
    write_shard(tmp_path, 0, arrays)
    npz = tmp_path / "shard-000000.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(RecordFormatError, match="SHA-256"):
        read_shard(npz)
    assert complete_shards(tmp_path) == {}  # a resumed run would redo it

    write_shard(tmp_path, 0, arrays)
    partial = {k: v for k, v in arrays.items() if k != "mass"}
    with zipfile.ZipFile(npz, "w") as z:
        for name, value in partial.items():
            with z.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array(f, value, allow_pickle=False)
    _rehash(tmp_path)
    with pytest.raises(RecordFormatError, match="mass"):
        read_shard(npz)

    write_shard(tmp_path, 0, arrays)
    manifest = json.loads((tmp_path / "shard-000000.json").read_text())
    manifest["version"] = 99
    (tmp_path / "shard-000000.json").write_text(json.dumps(manifest))
    with pytest.raises(RecordFormatError, match="version"):
        read_shard(npz)
    with pytest.raises(RecordFormatError, match="does not exist"):
        load_records(tmp_path / "empty")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordFormatError, match="no finished"):
        load_records(tmp_path / "empty")


def test_a_folder_of_another_run_is_not_resumed_into(tmp_path):
    cube = load_object("cube")
    spec = object_spec(cube)
    plan = plan_training_pushes(cube, make_actions(1), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    run_plan(spec, plan, tmp_path, workers=1, shard_size=1, progress=False)
    again = run_plan(spec, plan, tmp_path, workers=1, shard_size=1, progress=False)
    assert again.resumed_shards == 2 and again.simulated_pushes == 0
    other = plan_training_pushes(cube, make_actions(1), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=1)
    with pytest.raises(RecordFormatError, match="different run"):
        run_plan(spec, other, tmp_path, workers=1, shard_size=1, progress=False)
    # pushes of another robot are refused by name, never mixed in
    with pytest.raises(RecordFormatError, match="sim.robot: 'p3dx' -> 'ideal'"):
        run_plan(spec, plan, tmp_path, SimSettings(robot="ideal"), workers=1, shard_size=1, progress=False)


def test_pushes_of_an_older_world_are_refused_never_mixed(tmp_path):
    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(1), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    run_plan(object_spec(cube), plan, tmp_path, workers=1, shard_size=1, progress=False)
    manifest_path = tmp_path / "manifest.json"  # the run manifest (shards have their own)
    manifest = json.loads(manifest_path.read_text())
    assert manifest.get("world") is not None
    del manifest["world"]  # as written before the world had a version
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(RecordFormatError, match="another version of the world"):
        load_records(tmp_path)
    with pytest.raises(RecordFormatError, match="another version of the world"):
        run_plan(object_spec(cube), plan, tmp_path, workers=1, shard_size=1, progress=False)


def _overrides(run_dir: Path) -> list[str]:
    return ["samples_per_action=10", "shard_size=2", "progress=false", "rerun_pushes=0", "seed=21",
            f"hydra.run.dir={run_dir}"]


def _all_arrays(folder: Path) -> dict[str, np.ndarray]:
    shards = [read_shard(p) for _, p in sorted(complete_shards(folder).items())]
    return {name: np.concatenate([s[name] for s in shards]) if name != "time" else shards[0][name]
            for name in ARRAYS}


def test_killed_run_resumes_and_matches_an_uninterrupted_run(tmp_path):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    run_dir = tmp_path / "killed"
    command = [sys.executable, "-m", "pushtorch.apps.simulate", "workers=1", *_overrides(run_dir)]
    process = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    first = run_dir / "pushes" / "shard-000000.json"
    deadline = time.monotonic() + 120
    while not first.exists():
        assert process.poll() is None, "the run ended before writing its first shard"
        assert time.monotonic() < deadline, "no shard after 120 s"
        time.sleep(0.002)
    process.kill()
    process.wait()
    folder = run_dir / "pushes"
    finished = complete_shards(folder)
    assert 1 <= len(finished) < 15, "the kill came too late to test resumption"
    kept = {k: p.with_suffix(".npz").read_bytes() for k, p in finished.items()}
    # what a kill in mid-write leaves: a temporary file and data without its manifest
    (folder / ".shard-000014.npz.tmp-1-deadbeef").write_bytes(b"partial")
    (folder / "shard-000014.npz").write_bytes(b"half a shard")

    # resume: the same configuration into the same run directory (in process; the CLI is the same function)
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("simulate", overrides=["workers=1", *_overrides(run_dir)[:-1]])
    summary = simulate_from_config(cfg, run_dir)
    assert summary["resumed_shards"] == len(finished)
    assert summary["simulated_pushes"] == 30 - 2 * len(finished)
    assert not list(folder.glob(".shard-*"))
    for k, data in kept.items():  # finished shards were not redone
        assert (folder / f"shard-{k:06d}.npz").read_bytes() == data

    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        cfg = compose("simulate", overrides=["workers=2", *_overrides(tmp_path / "whole")[:-1]])
    whole_summary = simulate_from_config(cfg, tmp_path / "whole")
    assert whole_summary["resumed_shards"] == 0 and whole_summary["simulated_pushes"] == 30
    killed, whole = _all_arrays(folder), _all_arrays(tmp_path / "whole" / "pushes")
    for name in ARRAYS:  # identical records: same seed, any worker count, interrupted or not
        assert np.array_equal(killed[name], whole[name], equal_nan=name == "first_contact_time"), name


def test_records_without_trajectories_keep_only_the_final_sample(tmp_path):
    """What training loads: every per-push value, and of the trajectories only their last sample (the robot's
    final pose), bit for bit."""
    from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes, run_plan

    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(2), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=0)
    run_plan(object_spec(cube), plan, tmp_path / "pushes", workers=1, progress=False)
    full, light = load_records(tmp_path), load_records(tmp_path, trajectories=False)
    assert light.robot_trajectory.p.shape == (4, 1, 3) and light.time.shape == (1,)
    assert torch.equal(light.robot_trajectory.q[:, 0], full.robot_trajectory.q[:, -1])
    assert torch.equal(light.object_trajectory.p[:, 0], full.object_trajectory.p[:, -1])
    assert torch.equal(light.object_final.p, full.object_final.p) and torch.equal(light.valid, full.valid)


def test_a_finished_run_leaves_its_per_push_table_as_parquet(tmp_path):
    """pushes.parquet beside the shards: one row per push, the values of the records, readable by pyarrow alone."""
    import pyarrow.parquet as pq

    from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes, run_plan

    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=1)
    run_plan(object_spec(cube), plan, tmp_path / "pushes", workers=1, shard_size=4, progress=False)
    table = pq.read_table(tmp_path / "pushes" / "pushes.parquet").to_pydict()
    records = load_records(tmp_path, dtype=torch.float64)
    assert table["index"] == records.index.tolist() and len(table["index"]) == 6
    assert table["object_final_x"] == records.object_final.p[:, 0].tolist()
    assert table["robot_final_qw"] == records.robot_trajectory.q[:, -1, 0].tolist()
    assert table["mass"] == records.mass.tolist() and table["valid"] == records.valid.tolist()
    assert set(table["object_name"]) == {"cube"}


def test_a_resumed_run_does_not_hash_its_verified_shards_again(tmp_path, monkeypatch):
    """complete_shards keeps what it verified (size, mtime, SHA-256): unchanged shards are not hashed again, and
    a shard whose data changed since is hashed and, if corrupt, not finished."""
    import hashlib

    from pushtorch.sim import Normal, make_actions, object_spec, plan_training_pushes, run_plan
    from pushtorch.sim import shards as records_module

    cube = load_object("cube")
    plan = plan_training_pushes(cube, make_actions(3), 2, Normal(0.5, 0.025), Normal(0.3, 0.05), seed=2)
    folder = tmp_path / "pushes"
    run_plan(object_spec(cube), plan, folder, workers=1, shard_size=2, progress=False)
    assert len(complete_shards(folder)) == 3 and (folder / ".verified.json").is_file()
    hashed, sha256 = [], hashlib.sha256

    def counting(data=b""):
        hashed.append(len(data))
        return sha256(data)

    monkeypatch.setattr(records_module.hashlib, "sha256", counting)
    assert len(complete_shards(folder)) == 3 and hashed == []  # nothing hashed again
    npz = sorted(folder.glob("shard-*.npz"))[1]
    data = bytearray(npz.read_bytes())
    data[-10] ^= 0xFF
    npz.write_bytes(bytes(data))
    assert sorted(complete_shards(folder)) == [0, 2] and len(hashed) == 1  # only the changed shard
