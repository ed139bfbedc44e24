"""A lab's own pushes: the per-push Parquet table read, checked and turned into the records training uses.

Paper, Experimental Setup (a push action generates a PDR; the paper's came from Gazebo, a lab's come from its
robot and tracker) and Rigid Body Motions (a record is the object's initial and final pose, the robot's start
and the action: any model trains from that). A simulated run's ``pushes.parquet`` (:func:`records_table`) is the
reference of the format, and :func:`export_run_table` makes a run a complete table: clouds, mesh and metadata.

*The table* (``docs/usage.md``, "Your own pushes: a push table"): one row per push. Required columns:
``object_name``, ``action_index``, ``speed`` (m/s), ``yaw_rate`` (rad/s) and the poses ``object_initial_*``,
``object_final_*``, ``robot_start_*``, ``robot_final_*`` as ``x, y, z`` (m) and ``qw, qx, qy, qz``. Optional:
``duration`` (s; else the metadata's), ``index``, ``seed``, the flags ``touched``, ``tipped``, ``left_ground``
(else inferred, :func:`infer_flags`), ``cloud`` (a ``.ply``, ``.pcd`` or ``.npz`` file relative to the table:
the object's observed cloud at the push's start, world frame; rows may share one), ``mass`` (kg) and
``ground_friction`` (both or neither), ``object_friction`` and ``first_contact_time``. Object poses are those of
the object's mesh's own frame; they become object-frame (centre of mass) poses here.

*The metadata* (Parquet key-value): ``pushtorch.robot`` (one of :data:`ROBOTS`), ``pushtorch.pusher``
(:data:`PUSHER`), ``pushtorch.meshes`` (a JSON object: each object's mesh file, relative to the table) and
``pushtorch.duration`` where no column holds it.

*Checked on the way in* (:func:`read_push_table`): every problem is one :class:`RecordFormatError` that names the
column and, where a row is at fault, the first such row (0-based) and how many; nothing is returned from a table
with any. Missing or mistyped columns, nulls, NaN or infinite values, positions more than :data:`MAX_POSITION`
from the origin (millimetres written as metres), quaternions off unit length by more than
:data:`~pushtorch.sim.shards.UNIT_QUATERNION_TOLERANCE` (those within it are normalised), friction or mass
≤ 0, actions outside the configured set, another robot or pusher, and cloud or mesh files that are missing or
do not load (each distinct file is read once).
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from pushtorch.errors import InvalidPointCloudError, PushtorchError, RecordFormatError
from pushtorch.io import atomic_write_bytes
from pushtorch.paths import safe_name
from pushtorch.sim.drive import DRIVES
from pushtorch.sim.records import PushRecords, records_table
from pushtorch.sim.shards import UNIT_QUATERNION_TOLERANCE

__all__ = [
    "MAX_POSITION",
    "META",
    "POSES",
    "PUSHER",
    "PushTable",
    "REQUIRED",
    "ROBOTS",
    "TOUCH_ANGLE",
    "TOUCH_DISTANCE",
    "export_run_table",
    "infer_flags",
    "read_push_table",
    "write_push_table",
]

#: The robots a table may name (``pushtorch.robot``): the Pioneer 3-DX's drive, or the stiff pusher of the
#: ``ideal`` simulated robot. Both carry the paper's bumper.
ROBOTS = DRIVES
#: The only pusher the models know (``pushtorch.pusher``): the paper's flat bumper.
PUSHER = "bumper"
#: Parquet metadata keys.
META = {"format": "pushtorch.format", "robot": "pushtorch.robot", "pusher": "pushtorch.pusher",
        "meshes": "pushtorch.meshes", "duration": "pushtorch.duration"}
FORMAT = "pushtorch.push_table/1"
#: The four poses of a row, each as ``<name>_x, _y, _z, _qw, _qx, _qy, _qz``.
POSES = ("object_initial", "object_final", "robot_start", "robot_final")
_AXES = ("x", "y", "z", "qw", "qx", "qy", "qz")
#: Required columns and their kinds: "s" string, "i" integer, "f" number.
REQUIRED = {"object_name": "s", "action_index": "i", "speed": "f", "yaw_rate": "f",
            **{f"{pose}_{axis}": "f" for pose in POSES for axis in _AXES}}
_OPTIONAL = {"duration": "f", "index": "i", "seed": "i", "touched": "b", "tipped": "b", "left_ground": "b",
             "cloud": "s", "mass": "f", "ground_friction": "f", "object_friction": "f", "first_contact_time": "f"}
#: A position farther than this from the origin (m) is refused: most likely millimetres written as metres.
MAX_POSITION = 10.0
#: Without a ``touched`` column a push touched the object when the object moved this far (m) or turned this much
#: (rad): above a tracker's noise, far below a push (0.4 m in 4 s).
TOUCH_DISTANCE = 0.002
TOUCH_ANGLE = 0.02
#: Without ``tipped`` / ``left_ground``: the object's up axis turned more than this (deg) between the start and
#: the end, or its centre rose or sank more than this (m): the simulator's own thresholds, read at the end only.
TIP_ANGLE_DEG = 10.0
LIFT_TOLERANCE = 0.01
#: An object frame this close to its mesh file's origin (m) is taken as the mesh frame itself.
ORIGIN_TOLERANCE = 1e-6
#: Actions match the configured ones to this (m/s, rad/s, s).
ACTION_TOLERANCE = 1e-5


@dataclass
class PushTable:
    """A read push table.

    Attributes:
        path: the table file.
        records: its pushes as :class:`~pushtorch.sim.records.PushRecords` (``T = 1``: the final poses), object
            poses in each object's centre-of-mass frame; ``mass``, ``ground_friction`` and ``object_friction``
            NaN where the table has no such column.
        meshes: object name → mesh file (resolved), as the metadata names them.
        clouds: per row, the resolved cloud file or None.
        robot, pusher: the metadata's; duration: s.
        has_physics: the table has ``mass`` and ``ground_friction``.
        inferred: the flag columns the table lacked, inferred by :func:`infer_flags`.
    """

    path: Path
    records: PushRecords
    meshes: dict[str, Path]
    clouds: tuple[Path | None, ...]
    robot: str
    pusher: str
    duration: float
    has_physics: bool
    inferred: tuple[str, ...] = ()
    _objects: dict = field(default_factory=dict, repr=False)

    @property
    def object_names(self) -> tuple[str, ...]:
        """The table's objects in order of first appearance."""
        return tuple(dict.fromkeys(self.records.object_name))

    def object(self, name: str):
        """The :class:`~pushtorch.objects.ObjectModel` of ``name`` from its mesh (loaded once).

        Raises:
            RecordFormatError: the metadata names no mesh for it.
        """
        if name not in self._objects:
            if name not in self.meshes:
                raise RecordFormatError(f"{self.path}: the metadata {META['meshes']} names no mesh for object "
                                        f"{name!r}: training needs its mesh (the full cloud, symmetry and size)")
            self._objects[name] = _load_mesh(self.path, name, self.meshes[name])
        return self._objects[name]

    def cloud(self, row: int):
        """The observed cloud of row ``row`` (a :class:`~pushtorch.perception.PointCloud`, world frame).

        Raises:
            RecordFormatError: the row has no cloud.
        """
        path = self.clouds[row]
        if path is None:
            raise RecordFormatError(f"{self.path}: row {row} has no cloud (column 'cloud')")
        return _cloud_file(path)


