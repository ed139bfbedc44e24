"""A trained push model, its file format, and the model library with selection by H_r (paper, §TPMM, §Model Selection).

A :class:`PushModel` is what one training run produces (paper, Fig. pipeline, training): the manipulator
contact model and the position model of the training object (stage one) and one motion model per
action from the push records (stage two), with the settings used at prediction time. A
:class:`ModelLibrary` holds several (one per training object and prior) and selects, for a new cloud,
the one whose manipulator contact model has the lowest feature-distance heuristic ``H_r``.

Model files are ``.npz`` archives read with ``allow_pickle=False``: tensors plus one JSON header
(format name, version, settings, SHA-256 of every array), sealed by one SHA-256 over every byte of the
archive before it, kept as the archive's 64-character zip comment (:func:`pushtorch.io.sealed_archive`).
Any edited byte (an array, the header's action count or a setting, the zip structure) breaks the seal. A
file of another version, a corrupt, edited or malformed file, or one whose settings construction would
refuse is refused with :class:`~pushtorch.errors.RecordFormatError`. Saving is atomic; the temporaries a
killed save leaves are removed by the next save to the same path, under the folder's lock
(:func:`pushtorch.io.folder_lock`).
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.io import atomic_write_bytes, folder_lock, read_sealed_archive, sealed_archive, temporary_files
from pushtorch.models.contact import ManipulatorContactModel, fit_manipulator_contact_model
from pushtorch.models.frames import ContactFrames
from pushtorch.models.motion import MotionKernels, MotionModel, fit_motion_model
from pushtorch.models.position import PositionModel, fit_position_model
from pushtorch.objects import ObjectModel
from pushtorch.perception import capture_full_cloud

__all__ = [
    "DEFAULT_SEED",
    "FORMAT",
    "VERSION",
    "ModelLibrary",
    "ModelSettings",
    "PushModel",
    "as_generator",
    "check_action",
    "load_model",
    "train_push_model",
]

FORMAT = "pushtorch.push_model"
# 4: motion kernels carry their push's contact patch on the bumper, and the settings the expert exponents
# and the bandwidths chosen from data (issue 17); 3: the whole file sealed by one SHA-256 and a
# partial_data header field (2: only the arrays were checksummed; motion kernels in the robot's start
# frame since 2, at the contact point in 1)
VERSION = 4


@dataclass(frozen=True)
class ModelSettings:
    """Every number of training and prediction; defaults are the paper's (tables) or lineage's.

    Lengths in m, angles in rad, curvature stds in the embedded descriptor space
    (:func:`pushtorch.models.frames.embed_descriptors`).
    """

    # surface features (paper: Surface Features; lineage radius 0.005–0.015 m)
    voxel_size: float = 0.004
    feature_radius: float = 0.012
    # manipulator contact model (paper tables: Distance 0.01, Lambda 100)
    contact_cutoff: float = 0.01
    contact_drop_off: float = 100.0
    # motion model training (paper: 10 environment contacts per push)
    environment_contacts_training: int = 10
    manipulator_kernels_per_push: int = 1
    # prediction (paper tables: 5 environment contacts, 100 samples each, 5000 / 500 kernels)
    environment_contacts: int = 5
    environment_samples: int = 100
    environment_kernels: int = 5000
    manipulator_kernels: int = 500
    # query densities (paper, pose estimation table: 3000 kernels, 500 candidates x 100 steps)
    query_kernels: int = 3000
    position_frames: int = 3000  # uniform subset of the training features kept as position frames
    anneal_candidates: int = 500
    anneal_steps: int = 100
    # the fast path (method="fast") anneals for this fraction of anneal_steps, then moves every candidate
    # to its local mode by polish_steps mean-shift steps (docs/method.md: as accurate as the full schedule
    # on tools/bench_predict.py, a little less on the hardest pose); the dense reference runs it in full
    fast_anneal_fraction: float = 0.3
    polish_steps: int = 3
    descriptor_std: float = 0.5
    descriptor_cutoff_std: float = 5.0
    query_p_std: float = 0.01
    query_rot_std: float = 0.1
    # contact-frame kernel K^c over (u, r) and motion kernels over final poses
    contact_p_std: float = 0.02
    contact_rot_std: float = 0.3
    contact_robot_std: float = 0.05  # m, frame position in the robot's start frame (motion model)
    contact_patch_std: float = 0.02  # m, the push's contact patch on the bumper: its lateral extent
    contact_patch_yaw_std: float = 0.05  # rad, ... and its heading (motion model)
    motion_p_std: float = 0.01
    motion_rot_std: float = 0.05
    # Σ of the experts' exponents (w^P normalised; 1: a logarithmic opinion pool, docs/method.md)
    pool_sharpness: float = 1.0
    # k of the k-fold search that chooses the motion and contact bandwidths from the training pushes
    # (pushtorch.models.bandwidth); 0 keeps the values above
    bandwidth_folds: int = 5
    cutoff_std: float = 3.0
    alpha_t: float = 2.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
            zero_ok = f.name in ("polish_steps", "bandwidth_folds")
            if not (numeric and (value >= 0 if zero_ok else value > 0)):
                kind = "a number >= 0" if zero_ok else "a positive number"
                raise InvalidParameterError(f"model setting {f.name} must be {kind}, got {value!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "int":  # a count: 2.5 kernels would be silently floored
                if int(value) != value:
                    raise InvalidParameterError(f"model setting {f.name} must be an integer, got {value!r}")
                object.__setattr__(self, f.name, int(value))  # 3000.0 from a config is the count 3000
        if self.fast_anneal_fraction > 1:
            raise InvalidParameterError(f"fast_anneal_fraction must be in (0, 1], got {self.fast_anneal_fraction}")
        if self.alpha_t <= 1:
            raise InvalidParameterError(f"alpha_t must be > 1, got {self.alpha_t}")

    @property
    def fast_anneal_steps(self) -> int:
        """Annealing steps of the fast path: ``fast_anneal_fraction`` of ``anneal_steps`` (at least 1)."""
        return max(1, round(self.anneal_steps * self.fast_anneal_fraction))

    @staticmethod
    def from_mapping(mapping) -> ModelSettings:
        """Settings from a dict / Hydra node; unknown keys are an error (a typo would be silent)."""
        known = {f.name for f in fields(ModelSettings)}
        if not isinstance(mapping, Mapping):
            raise InvalidParameterError(f"model settings must be a mapping of names to numbers, got {mapping!r}")
        extra = set(mapping) - known
        if extra:
            raise InvalidParameterError(f"unknown model settings: {sorted(extra)}; known: {sorted(known)}")
        return ModelSettings(**dict(mapping))


@dataclass
class PushModel:
    """A trained model: contact, position and per-action motion models of one object and prior."""

    name: str
    object_name: str
    settings: ModelSettings
    contact: ManipulatorContactModel
    position: PositionModel
    motions: list[MotionModel]
    meta: dict = field(default_factory=dict)
    #: None when trained on every push its runs promised; else what was missing (``train(allow_partial)``)
    partial_data: dict | None = None

    @property
    def device(self) -> torch.device:
        """Where the model's tensors are (prediction runs there; open3d's steps stay on the CPU)."""
        return self.position.frames.r.device

    @property
    def dtype(self) -> torch.dtype:
        """The floating dtype of the model's tensors (clouds are cast to it)."""
        return self.position.frames.r.dtype

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> PushModel:
        """A copy of the model on ``device`` and in the floating ``dtype`` (``Module.to``'s arguments by name).

        Raises:
            InvalidParameterError: a dtype that is not floating.
        """
        if dtype is not None and not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise InvalidParameterError(f"a model's dtype must be a floating torch dtype, got {dtype!r}")
        contact = ManipulatorContactModel(self.contact.frames.to(device, dtype), self.contact.cutoff,
                                          self.contact.drop_off)
        position = PositionModel(self.position.frames.to(device, dtype),
                                 self.position.descriptor_std.to(device, dtype))
        return replace(self, contact=contact, position=position,
                       motions=[m.to(device, dtype) for m in self.motions], meta=dict(self.meta))

    @property
    def configured_settings(self) -> ModelSettings:
        """The settings this model was trained with, before the bandwidth search replaced the values it
        chose (``meta["bandwidths"]``; :mod:`pushtorch.models.bandwidth`)."""
        search = self.meta.get("bandwidths")
        return replace(self.settings, **search["start"]) if search else self.settings

    @property
    def actions(self) -> torch.Tensor:
        """``(A, 2)`` the actions this model predicts (ẋ m/s, θ̇ rad/s)."""
        return torch.stack([m.action for m in self.motions])

    def action_index(self, action) -> int:
        """Index of the model's action equal to ``action`` within 1e-6.

        Raises:
            InvalidParameterError: not two finite numbers, or an action the model was not trained for.
        """
        a = check_action(action).to(self.actions.dtype)
        d = (self.actions - a).abs().amax(-1)
        i = int(d.argmin())
        if not d[i] <= 1e-6:
            raise InvalidParameterError(
                f"model {self.name!r} was not trained for action {a.tolist()}; it knows {self.actions.tolist()}"
            )
        return i

    # -- files ---------------------------------------------------------------------------------

    def arrays(self) -> dict[str, torch.Tensor]:
        out = {}
        out.update(self.contact.frames.arrays("contact"))
        out.update(self.position.frames.arrays("position"))
        out["position.descriptor_std"] = self.position.descriptor_std
        for i, m in enumerate(self.motions):
            out[f"motion{i}.action"] = m.action
            out.update(m.manipulator.arrays(f"motion{i}.manipulator"))
            out.update(m.environment.arrays(f"motion{i}.environment"))
            out[f"motion{i}.mean_motion_p"], out[f"motion{i}.mean_motion_q"] = m.mean_motion
        return out

    def save(self, path: str | Path) -> Path:
        """Write the model atomically to ``path`` (sealed ``.npz``, no pickle).

        Saves to one folder are serialised by a lock on the folder, under which the temporaries a
        killed save to ``path`` left behind are removed.
        """
        arrays = {k: v.detach().cpu().numpy() for k, v in self.arrays().items()}
        header = {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            "object_name": self.object_name,
            "settings": asdict(self.settings),
            "contact": {"cutoff": self.contact.cutoff, "drop_off": self.contact.drop_off},
            "actions": len(self.motions),
            "meta": self.meta,
            "partial_data": self.partial_data,
            "sha256": {k: _digest(v) for k, v in arrays.items()},
        }
        data = _model_archive(header, arrays)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with folder_lock(path.parent):  # no other save to this folder is mid-write now
            for orphan in temporary_files(path.parent, path.name):
                orphan.unlink(missing_ok=True)
            atomic_write_bytes(path, data)
        return path


