"""A trained push model and its file format (paper, Fig. pipeline, training: the manipulator contact and
position models of one training object and one motion model per action).

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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.io import atomic_write_bytes, folder_lock, read_sealed_archive, sealed_archive, temporary_files
from pushtorch.models.conditioning import (
    Observation,
    PhysicsPosterior,
    PosteriorSummary,
    kernel_physics,
    new_posterior,
    summarise,
)
from pushtorch.models.contact import ManipulatorContactModel
from pushtorch.models.evidence import condition_model
from pushtorch.models.frames import ContactFrames
from pushtorch.models.motion import MotionKernels, MotionModel
from pushtorch.models.position import PositionModel
from pushtorch.models.settings import ModelSettings, as_generator, check_action

__all__ = [
    "FORMAT",
    "PushModel",
    "VERSION",
    "load_model",
    "model_from_parts",
    "read_model_file",
    "write_model_file",
]


FORMAT = "pushtorch.push_model"


# 5: every motion kernel keeps the ground friction and mass of its push (``.physics``), a conditioned model its
# kernels' log weights (``.log_weight``) and its posterior (``posterior.*``); 4: motion kernels carry their
# push's contact patch on the bumper, and the settings the expert exponents and the bandwidths chosen from data;
# 3: the whole file sealed by one SHA-256 and a partial_data header field (2: only the arrays were checksummed;
# motion kernels in the robot's start frame since 2, at the contact point in 1)
VERSION = 5


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
    #: the posterior over friction and mass a conditioned model holds (:meth:`condition_on`), else None
    physics_posterior: PhysicsPosterior | None = None

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

    # -- online adaptation ---------------------------------------------------------------------

    @property
    def motion_kernels(self) -> list[MotionKernels]:
        """Every action's motion kernels, manipulator then environment, action by action: the order a
        conditioned model's kernel weights follow (:mod:`pushtorch.models.conditioning`)."""
        return [k for m in self.motions for k in (m.manipulator, m.environment)]

    def condition_on(self, observations: Observation | list[Observation], seed: int | None = None,
                     prior: tuple | None = None, bandwidth=None) -> PushModel:
        """This model conditioned on observed pushes of the object it will predict
        (:mod:`pushtorch.models.conditioning`): its kernels re-weighted by a posterior over the friction and
        mass their pushes were simulated with. ``predict``, ``predict_many`` and the density take it unchanged.

        Conditioning is sequential: ``m.condition_on([a]).condition_on([b])`` equals ``m.condition_on([a, b])``.

        Args:
            observations: :class:`~pushtorch.models.conditioning.Observation` s (one or a list; may be empty), or
                a push table's rows (a :class:`~pushtorch.sim.tables.PushTable`, every row with its cloud:
                :func:`~pushtorch.models.conditioning.observations_from_table`).
            seed: the seed of the observations' push conditions (default: the posterior's, or 0).
            prior: ``(friction prior, mass prior)`` (:mod:`pushtorch.sim.priors`): de-bias the kernels towards
                the training prior rather than where they crowd; only on a model not yet conditioned.
            bandwidth: the motion kernels the observations are scored under: an
                :class:`~pushtorch.models.evidence.EvidenceKernels` (the density's width with its outlier share)
                or a :class:`~pushtorch.kde.KernelBandwidth` (those kernels alone); default the model's own
                (a library passes its models' common kernels).

        Raises:
            ModelError: kernels that do not know their physics (retrain), or an observation whose push
                condition cannot be built (its robot start does not touch the cloud).
            InvalidParameterError: an observation of an action the model was not trained for, or a malformed one.
        """
        return condition_model(self, observations, seed, prior, bandwidth)

    def posterior(self, n: int = 256, generator: torch.Generator | int | None = None) -> PosteriorSummary:
        """The posterior over ``(μ, m)`` this model holds (the kernels' own spread before any observation):
        ``n`` draws, the mean and spread of ``μ`` and of ``log m`` (:class:`PosteriorSummary`)."""
        kernels = self.motion_kernels
        theta = kernel_physics(kernels)
        post = self.physics_posterior or new_posterior(kernels)
        log_w, tau = post.kernel_log_weights(theta)
        return summarise(theta, log_w, n, as_generator(generator), post.observed, post.rejected, tau)

    @property
    def configured_settings(self) -> ModelSettings:
        """The settings this model was trained with, before the bandwidth search, a pooled model's kernel budget
        and its widening search replaced the values they chose (``meta["bandwidths"]``,
        :mod:`pushtorch.models.bandwidth`; ``meta["budget"]``, :mod:`pushtorch.models.pooled`; ``meta["widening"]``,
        :mod:`pushtorch.evaluation.transfer`)."""
        start = {}
        # pushtorch.models.bandwidth, a pooled model's kernel budget, pushtorch.evaluation.transfer
        for searched in ("bandwidths", "budget", "widening"):
            if self.meta.get(searched):
                start.update(self.meta[searched]["start"])
        return replace(self.settings, **start) if start else self.settings

    @property
    def actions(self) -> torch.Tensor:
        """``(A, 2)`` the actions this model predicts (ẋ m/s, θ̇ rad/s)."""
        return torch.stack([m.action for m in self.motions])

    def action_index(self, action) -> int:
        """Index of the model's action equal to ``action`` within 1e-6.

        Raises:
            InvalidParameterError: not two finite numbers, or an action the model was not trained for.
        """
        a = check_action(action).to(self.actions)  # dtype and device: a CPU action for a model on the GPU
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
        if self.physics_posterior is not None:
            out.update(self.physics_posterior.arrays())
        return out

    def save(self, path: str | Path) -> Path:
        """Write the model atomically to ``path`` (sealed ``.npz``, no pickle).

        Saves to one folder are serialised by a lock on the folder, under which the temporaries a
        killed save to ``path`` left behind are removed.
        """
        return write_model_file(path, *self.file_parts())

    def file_parts(self, extra_arrays: dict[str, torch.Tensor] | None = None,
                   extra_header: dict | None = None) -> tuple[dict, dict[str, np.ndarray]]:
        """The header and arrays of this model's file, with ``extra_arrays`` and ``extra_header`` fields (a
        model built on this one, as the residual model, keeps its own parts in the same sealed file)."""
        tensors = {**self.arrays(), **(extra_arrays or {})}
        arrays = {k: v.detach().cpu().numpy() for k, v in tensors.items()}
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
            "posterior": None if self.physics_posterior is None else self.physics_posterior.header(),
            **(extra_header or {}),
            "sha256": {k: _digest(v) for k, v in arrays.items()},
        }
        return header, arrays