def _cloud_file(path: Path):
    """The cloud in ``path``, read once per version of the file (rows share files)."""
    try:
        stamp = path.stat()
    except OSError:
        stamp = None
    return _cached_cloud(str(path), None if stamp is None else (stamp.st_mtime_ns, stamp.st_size))


@lru_cache(maxsize=64)
def _cached_cloud(path: str, stamp):
    from pushtorch.perception import load_cloud_file

    return load_cloud_file(path)


def _load_mesh(table: Path, name: str, path: Path):
    from pushtorch.objects import load_mesh_file

    try:
        return load_mesh_file(path, name=name)
    except PushtorchError as exc:  # an InvalidMeshError, or a name unfit for a file
        raise RecordFormatError(f"{table}: the mesh of object {name!r} ({META['meshes']}): {exc}") from exc


def _fail(table: Path, column: str, bad: np.ndarray, what: str) -> None:
    """Raise for the rows where ``bad``, naming the first and how many."""
    rows = np.flatnonzero(bad)
    if rows.size:
        more = f" (and {rows.size - 1} more rows)" if rows.size > 1 else ""
        raise RecordFormatError(f"{table}: row {int(rows[0])}, column {column!r}: {what}{more}")


def _kind_ok(arrow_type, kind: str) -> bool:
    import pyarrow as pa

    if kind == "s":
        return pa.types.is_string(arrow_type) or pa.types.is_large_string(arrow_type)
    if kind == "i":
        return pa.types.is_integer(arrow_type)
    if kind == "b":
        return pa.types.is_boolean(arrow_type)
    return pa.types.is_floating(arrow_type) or pa.types.is_integer(arrow_type)


