"""Reading a residual model's file (:meth:`pushtorch.models.residual.ResidualModel.save`): the push model's sealed
file with the residuals' arrays and the ``residual`` header, checked field by field (beyond the paper, as the
residual model is: its §Conclusions and future work).
"""

from __future__ import annotations

import math

import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, RecordFormatError
from pushtorch.kde import KernelBandwidth
from pushtorch.models.model import PushModel, load_model, model_from_parts, read_model_file
from pushtorch.models.residual import POINTS, ResidualModel
from pushtorch.sim.engines import engine_version
from pushtorch.sim.settings import SimSettings

__all__ = ["load_any_model", "load_residual_model"]


def load_residual_model(path, dtype: torch.dtype = torch.float32, other_engine: bool = False) -> ResidualModel:
    """Read a residual model file (:meth:`ResidualModel.save`).

    Args:
        other_engine: load it even where the installed rollout engine's version is not the one it was trained
            against (its residuals correct that version's outcomes).

    Raises:
        RecordFormatError: as :func:`~pushtorch.models.model.load_model`; a push model's file without residuals;
            a file of another engine version, unless ``other_engine``.
    """
    header, arrays = read_model_file(path)
    if not isinstance(header.get("residual"), dict):
        raise RecordFormatError(f"{path} is a push model without residuals: load it with load_model")
    return _residual_from_parts(path, header, arrays, dtype, other_engine)


def load_any_model(path, dtype: torch.dtype = torch.float32, other_engine: bool = False) -> PushModel | ResidualModel:
    """A model file as what it holds: a :class:`ResidualModel` where it has residuals
    (:func:`load_residual_model`), else the :class:`PushModel` (:func:`~pushtorch.models.model.load_model`).
    What the predict app reads its ``models`` with."""
    header, arrays = read_model_file(path)
    if isinstance(header.get("residual"), dict):
        return _residual_from_parts(path, header, arrays, dtype, other_engine)
    return load_model(path, dtype)  # its own checks and messages


def _residual_from_parts(path, header: dict, arrays: dict, dtype: torch.dtype, other_engine: bool) -> ResidualModel:
    spec = header["residual"]
    try:
        sim = SimSettings(**spec["sim"])
        installed = engine_version(sim.engine)
        if installed != spec["engine_version"] and not other_engine:
            raise RecordFormatError(f"{path} was trained against {spec['engine_version']}, this machine has "
                                    f"{installed}: its residuals correct the other's outcomes (other_engine=True "
                                    "loads it anyway)")
        model = model_from_parts(header, {k: v for k, v in arrays.items() if not k.startswith("residual")}, dtype)
        residuals = [se3.Pose.unchecked(torch.from_numpy(arrays[f"residual{a}.p"]).to(dtype),
                                        torch.from_numpy(arrays[f"residual{a}.q"]).to(dtype))
                     for a in range(len(model.motions))]
        for r, m in zip(residuals, model.motions, strict=True):
            if r.p.shape != (len(m.manipulator), 3) or r.q.shape != (len(m.manipulator), 4):
                raise ValueError("the residuals do not match the manipulator kernels")
        bandwidth = KernelBandwidth(float(spec["p_std"]), float(spec["rot_std"]),
                                    cutoff_std=(math.inf, math.inf, math.inf), alpha_t=model.settings.alpha_t)
        shapes = None
        if "residual0.shape" in arrays:
            shapes = [torch.from_numpy(arrays[f"residual{a}.shape"]).to(torch.int64) for a in range(len(residuals))]
            if any(s.shape != (len(r.p),) for s, r in zip(shapes, residuals, strict=True)):
                raise ValueError("the residual kernels' shapes do not match the kernels")
        widening = float(spec.get("widening", 0.0))
        if not math.isfinite(widening) or widening < 0:
            raise ValueError(f"a widening of {widening}")
        outcomes = None
        if "residual0.outcome" in arrays:
            outcomes = [torch.from_numpy(arrays[f"residual{a}.outcome"]).double() for a in range(len(residuals))]
            if any(o.shape != (len(r.p), 3) for o, r in zip(outcomes, residuals, strict=True)):
                raise ValueError("the residual kernels' rollout outcomes do not match the kernels")
        width = math.inf if spec.get("outcome_width") is None else float(spec["outcome_width"])
        if not width > 0:
            raise ValueError(f"an outcome width of {width}")
        novelty = float(spec.get("novelty_widening", 0.0))
        if not math.isfinite(novelty) or novelty < 0:
            raise ValueError(f"a novelty widening of {novelty}")
        defensive = tuple(float(v) for v in spec.get("defensive", (0.0, 0.0, 0.0)))
        if len(defensive) != 3 or not (0.0 <= defensive[0] < 1.0 and all(math.isfinite(v) and v >= 0
                                                                          for v in defensive)):
            raise ValueError(f"a defensive part {defensive}")
        uncorrected = float(spec.get("uncorrected", 0.0))
        if not math.isfinite(uncorrected) or uncorrected < 0:
            raise ValueError(f"an uncorrected share's rate of {uncorrected}")
        weight = float(spec.get("disagreement", 0.0))
        if not math.isfinite(weight) or weight < 0:
            raise ValueError(f"a disagreement weight of {weight}")
        point = str(spec.get("point", "corrected"))
        if point not in POINTS:
            raise ValueError(f"a point prediction {point!r}, not one of {POINTS}")
        return ResidualModel(model, residuals, bandwidth, sim, str(spec["engine_version"]), int(spec["ensemble"]),
                             dict(spec.get("meta") or {}), shapes, [str(n) for n in spec.get("shape_names", [])],
                             widening, outcomes, width if outcomes is not None else math.inf,
                             novelty if outcomes is not None else 0.0, defensive,
                             uncorrected if outcomes is not None else 0.0, point,
                             weight if outcomes is not None else 0.0)
    except RecordFormatError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError, RuntimeError, InvalidParameterError) as exc:
        raise RecordFormatError(f"{path} has a malformed residual model ({type(exc).__name__}: {exc})") from exc