def write_model_file(path: str | Path, header: dict, arrays: dict[str, np.ndarray]) -> Path:
    """Write a model file's ``header`` and ``arrays`` atomically to ``path`` (:meth:`PushModel.save`)."""
    data = _model_archive(header, arrays)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(path.parent):  # no other save to this folder is mid-write now
        for orphan in temporary_files(path.parent, path.name):
            orphan.unlink(missing_ok=True)
        atomic_write_bytes(path, data)
    return path


def _model_archive(header: dict, arrays: dict[str, np.ndarray]) -> bytes:
    """The sealed ``.npz`` bytes of a model file: ``header`` (JSON) and ``arrays``."""
    buffer = io.BytesIO()
    np.savez(buffer, __header__=np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), **arrays)
    return sealed_archive(buffer.getvalue())


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
    header, arrays = read_model_file(path)
    try:
        model = model_from_parts(header, arrays, dtype)
        return model if map_location is None else model.to(device=map_location)
    except InvalidParameterError as exc:
        raise RecordFormatError(f"{path} holds settings this pushtorch refuses: {exc}") from exc
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError) as exc:
        raise RecordFormatError(f"{path} has a malformed header or arrays ({type(exc).__name__}: {exc})") from exc


def read_model_file(path: str | Path) -> tuple[dict, dict[str, np.ndarray]]:
    """The checked header and arrays of a model file (:func:`load_model`'s refusals, before any model is built).

    Raises:
        RecordFormatError: as :func:`load_model`.
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
            "retrain the model with this version (pushtorch-train ...)"
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
    return header, arrays


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


def model_from_parts(header: dict, arrays: dict[str, np.ndarray], dtype: torch.dtype) -> PushModel:
    """Build the model of a checked file's header and arrays (:func:`read_model_file`); every header field is
    type-checked here, so a malformed one raises a KeyError/TypeError/ValueError that :func:`load_model` reports
    as a RecordFormatError."""

    def typed(key: str, kind: type | tuple[type, ...]):
        value = header[key]
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            raise TypeError(f"header field {key!r} must be {kind}, got {value!r}")
        return value

    n_actions = typed("actions", int)
    motion_arrays = {k.split(".", 1)[0] for k in arrays if k.startswith("motion")}
    posterior = header.get("posterior")
    if posterior is not None and not isinstance(posterior, dict):
        raise TypeError(f"header field 'posterior' must be null or an object, got {posterior!r}")
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
        physics_posterior=None if posterior is None else PhysicsPosterior.from_file(
            posterior, {k: torch.from_numpy(np.array(v)) for k, v in arrays.items() if k.startswith("posterior.")}),
    )