_KIND_NAMES = {"s": "strings", "i": "integers", "b": "booleans", "f": "numbers"}


def _columns(table_path: Path, table) -> dict[str, np.ndarray]:
    """Every known column as numpy, after its presence, type and nulls are checked."""
    names = set(table.column_names)
    missing = [c for c in REQUIRED if c not in names]
    if missing:
        raise RecordFormatError(f"{table_path}: missing column{'s' if len(missing) > 1 else ''} "
                                f"{', '.join(map(repr, missing))} (the schema: docs/usage.md, 'Your own pushes: "
                                "a push table')")
    out: dict[str, np.ndarray] = {}
    for name, kind in {**REQUIRED, **_OPTIONAL}.items():
        if name not in names:
            continue
        column = table.column(name)
        if not _kind_ok(column.type, kind):
            raise RecordFormatError(f"{table_path}: column {name!r} holds {column.type}, not {_KIND_NAMES[kind]}")
        if column.null_count and name != "cloud":
            _fail(table_path, name, np.asarray(column.is_null().to_numpy(zero_copy_only=False)), "no value (null)")
        values = np.array(column.to_numpy(zero_copy_only=False))  # writable: torch refuses read-only arrays
        if kind == "f":
            values = np.asarray(values, dtype=np.float64)
        elif kind == "i":
            values = np.asarray(values, dtype=np.int64)
        elif kind == "b":
            values = np.asarray(values, dtype=bool)
        else:
            values = np.asarray(values, dtype=object)
        out[name] = values
    return out


def _metadata(table_path: Path, schema) -> dict[str, str]:
    raw = schema.metadata or {}
    return {k.decode(): v.decode() for k, v in raw.items() if k.decode().startswith("pushtorch.")}


def _check_robot(table_path: Path, meta: Mapping[str, str]) -> tuple[str, str]:
    robot, pusher = meta.get(META["robot"]), meta.get(META["pusher"])
    if robot is None or pusher is None:
        raise RecordFormatError(
            f"{table_path}: the table names no {'robot' if robot is None else 'pusher'} (Parquet metadata "
            f"{META['robot']!r} and {META['pusher']!r}): pushtorch's models are of a {' or '.join(ROBOTS)} robot "
            f"with a {PUSHER}; say so in the metadata if the pushes are its")
    if pusher != PUSHER:
        raise RecordFormatError(f"{table_path}: the pushes were made with a {pusher!r} pusher (metadata "
                                f"{META['pusher']}); pushtorch models the pushes of a flat {PUSHER} only")
    if robot not in ROBOTS:
        raise RecordFormatError(f"{table_path}: the pushes were made by robot {robot!r} (metadata {META['robot']}); "
                                f"pushtorch models the pushes of {' or '.join(ROBOTS)}")
    return robot, pusher


