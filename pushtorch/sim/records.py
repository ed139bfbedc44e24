"""Push records: what every simulated push leaves behind, loaded as stacked tensors, and its per-push table.

Paper, Experimental Setup ("a push action is generated and a PDR is recorded") and Rigid Body Motions
(contact frames are rigidly attached to the object, so their motion follows from the object's initial and
final poses: a record holds poses, never model-specific contact data, and any model can be trained from it).

Per push: object name, push index and run seed, action ``(ẋ m/s, θ̇ rad/s)`` and its index, the object's
initial and final pose, the robot's start pose, object and robot trajectories at the record rate, the
sampled mass and ground friction and the object's own friction coefficient, and validity flags (touched,
tipped, left the ground). Poses are world-frame, quaternions w,x,y,z.

On disk the records are shards that load without pickle (:mod:`pushtorch.sim.shards`) beside their run's
manifest (:mod:`pushtorch.sim.run_manifest`). :func:`load_records` reads one shard, a shard folder or a run
folder and checks it against the run's manifest: exactly the shards and push indices it promises, each
push's action, no duplicates, finite poses and unit quaternions; an unfinished run is refused with what is
missing and how to resume it, unless ``allow_partial``. :func:`write_table` leaves a finished run's pushes
as a Parquet table (:data:`TABLE`) beside its shards.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import IncompleteRunError, RecordFormatError
from pushtorch.io import atomic_write_bytes
from pushtorch.sim.run_manifest import check_against_manifest, read_run_manifest, run_status, shard_folder
from pushtorch.sim.shards import check_arrays, complete_shards, read_shard

__all__ = [
    "PushRecords",
    "TABLE",
    "load_records",
    "records_from_arrays",
    "records_table",
    "write_table",
]



@dataclass
class PushRecords:
    """A batch of N pushes as stacked tensors (the loader's output; fields mirror
    :data:`pushtorch.sim.shards.ARRAYS`).

    Attributes:
        object_name: N object names.
        index: ``(N,)`` int64 push index within its run; seed: ``(N,)`` the run's base seed.
        action: ``(N, 2)`` (ẋ m/s, θ̇ rad/s); action_index: ``(N,)`` int64.
        object_initial, object_final, robot_start: poses ``(N,)``.
        object_trajectory, robot_trajectory: poses ``(N, T)`` at ``time (T,)`` seconds.
        mass: ``(N,)`` kg; ground_friction: ``(N,)`` effective object-ground coefficient;
        object_friction: ``(N,)`` the object body's own coefficient in the engine.
        touched, tipped, left_ground: ``(N,)`` bool; first_contact_time: ``(N,)`` s (NaN: never).
    """

    object_name: tuple[str, ...]
    index: torch.Tensor
    seed: torch.Tensor
    action_index: torch.Tensor
    action: torch.Tensor
    object_initial: se3.Pose
    object_final: se3.Pose
    robot_start: se3.Pose
    object_trajectory: se3.Pose
    robot_trajectory: se3.Pose
    time: torch.Tensor
    mass: torch.Tensor
    ground_friction: torch.Tensor
    object_friction: torch.Tensor
    touched: torch.Tensor
    tipped: torch.Tensor
    left_ground: torch.Tensor
    first_contact_time: torch.Tensor

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @property
    def valid(self) -> torch.Tensor:
        """``(N,)`` bool: the robot touched the object and it neither tipped nor left the ground."""
        return self.touched & ~self.tipped & ~self.left_ground

    def take(self, selection) -> PushRecords:
        """A subset by index, index list or tensor, slice or boolean mask (the N dim is kept)."""
        if isinstance(selection, int):
            selection = [selection]
        if isinstance(selection, list):
            selection = torch.as_tensor(selection, dtype=torch.int64)
        if isinstance(selection, torch.Tensor) and selection.dtype == torch.bool:
            selection = selection.nonzero(as_tuple=True)[0]
        names = np.asarray(self.object_name, dtype=object)[
            selection.cpu().numpy() if isinstance(selection, torch.Tensor) else selection
        ]
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "object_name":
                values[f.name] = tuple(str(n) for n in np.atleast_1d(names))
            elif f.name == "time":
                values[f.name] = value
            elif isinstance(value, se3.Pose):
                values[f.name] = se3.Pose.unchecked(value.p[selection], value.q[selection])
            else:
                values[f.name] = value[selection]
        return PushRecords(**values)

    def to(self, *args, **kwargs) -> PushRecords:
        """Move or cast the floating-point tensors (index, flags and names keep their types)."""
        values = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, se3.Pose):
                values[f.name] = value.to(*args, **kwargs)
            elif isinstance(value, torch.Tensor) and value.is_floating_point():
                values[f.name] = value.to(*args, **kwargs)
            elif isinstance(value, torch.Tensor):
                positional = (a for a in args if isinstance(a, str | torch.device))
                device = kwargs.get("device", next(positional, None))
                values[f.name] = value.to(device) if device is not None else value
            else:
                values[f.name] = value
        return PushRecords(**values)

    @staticmethod
    def cat(batches: Iterable[PushRecords]) -> PushRecords:
        """Concatenate batches recorded at the same times.

        Raises:
            RecordFormatError: no batch, or batches with different record times.
        """
        batches = list(batches)
        if not batches:
            raise RecordFormatError("no push records to concatenate")
        time = batches[0].time
        for b in batches[1:]:
            if b.time.shape != time.shape or not torch.allclose(b.time, time):
                raise RecordFormatError("push records with different record times cannot be concatenated")
        values = {}
        for f in fields(PushRecords):
            items = [getattr(b, f.name) for b in batches]
            if f.name == "object_name":
                values[f.name] = tuple(n for item in items for n in item)
            elif f.name == "time":
                values[f.name] = time
            elif isinstance(items[0], se3.Pose):
                values[f.name] = se3.Pose.cat(items, 0)
            else:
                values[f.name] = torch.cat(items, 0)
        return PushRecords(**values)


def records_from_arrays(
    arrays: Mapping[str, np.ndarray], dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu"
) -> PushRecords:
    """Stack shard arrays into :class:`PushRecords` (floats cast to ``dtype``).

    Raises:
        RecordFormatError: the arrays do not match :data:`~pushtorch.sim.shards.ARRAYS`.
    """
    check_arrays(arrays, "push records")

    def f(name: str) -> torch.Tensor:
        return torch.as_tensor(np.asarray(arrays[name], dtype=np.float64), device=device).to(dtype)

    def pose(prefix: str) -> se3.Pose:
        return se3.Pose.unchecked(f(prefix + "_p"), f(prefix + "_q"))

    return PushRecords(
        object_name=tuple(str(n) for n in np.asarray(arrays["object_name"]).tolist()),
        index=torch.as_tensor(np.asarray(arrays["index"], dtype=np.int64), device=device),
        seed=torch.as_tensor(np.asarray(arrays["seed"], dtype=np.int64), device=device),
        action_index=torch.as_tensor(np.asarray(arrays["action_index"], dtype=np.int64), device=device),
        action=f("action"),
        object_initial=pose("object_initial"),
        object_final=pose("object_final"),
        robot_start=pose("robot_start"),
        object_trajectory=pose("object_trajectory"),
        robot_trajectory=pose("robot_trajectory"),
        time=f("time"),
        mass=f("mass"),
        ground_friction=f("ground_friction"),
        object_friction=f("object_friction"),
        touched=torch.as_tensor(np.asarray(arrays["touched"], dtype=bool), device=device),
        tipped=torch.as_tensor(np.asarray(arrays["tipped"], dtype=bool), device=device),
        left_ground=torch.as_tensor(np.asarray(arrays["left_ground"], dtype=bool), device=device),
        first_contact_time=f("first_contact_time"),
    )


def _trimmed(arrays: dict[str, np.ndarray], trajectories: bool) -> dict[str, np.ndarray]:
    """The shard's arrays, its trajectories cut to their last sample unless ``trajectories``."""
    if trajectories:
        return arrays
    out = dict(arrays)
    for name in ("object_trajectory_p", "object_trajectory_q", "robot_trajectory_p", "robot_trajectory_q"):
        out[name] = np.ascontiguousarray(arrays[name][:, -1:])
    out["time"] = np.ascontiguousarray(arrays["time"][-1:])
    return out


