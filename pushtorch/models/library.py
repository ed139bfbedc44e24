"""A trained push model, its file format, and the model library with selection by H_r (paper, §TPMM, §Model Selection).

A :class:`PushModel` is what one training run produces (paper, Fig. pipeline, training): the manipulator
contact model and the position model of the training object (stage one) and one motion model per
action from the push records (stage two), with the settings used at prediction time. A
:class:`ModelLibrary` holds several (one per training object and prior) and selects, for a new cloud,
the one whose manipulator contact model has the lowest feature-distance heuristic ``H_r``.

Model files are ``.npz`` archives read with ``allow_pickle=False``: tensors plus one JSON header
(format name, version, settings, SHA-256 of every array). A file of another version, a corrupt file or
one whose arrays were edited is refused with :class:`~pushtorch.errors.RecordFormatError`.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.features import SurfaceFeatures, compute_surface_features
from pushtorch.models.contact import ManipulatorContactModel, fit_manipulator_contact_model
from pushtorch.models.frames import ContactFrames
from pushtorch.models.motion import MotionKernels, MotionModel, fit_motion_model
from pushtorch.models.position import PositionModel, fit_position_model
from pushtorch.objects import ObjectModel
from pushtorch.perception import capture_full_cloud

__all__ = ["FORMAT", "VERSION", "ModelLibrary", "ModelSettings", "PushModel", "load_model", "train_push_model"]

FORMAT = "pushtorch.push_model"
# 2: motion kernels expressed in the robot's start frame (version 1: at the contact point)
VERSION = 2


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
    motion_p_std: float = 0.01
    motion_rot_std: float = 0.05
    cutoff_std: float = 3.0
    alpha_t: float = 2.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
            zero_ok = f.name == "polish_steps"
            if not (numeric and (value >= 0 if zero_ok else value > 0)):
                kind = "a number >= 0" if zero_ok else "a positive number"
                raise InvalidParameterError(f"model setting {f.name} must be {kind}, got {value!r}")
        if int(self.polish_steps) != self.polish_steps:
            raise InvalidParameterError(f"polish_steps must be an integer >= 0, got {self.polish_steps!r}")
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

    @property
    def actions(self) -> torch.Tensor:
        """``(A, 2)`` the actions this model predicts (ẋ m/s, θ̇ rad/s)."""
        return torch.stack([m.action for m in self.motions])

    def action_index(self, action) -> int:
        """Index of the model's action nearest ``action`` (raises if none is within 1e-6)."""
        a = torch.as_tensor(action, dtype=self.actions.dtype).reshape(2)
        d = (self.actions - a).abs().amax(-1)
        i = int(d.argmin())
        if d[i] > 1e-6:
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
        """Write the model atomically to ``path`` (``.npz``, no pickle)."""
        from pushtorch.sim.records import atomic_write_bytes

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
            "sha256": {k: _digest(v) for k, v in arrays.items()},
        }
        buffer = io.BytesIO()
        np.savez(buffer, __header__=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buffer.getvalue())
        return path


def _digest(array: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update(f"{array.dtype.str}{array.shape}".encode())
    h.update(np.ascontiguousarray(array).tobytes())
    return h.hexdigest()


def load_model(path: str | Path, dtype: torch.dtype = torch.float32) -> PushModel:
    """Read a model file written by :meth:`PushModel.save` (no code runs on load).

    Raises:
        RecordFormatError: missing, unreadable, of another format or version, or any array whose
            checksum does not match the header (a corrupt or edited file).
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {k: archive[k] for k in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise RecordFormatError(f"{path} is not a readable pushtorch model file: {exc}") from exc
    try:
        header = json.loads(arrays.pop("__header__").tobytes().decode())
    except (KeyError, ValueError, UnicodeDecodeError) as exc:
        raise RecordFormatError(f"{path} has no valid pushtorch model header") from exc
    if header.get("format") != FORMAT:
        raise RecordFormatError(f"{path} is not a {FORMAT} file (format {header.get('format')!r})")
    if header.get("version") != VERSION:
        raise RecordFormatError(
            f"{path} is model format version {header.get('version')}, this pushtorch reads version {VERSION}"
        )
    expected = header.get("sha256", {})
    if set(expected) != set(arrays):
        raise RecordFormatError(f"{path}: the arrays in the file do not match its header (edited file?)")
    for name, array in arrays.items():
        if _digest(array) != expected[name]:
            raise RecordFormatError(f"{path}: array {name!r} fails its checksum (corrupt or edited file)")
    t = {k: torch.from_numpy(np.array(v)).to(dtype) for k, v in arrays.items()}
    motions = [
        MotionModel(
            t[f"motion{i}.action"],
            MotionKernels.from_arrays(t, f"motion{i}.manipulator"),
            MotionKernels.from_arrays(t, f"motion{i}.environment"),
            se3.Pose(t[f"motion{i}.mean_motion_p"], t[f"motion{i}.mean_motion_q"]),
        )
        for i in range(int(header["actions"]))
    ]
    return PushModel(
        name=header["name"],
        object_name=header["object_name"],
        settings=ModelSettings(**header["settings"]),
        contact=ManipulatorContactModel(
            ContactFrames.from_arrays(t, "contact"), header["contact"]["cutoff"], header["contact"]["drop_off"]
        ),
        position=PositionModel(ContactFrames.from_arrays(t, "position"), t["position.descriptor_std"]),
        motions=motions,
        meta=header.get("meta", {}),
    )


def training_features(obj: ObjectModel, settings: ModelSettings) -> tuple[se3.Pose, SurfaceFeatures]:
    """The object's training pose (upright at the origin, yaw 0) and its full-cloud features (world)."""
    pose = obj.resting_pose()
    cloud = capture_full_cloud(obj, pose, voxel_size=settings.voxel_size)
    return pose, compute_surface_features(cloud, radius=settings.feature_radius)


def _in_object_frame(features: SurfaceFeatures, pose: se3.Pose) -> SurfaceFeatures:
    """The same features expressed in the frame of ``pose`` (the training object's ``B^O``)."""
    inv = se3.inverse(pose)
    rotate = se3.Pose(torch.zeros_like(inv.p), inv.q)
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
    generator: torch.Generator | None = None,
    meta: dict | None = None,
) -> PushModel:
    """Train a model from an object and its push records (paper, Fig. pipeline, both training stages).

    The manipulator contact model is learnt at the nominal training placement (bumper flat against the
    side facing the robot, centred: :func:`pushtorch.sim.push.place_robot_against`); the records, whose
    placements may be jittered, train the motion models.

    Args:
        obj: the training object.
        records: :class:`pushtorch.sim.records.PushRecords` of this object (invalid pushes are skipped).
        settings: model settings (default: the paper's).
    Raises:
        InvalidParameterError: no valid record.
    """
    from pushtorch.robot import bumper_mesh
    from pushtorch.sim.push import place_robot_against

    settings = settings or ModelSettings()
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
    return PushModel(name or obj.name, obj.name, settings, contact, position, motions, meta or {})


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