def _duration(table_path: Path, cols: dict, meta: Mapping[str, str], n: int) -> float:
    if "duration" in cols:
        d = cols["duration"]
        _fail(table_path, "duration", ~np.isfinite(d) | (d <= 0), "the duration must be a positive number of seconds")
        _fail(table_path, "duration", np.abs(d - d[0]) > ACTION_TOLERANCE,
              f"every push of a table has one duration ({d[0]:g} s in row 0)")
        return float(d[0]) if n else math.nan
    if META["duration"] not in meta:
        raise RecordFormatError(f"{table_path}: no push duration: add a column 'duration' (s) or the metadata "
                                f"{META['duration']!r}")
    try:
        value = float(meta[META["duration"]])
    except ValueError as exc:
        raise RecordFormatError(f"{table_path}: metadata {META['duration']} is {meta[META['duration']]!r}, not a "
                                "number of seconds") from exc
    if not (math.isfinite(value) and value > 0):
        raise RecordFormatError(f"{table_path}: metadata {META['duration']} must be a positive number of seconds")
    return value


def _check_actions(table_path: Path, cols: dict, actions, duration: float, configured_duration) -> None:
    index, speed, rate = cols["action_index"], cols["speed"], cols["yaw_rate"]
    if configured_duration is not None and abs(duration - float(configured_duration)) > ACTION_TOLERANCE:
        raise RecordFormatError(f"{table_path}: the pushes last {duration:g} s, not the configured actions' "
                                f"{float(configured_duration):g} s (column or metadata 'duration')")
    for name in ("speed", "yaw_rate"):
        _fail(table_path, name, ~np.isfinite(cols[name]), "not a finite number")
    if actions is None:  # the table's own actions: one action per index
        for a in np.unique(index):
            rows = index == a
            first = int(np.flatnonzero(rows)[0])
            off = rows & ((np.abs(speed - speed[first]) > ACTION_TOLERANCE)
                          | (np.abs(rate - rate[first]) > ACTION_TOLERANCE))
            _fail(table_path, "action_index", off, f"action_index {a} names two different actions "
                  f"({speed[first]:g} m/s, {rate[first]:g} rad/s in row {first})")
        _fail(table_path, "speed", speed <= 0, "the speed must be positive (the bumper pushes forward)")
        return
    actions = np.asarray(torch.as_tensor(actions, dtype=torch.float64).reshape(-1, 2))
    listed = ", ".join(f"{i}: ({a[0]:g} m/s, {a[1]:.4g} rad/s)" for i, a in enumerate(actions))
    where = f"the configured actions are {listed}"
    _fail(table_path, "action_index", (index < 0) | (index >= len(actions)),
          f"action_index outside 0..{len(actions) - 1}: " + where)
    expected = actions[index]
    _fail(table_path, "speed", np.abs(speed - expected[:, 0]) > ACTION_TOLERANCE,
          f"speed {speed[np.argmax(np.abs(speed - expected[:, 0]))]:g} m/s is not its action's: " + where)
    _fail(table_path, "yaw_rate", np.abs(rate - expected[:, 1]) > ACTION_TOLERANCE,
          "the yaw rate is not its action's: " + where)