def load_records(
    path: str | Path,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    allow_partial: bool = False,
    trajectories: bool = True,
) -> PushRecords:
    """Load push records: one shard (``.json``/``.npz``), a shard folder, or a run folder (its ``pushes/``). A push
    table (``.parquet``) is read by its sibling :func:`pushtorch.sim.tables.read_push_table`.

    Shards are read in push-index order, verified against their manifests and never unpickled. A folder
    with a run manifest is checked against it: every promised shard finished, each holding exactly the
    push indices and actions the run promises there, no push twice, finite poses, unit quaternions.

    Args:
        allow_partial: load the finished shards of an unfinished run instead of refusing it (check with
            :func:`~pushtorch.sim.run_manifest.run_status` what is missing).
        trajectories: keep the recorded trajectories; False keeps only their last sample (``T = 1``: the
            robot's final pose, all training uses), a sixteenth of the memory at the paper's 41 samples.

    Returns:
        :class:`PushRecords` with every push of every finished shard.

    Raises:
        IncompleteRunError: an unfinished run (what is missing and how to resume it), unless ``allow_partial``.
        RecordFormatError: nothing to load, or a corrupt, tampered, duplicated or foreign shard.
    """
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        raise RecordFormatError(f"{path} is a push table: read it with pushtorch.read_push_table(path) (its .records "
                                "are these records, checked; pushtorch.sim.tables)")
    if path.is_file():
        return records_from_arrays(_trimmed(read_shard(path), trajectories), dtype, device)
    if not path.exists():
        raise RecordFormatError(f"{path} does not exist: give a pushtorch-simulate run folder (or its pushes/)")
    folder = shard_folder(path)
    status = run_status(folder)
    if status is not None and not status.complete and not allow_partial:
        raise IncompleteRunError(status.describe() + "; or train on what is there with allow_partial=true")
    shards = complete_shards(folder, verify=False)
    if not shards:
        raise RecordFormatError(f"no finished push-record shard in {path}")
    arrays = {k: _trimmed(read_shard(p), trajectories) for k, p in sorted(shards.items())}
    if status is not None:
        check_against_manifest(arrays, read_run_manifest(folder), folder, status.complete)
    records = PushRecords.cat([records_from_arrays(a, dtype, device) for a in arrays.values()])
    order = torch.argsort(records.index, stable=True)
    repeated = records.index[order][1:] == records.index[order][:-1]
    if repeated.any():
        twice = int(records.index[order][1:][repeated][0])
        holders = [k for k, a in arrays.items() if twice in a["index"]]
        raise RecordFormatError(
            f"{folder}: push {twice} appears more than once (in shards {', '.join(map(str, holders))}): a duplicated"
            " shard; remove the copy"
        )
    if not torch.equal(order, torch.arange(len(records))):
        records = records.take(order)
    return records