def check_action(action) -> torch.Tensor:
    """``action`` as a float64 ``(2,)`` tensor (ẋ m/s, θ̇ rad/s), or a clear error.

    Raises:
        InvalidParameterError: not numeric, not exactly two numbers, or NaN/infinite.
    """
    try:
        a = torch.as_tensor(action, dtype=torch.float64) if not isinstance(action, torch.Tensor) else action
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InvalidParameterError(f"an action must be two numbers (ẋ m/s, θ̇ rad/s), got {action!r}") from exc
    if a.is_complex() or a.dtype == torch.bool or a.numel() != 2:
        raise InvalidParameterError(
            f"an action must be two real numbers (ẋ m/s, θ̇ rad/s), got shape {tuple(a.shape)} of {a.dtype}"
        )
    a = a.detach().reshape(2).to(torch.float64)
    if not torch.isfinite(a).all():
        raise InvalidParameterError(f"an action must be finite, got {a.tolist()}")
    return a


def _model_archive(header: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """The sealed ``.npz`` bytes of a model file: ``header`` (JSON) and ``arrays``."""
    buffer = io.BytesIO()
    np.savez(buffer, __header__=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
    return sealed_archive(buffer.getvalue())


#: The seed of the generator a function that draws random numbers uses when given none: results never depend
#: on torch's global random state (issue 23, "reproducible by default").
DEFAULT_SEED = 0


def as_generator(generator: torch.Generator | int | None, device: torch.device | str | None = None
                 ) -> torch.Generator:
    """A ``torch.Generator`` as given, a new one seeded with an int, or (None) a new one seeded with
    :data:`DEFAULT_SEED`: never torch's global stream, so a call without a generator is reproducible. New
    generators are made for ``device`` (default the CPU).

    Raises:
        InvalidParameterError: anything else (a float, a string, a negative or too large seed).
    """
    if generator is None:
        return torch.Generator(device=device or "cpu").manual_seed(DEFAULT_SEED)
    if isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, int | np.integer) and not isinstance(generator, bool):
        if not 0 <= int(generator) < 2**64:
            raise InvalidParameterError(f"a seed must be an integer in [0, 2**64), got {generator}")
        return torch.Generator(device=device or "cpu").manual_seed(int(generator))
    raise InvalidParameterError(
        f"generator must be a torch.Generator or an integer seed, got {type(generator).__name__} {generator!r}"
    )


def _digest(array: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(f"{array.dtype.str}{array.shape}".encode())
    h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


def load_model(path: str | Path, dtype: torch.dtype = torch.float32,
               map_location: torch.device | str | None = None) -> PushModel:
    """Read a model file written by :meth:`PushModel.save` (no code runs on load), in ``dtype`` on
    ``map_location`` (default the CPU).

    Raises:
        RecordFormatError: missing, unreadable, of another format or version, a broken seal or array
            checksum (a corrupt or edited file), a malformed header, or settings that
            :class:`ModelSettings` refuses.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise RecordFormatError(f"{path} is not a readable pushtorch model file: {exc.strerror or exc}") from exc
    _refuse_other_files(path, data)
    version = _format_version(data)
    if version is not None and version != VERSION:  # before the seal: older versions have none
        raise RecordFormatError(
            f"{path} is model format version {version}, this pushtorch reads version {VERSION}: "
            "retrain the model with this version (python -m pushtorch.train ...)"
        )
    archive_bytes = read_sealed_archive(data, path, sealed="the header and every array",
                                        remedy="retrain or restore the model")
    try:
        with np.load(io.BytesIO(archive_bytes), allow_pickle=False) as archive:
            arrays = {k: archive[k] for k in archive.files}
    except Exception as exc:  # zipfile, numpy format and pickle refusals alike
        raise RecordFormatError(f"{path} is not a readable pushtorch model file: {exc}") from exc
    try:
        header = json.loads(arrays.pop("__header__").tobytes().decode())
    except (KeyError, ValueError, UnicodeDecodeError) as exc:
        raise RecordFormatError(f"{path} has no valid pushtorch model header") from exc
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        kind = header.get("format") if isinstance(header, dict) else type(header).__name__
        raise RecordFormatError(f"{path} is not a {FORMAT} file (format {kind!r})")
    if header.get("version") != VERSION:
        raise RecordFormatError(
            f"{path} is model format version {header.get('version')}, this pushtorch reads version {VERSION}"
        )
    expected = header.get("sha256")
    if not isinstance(expected, dict) or set(expected) != set(arrays):
        raise RecordFormatError(f"{path}: the arrays in the file do not match its header (edited file?)")
    for name, array in arrays.items():
        if _digest(array) != expected[name]:
            raise RecordFormatError(f"{path}: array {name!r} fails its checksum (corrupt or edited file)")
    try:
        model = _model_from(header, arrays, dtype)
        return model if map_location is None else model.to(device=map_location)
    except InvalidParameterError as exc:
        raise RecordFormatError(f"{path} holds settings this pushtorch refuses: {exc}") from exc
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError) as exc:
        raise RecordFormatError(f"{path} has a malformed header or arrays ({type(exc).__name__}: {exc})") from exc


def _refuse_other_files(path: Path, data: bytes) -> None:
    """A clear error for a file that was never a model (before the seal check would call it edited)."""
    import zipfile

    if not data.startswith(b"PK\x03\x04"):
        raise RecordFormatError(f"{path} is not a pushtorch model file (not an .npz archive)")
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            names = set(archive.namelist())
    except zipfile.BadZipFile:
        return  # a damaged model: the seal check names it
    if "__header__.npy" not in names:
        raise RecordFormatError(f"{path} is not a pushtorch model file (an .npz without a model header: a push-record"
                                " shard or another archive?)")


def _format_version(data: bytes) -> object:
    """The version in the header of a model file of this format, or None (not one, or unreadable)."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            header = json.loads(archive["__header__"].tobytes().decode())
        return header.get("version") if header.get("format") == FORMAT else None
    except Exception:  # anything unreadable is reported after the seal check
        return None


def _model_from(header: dict, arrays: dict[str, np.ndarray], dtype: torch.dtype) -> PushModel:
    """Build the model of a checked file; every header field is type-checked here, so a malformed one
    raises a KeyError/TypeError/ValueError that :func:`load_model` reports as a RecordFormatError."""

    def typed(key: str, kind: type | tuple[type, ...]):
        value = header[key]
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise TypeError(f"header field {key!r} must be {kind}, got {value!r}")
        return value

    n_actions = typed("actions", int)
    motion_arrays = {k.split(".", 1)[0] for k in arrays if k.startswith("motion")}
    if n_actions < 1 or motion_arrays != {f"motion{i}" for i in range(n_actions)}:
        raise ValueError(f"the header's action count {n_actions} does not match the arrays' motion models"
                         f" {sorted(motion_arrays)}")
    contact = typed("contact", dict)
    cutoff, drop_off = contact["cutoff"], contact["drop_off"]
    for key, value in (("contact.cutoff", cutoff), ("contact.drop_off", drop_off)):
        if not isinstance(value, int | float) or isinstance(value, bool) or not np.isfinite(value) or value <= 0:
            raise ValueError(f"header field {key} must be a positive number, got {value!r}")
    partial = header.get("partial_data")
    if partial is not None and not isinstance(partial, dict):
        raise TypeError(f"header field 'partial_data' must be null or an object, got {partial!r}")
    settings = ModelSettings.from_mapping(typed("settings", dict))
    t = {k: torch.from_numpy(np.array(v)).to(dtype) for k, v in arrays.items()}
    motions = [
        MotionModel(
            t[f"motion{i}.action"],
            MotionKernels.from_arrays(t, f"motion{i}.manipulator"),
            MotionKernels.from_arrays(t, f"motion{i}.environment"),
            se3.Pose.unchecked(t[f"motion{i}.mean_motion_p"], t[f"motion{i}.mean_motion_q"]),
        )
        for i in range(n_actions)
    ]
    for m in motions:
        check_action(m.action)
    return PushModel(
        name=typed("name", str),
        object_name=typed("object_name", str),
        settings=settings,
        contact=ManipulatorContactModel(ContactFrames.from_arrays(t, "contact"), cutoff, drop_off),
        position=PositionModel(ContactFrames.from_arrays(t, "position"), t["position.descriptor_std"]),
        motions=motions,
        meta=typed("meta", dict),
        partial_data=partial,
    )


def training_features(obj: ObjectModel, settings: ModelSettings) -> tuple[se3.Pose, SurfaceFeatures]:
    """The object's training pose (upright at the origin, yaw 0) and its full-cloud features (world)."""
    pose = obj.resting_pose()
    cloud = capture_full_cloud(obj, pose, voxel_size=settings.voxel_size)
    return pose, compute_surface_features(cloud, radius=settings.feature_radius)


def _in_object_frame(features: SurfaceFeatures, pose: se3.Pose) -> SurfaceFeatures:
    """The same features expressed in the frame of ``pose`` (the training object's ``B^O``)."""
    inv = se3.inverse(pose)
    rotate = se3.Pose.unchecked(torch.zeros_like(inv.p), inv.q)
    frames = se3.compose(inv, features.pose)
    return SurfaceFeatures(
        p=frames.p, q=frames.q, r=features.r, normal=se3.apply(rotate, features.normal),
        k1=se3.apply(rotate, features.k1), k2=se3.apply(rotate, features.k2), index=features.index,
    )


def train_push_model(
    obj: ObjectModel,
    records,
    settings: ModelSettings | None = None,
    name: str | None = None,
    generator: torch.Generator | int | None = None,
    meta: dict | None = None,
    partial_data: dict | None = None,
) -> PushModel:
    """Train a model from an object and its push records (paper, Fig. pipeline, both training stages).

    The manipulator contact model is learnt at the nominal training placement (bumper flat against the
    side facing the robot, centred: :func:`pushtorch.sim.push.place_robot_against`); the records, whose
    placements may be jittered, train the motion models.

    Args:
        obj: the training object.
        records: :class:`pushtorch.sim.records.PushRecords` of this object (invalid pushes are skipped).
        settings: model settings (default: the paper's).
        generator: a seeded ``torch.Generator`` or an int seed (None: seeded with :data:`DEFAULT_SEED`, so
            training is reproducible).
        partial_data: set when the records are only part of their runs (kept in the model file).
    Raises:
        InvalidParameterError: no valid record.
    """
    from pushtorch.models.bandwidth import select_bandwidths
    from pushtorch.robot import bumper_mesh
    from pushtorch.sim.push import place_robot_against

    settings = settings or ModelSettings()
    generator = as_generator(generator)
    valid = records.take(records.valid)
    if len(valid) == 0:
        raise InvalidParameterError("no valid push record (every push tipped, lifted or missed the object)")
    valid = valid.to(torch.float32)
    pose, features = training_features(obj, settings)
    # the contact model is learnt at the nominal placement; the records' jittered placements only
    # enter the motion model
    robot_pose = place_robot_against(obj.mesh, pose)
    contact = fit_manipulator_contact_model(
        features, pose, robot_pose, bumper_mesh(robot_pose),
        cutoff=settings.contact_cutoff, drop_off=settings.contact_drop_off,
    )
    keep = torch.randperm(len(features), generator=generator)[: settings.position_frames]
    position = fit_position_model(features.select(keep.sort().values), pose)
    features_object = _in_object_frame(features, pose)
    motions = []
    for a in torch.unique(valid.action_index).tolist():
        sel = valid.take(valid.action_index == a)
        motions.append(
            fit_motion_model(
                features_object, sel.object_initial, sel.object_final, sel.robot_start, bumper_mesh(se3.identity()),
                sel.action[0], settings.environment_contacts_training, settings.manipulator_kernels_per_push,
                settings.contact_cutoff, settings.contact_drop_off, generator,
            )
        )
    meta = dict(meta or {})
    if settings.bandwidth_folds >= 2:
        settings, search = select_bandwidths(settings, motions, settings.bandwidth_folds, generator)
        meta["bandwidths"] = search.as_meta()
    return PushModel(name or obj.name, obj.name, settings, contact, position, motions, meta, partial_data)


class ModelLibrary:
    """Several trained models; :meth:`select` picks one for a cloud by the lowest ``H_r``."""

    def __init__(self, models: list[PushModel]) -> None:
        if not models:
            raise InvalidParameterError("a model library needs at least one model")
        self.models = list(models)

    def __len__(self) -> int:
        return len(self.models)

    def feature_distances(self, features: SurfaceFeatures) -> torch.Tensor:
        """``H_r`` of every model's manipulator contact model on the cloud's features, ``(L,)``."""
        from pushtorch.models.query import feature_distance_heuristic, heuristic_descriptors

        r = heuristic_descriptors(features)
        return torch.stack([feature_distance_heuristic(r, m.contact.frames.r) for m in self.models])

    def select(self, features: SurfaceFeatures) -> tuple[PushModel, torch.Tensor]:
        """The model with the lowest ``H_r`` and all models' ``H_r``."""
        h = self.feature_distances(features)
        return self.models[int(h.argmin())], h