def _poses(table_path: Path, cols: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    poses = {}
    for pose in POSES:
        p = np.stack([cols[f"{pose}_{a}"] for a in "xyz"], -1)
        q = np.stack([cols[f"{pose}_{a}"] for a in ("qw", "qx", "qy", "qz")], -1)
        for k, axis in enumerate(_AXES):
            values = p[:, k] if k < 3 else q[:, k - 3]
            _fail(table_path, f"{pose}_{axis}", ~np.isfinite(values), "NaN or infinite")
        far = np.linalg.norm(p, axis=-1)
        _fail(table_path, f"{pose}_x", far > MAX_POSITION,
              f"the {pose} position lies {far.max():.4g} m from the origin (more than {MAX_POSITION:g} m): positions "
              "are metres (millimetres written as metres?)")
        norm = np.linalg.norm(q, axis=-1)
        _fail(table_path, f"{pose}_qw", np.abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE,
              f"the {pose} quaternion (w, x, y, z) has norm {norm[np.argmax(np.abs(norm - 1))]:.4g}, not 1")
        off = np.abs(norm - 1.0) > 1e-7  # a tracker's rounding: normalised; exact unit quaternions stay bit for bit
        q = q.copy()
        q[off] /= norm[off, None]
        poses[pose] = (p, q)
    return poses


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate ``v (3,)`` by the unit wxyz quaternions ``q (N, 4)``."""
    w, u = q[:, :1], q[:, 1:]
    t = 2.0 * np.cross(u, np.broadcast_to(v, u.shape))
    return v + w * t + np.cross(u, t)


def infer_flags(poses: Mapping[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """The validity flags of pushes without a tracker's: ``touched`` (the object moved more than
    :data:`TOUCH_DISTANCE` or turned more than :data:`TOUCH_ANGLE`), ``tipped`` (its up axis turned more than
    :data:`TIP_ANGLE_DEG` between start and end) and ``left_ground`` (its centre rose or sank more than
    :data:`LIFT_TOLERANCE`). ``poses`` maps ``object_initial`` and ``object_final`` to ``(p (N, 3), q (N, 4))``."""
    p0, q0 = poses["object_initial"]
    p1, q1 = poses["object_final"]
    z = np.array([0.0, 0.0, 1.0])
    up0, up1 = _rotate(q0, z), _rotate(q1, z)
    tilt = np.degrees(np.arccos(np.clip((up0 * up1).sum(-1), -1.0, 1.0)))
    turn = 2.0 * np.arccos(np.clip(np.abs((q0 * q1).sum(-1)), 0.0, 1.0))
    moved = np.linalg.norm(p1[:, :2] - p0[:, :2], axis=-1)
    return {"touched": (moved > TOUCH_DISTANCE) | (turn > TOUCH_ANGLE), "tipped": tilt > TIP_ANGLE_DEG,
            "left_ground": np.abs(p1[:, 2] - p0[:, 2]) > LIFT_TOLERANCE}


def _mesh_paths(table_path: Path, meta: Mapping[str, str], names: Sequence[str]) -> dict[str, Path]:
    if META["meshes"] not in meta:
        return {}
    try:
        meshes = json.loads(meta[META["meshes"]])
    except json.JSONDecodeError as exc:
        raise RecordFormatError(f"{table_path}: metadata {META['meshes']} is not a JSON object of object name → "
                                "mesh file") from exc
    if not isinstance(meshes, dict) or not all(isinstance(v, str) for v in meshes.values()):
        raise RecordFormatError(f"{table_path}: metadata {META['meshes']} must map object names to mesh files")
    return {str(k): table_path.parent / v for k, v in meshes.items() if k in names}


def _physics(table_path: Path, cols: dict, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    present = [c for c in ("mass", "ground_friction") if c in cols]
    if len(present) == 1:
        other = "ground_friction" if present[0] == "mass" else "mass"
        raise RecordFormatError(f"{table_path}: column {present[0]!r} without {other!r}: give both, or neither")
    for name in ("mass", "ground_friction", "object_friction"):
        if name in cols:
            _fail(table_path, name, ~np.isfinite(cols[name]) | (cols[name] <= 0), f"{name} must be a positive number")
    nan = np.full(n, np.nan)
    return (cols.get("mass", nan), cols.get("ground_friction", nan), cols.get("object_friction", nan),
            len(present) == 2)


def read_push_table(path: str | Path, actions=None, duration: float | None = None, check_files: bool = True,
                    dtype: torch.dtype = torch.float32, device: str | torch.device = "cpu") -> PushTable:
    """Read and check a push table (module docstring).

    Args:
        path: the ``.parquet`` file.
        actions: ``(A, 2)`` the configured actions (ẋ m/s, θ̇ rad/s) the rows' ``action_index`` must name; None
            checks only that each index names one action.
        duration: the configured actions' duration (s), or None.
        check_files: load every distinct cloud file once, so a bad one is refused now (the meshes are always
            loaded: an object's poses are converted to its centre-of-mass frame by its mesh).

    Raises:
        RecordFormatError: anything wrong with the table (module docstring); the message names the column and
            the first row at fault.
    """
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.is_file():
        raise RecordFormatError(f"push table not found: {path}")
    try:
        table = pq.read_table(path)
    except Exception as exc:  # pyarrow raises several types on a file that is not Parquet
        raise RecordFormatError(f"could not read {path} as a Parquet table ({type(exc).__name__}: {exc})") from exc
    n = table.num_rows
    if n == 0:
        raise RecordFormatError(f"{path}: the table has no rows")
    meta = _metadata(path, table.schema)
    robot, pusher = _check_robot(path, meta)
    cols = _columns(path, table)
    names = tuple(str(v) for v in cols["object_name"])
    for name in dict.fromkeys(names):
        try:
            safe_name(name, "object_name")
        except PushtorchError as exc:
            _fail(path, "object_name", np.asarray(names, dtype=object) == name, str(exc))
    d = _duration(path, cols, meta, n)
    _check_actions(path, cols, actions, d, duration)
    poses = _poses(path, cols)
    mass, ground, own, has_physics = _physics(path, cols, n)
    flags = {k: cols[k] for k in ("touched", "tipped", "left_ground") if k in cols}
    inferred = tuple(k for k in ("touched", "tipped", "left_ground") if k not in flags)
    if inferred:
        flags = {**infer_flags(poses), **flags}
    meshes = _mesh_paths(path, meta, names)
    clouds: list[Path | None] = [None] * n
    if "cloud" in cols:
        files = {v: (path.parent / v) for v in dict.fromkeys(cols["cloud"]) if isinstance(v, str) and v}
        clouds = [files.get(v) if isinstance(v, str) else None for v in cols["cloud"]]
        if check_files:
            for value, file in files.items():
                try:
                    _cloud_file(file)
                except InvalidPointCloudError as exc:
                    _fail(path, "cloud", cols["cloud"] == value, str(exc))
    objects = {name: _load_mesh(path, name, file) for name, file in meshes.items()}
    for name in ("object_initial", "object_final"):  # the mesh frame's poses → the object frame's
        p, q = poses[name]
        for obj_name, obj in objects.items():
            origin = obj.source_origin
            if origin is not None and np.linalg.norm(origin) > ORIGIN_TOLERANCE:
                rows = np.asarray(names, dtype=object) == obj_name
                p = p.copy()
                p[rows] = p[rows] + _rotate(q[rows], np.asarray(origin, dtype=np.float64))
        poses[name] = (p, q)
    records = _records(cols, poses, names, flags, mass, ground, own, d, dtype, device)
    return PushTable(path, records, meshes, tuple(clouds), robot, pusher, d, has_physics, inferred, objects)


def _records(cols, poses, names, flags, mass, ground, own, duration, dtype, device) -> PushRecords:
    from pushtorch import se3

    n = len(names)

    def f(values) -> torch.Tensor:
        return torch.as_tensor(np.asarray(values, dtype=np.float64), device=device).to(dtype)

    def pose(name: str, t: bool = False) -> se3.Pose:
        p, q = poses[name]
        return se3.Pose.unchecked(f(p[:, None] if t else p), f(q[:, None] if t else q))

    return PushRecords(
        object_name=names,
        index=torch.as_tensor(cols.get("index", np.arange(n)), dtype=torch.int64, device=device),
        seed=torch.as_tensor(cols.get("seed", np.zeros(n, dtype=np.int64)), dtype=torch.int64, device=device),
        action_index=torch.as_tensor(cols["action_index"], dtype=torch.int64, device=device),
        action=f(np.stack([cols["speed"], cols["yaw_rate"]], -1)),
        object_initial=pose("object_initial"), object_final=pose("object_final"), robot_start=pose("robot_start"),
        object_trajectory=pose("object_final", True), robot_trajectory=pose("robot_final", True),
        time=f([duration]), mass=f(mass), ground_friction=f(ground), object_friction=f(own),
        touched=torch.as_tensor(flags["touched"], device=device),
        tipped=torch.as_tensor(flags["tipped"], device=device),
        left_ground=torch.as_tensor(flags["left_ground"], device=device),
        first_contact_time=f(cols.get("first_contact_time", np.full(n, np.nan))),
    )


def write_push_table(path: str | Path, records: PushRecords, robot: str, duration: float,
                     meshes: Mapping[str, str] | None = None, clouds: Sequence[str | None] | None = None,
                     pusher: str = PUSHER) -> Path:
    """Write ``records`` as a push table (Parquet, atomically) that :func:`read_push_table` reads back.

    Args:
        meshes: object name → mesh file relative to the table; clouds: per row, a cloud file relative to the
            table or None.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = records_table(records)
    unknown = [c for c in ("mass", "ground_friction", "object_friction")
               if np.isnan(table.column(c).to_numpy()).all()]  # records of a table without them
    table = table.drop_columns(unknown)
    if clouds is not None:
        table = table.append_column("cloud", pa.array(list(clouds), type=pa.string()))
    meta = {META["format"]: FORMAT, META["robot"]: robot, META["pusher"]: pusher,
            META["duration"]: repr(float(duration))}
    if meshes:
        meta[META["meshes"]] = json.dumps(dict(meshes), sort_keys=True)
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
    buffer = io.BytesIO()
    pq.write_table(table, buffer)
    path = Path(path)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def export_run_table(folder: str | Path, obj, robot: str, duration: float, voxel_size: float | None = None,
                     seed: int = 0) -> Path:
    """Make a finished run's ``pushes.parquet`` a complete push table: the object's mesh (lossless PLY, the
    object frame), one single-shot cloud per distinct start pose of the object (``clouds/start_<k>.npz``, shared
    by the rows that start there) and the metadata. Returns the table's path.

    Raises:
        IncompleteRunError: the run is not finished.
    """
    from pushtorch import se3
    from pushtorch.objects import save_mesh_file
    from pushtorch.perception import DEFAULT_VOXEL_SIZE, capture_partial_cloud, save_cloud_file
    from pushtorch.sim.records import TABLE, load_records
    from pushtorch.sim.run_manifest import shard_folder

    folder = shard_folder(Path(folder))
    records = load_records(folder, dtype=torch.float64, trajectories=False)
    mesh_file = f"meshes/{obj.name}.ply"
    save_mesh_file(obj.mesh, folder / mesh_file)
    starts = np.concatenate([records.object_initial.p.numpy(), records.object_initial.q.numpy()], -1)
    unique, which = np.unique(starts, axis=0, return_inverse=True)
    clouds = []
    for k, start in enumerate(unique):
        pose = se3.Pose(torch.as_tensor(start[:3], dtype=torch.float32),
                        torch.as_tensor(start[3:], dtype=torch.float32))
        cloud = capture_partial_cloud(obj, pose, voxel_size=DEFAULT_VOXEL_SIZE if voxel_size is None else voxel_size,
                                      generator=torch.Generator().manual_seed(int(seed) + k))
        save_cloud_file(cloud, folder / f"clouds/start_{k}.npz")
        clouds.append(f"clouds/start_{k}.npz")
    return write_push_table(folder / TABLE, records, robot, duration, {obj.name: mesh_file},
                            [clouds[int(k)] for k in np.asarray(which).reshape(-1)])