#: The per-push table beside a finished run's shards (:func:`write_table`): Parquet, readable without pushtorch.
TABLE = "pushes.parquet"


def records_table(records: PushRecords):
    """The per-push table of ``records`` as a ``pyarrow.Table``: one row per push, the columns ``index``,
    ``seed``, ``object_name``, ``action_index``, ``speed``, ``yaw_rate`` (m/s, rad/s), the poses
    ``object_initial_*``, ``object_final_*``, ``robot_start_*`` and ``robot_final_*`` as ``x, y, z`` (m) and
    ``qw, qx, qy, qz``, then ``mass``, ``ground_friction``, ``object_friction``, ``touched``, ``tipped``,
    ``left_ground``, ``valid`` and ``first_contact_time`` (s). No trajectories: those stay in the shards.
    """
    import pyarrow as pa

    columns: dict[str, np.ndarray] = {
        "index": records.index.numpy(), "seed": records.seed.numpy(),
        "object_name": np.asarray(records.object_name, dtype=object),
        "action_index": records.action_index.numpy(),
        "speed": records.action[:, 0].double().numpy(), "yaw_rate": records.action[:, 1].double().numpy(),
    }
    final_robot = se3.Pose.unchecked(records.robot_trajectory.p[:, -1], records.robot_trajectory.q[:, -1])
    for name, pose in (("object_initial", records.object_initial), ("object_final", records.object_final),
                       ("robot_start", records.robot_start), ("robot_final", final_robot)):
        for k, axis in enumerate("xyz"):
            columns[f"{name}_{axis}"] = pose.p[:, k].double().numpy()
        for k, axis in enumerate(("qw", "qx", "qy", "qz")):
            columns[f"{name}_{axis}"] = pose.q[:, k].double().numpy()
    for name in ("mass", "ground_friction", "object_friction", "first_contact_time"):
        columns[name] = getattr(records, name).double().numpy()
    for name in ("touched", "tipped", "left_ground", "valid"):
        columns[name] = getattr(records, name).numpy()
    return pa.table(columns)


def write_table(folder: str | Path) -> Path:
    """Write :data:`TABLE` (Parquet) beside a finished run's shards, atomically; returns its path.

    ``pandas.read_parquet(path)`` or ``pyarrow.parquet.read_table(path)`` read it without pushtorch.

    Raises:
        IncompleteRunError: the run is not finished.
    """
    import pyarrow.parquet as pq

    folder = shard_folder(Path(folder))
    table = records_table(load_records(folder, dtype=torch.float64, trajectories=False))
    buffer = io.BytesIO()
    pq.write_table(table, buffer)
    path = folder / TABLE
    atomic_write_bytes(path, buffer.getvalue())
    return path
