"""A kernel density's queries: checked against the density, broadcast with its batch and cut into chunks
bounded in memory (:func:`prepare_queries`, :func:`query_chunk_size`, :func:`query_chunks`).

Paper, Background → Kernel Density Estimation: the query poses x (and descriptors r) at which a density of Eq.
surface_feature_probability is evaluated; every evaluation of :class:`~pushtorch.kde.PoseKDE`, its trial-round
search (:mod:`pushtorch.kde.rounds`) and the textbook evaluation (:mod:`pushtorch.kde.straightforward`) take
them from here. The dense reference evaluates them in ``(chunk, N)`` blocks.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

import torch

from pushtorch.errors import InvalidParameterError, InvalidPoseError
from pushtorch.kde.fused import DEFAULT_BLOCK_ELEMENTS
from pushtorch.se3 import Pose, check_unit_quaternion

if TYPE_CHECKING:
    from pushtorch.kde.density import PoseKDE

Tensor = torch.Tensor

__all__ = ["prepare_queries", "query_chunk_size", "query_chunks"]


def prepare_queries(kde: PoseKDE, pose: Pose, descriptors: Tensor | None) -> tuple[Tensor, Tensor, Tensor | None]:
    """Queries ``pose`` (and ``descriptors``) of ``kde`` in its dtype, broadcast to one shape ``(*B', M)``:
    ``p (*B', M, 3)``, ``q (*B', M, 4)``, ``r (*B', M, k)`` or None; checked (finite, unit quaternions) when
    ``kde.validate_args``.

    Raises:
        InvalidPoseError: misshaped poses, or batch dims that do not broadcast with the density's.
        InvalidParameterError: descriptors for a density without them, or misshaped / non-finite ones.
    """
    p, q = pose
    if p.dim() < 2 or p.shape[-1] != 3 or q.dim() < 2 or q.shape[-1] != 4:
        raise InvalidPoseError(
            f"query poses need p (..., M, 3) and q (..., M, 4); got {tuple(p.shape)} and {tuple(q.shape)}"
        )
    p = p.to(kde.dtype)
    q = q.to(kde.dtype)
    try:
        shape = torch.broadcast_shapes(p.shape[:-1], q.shape[:-1])
    except RuntimeError as exc:
        raise InvalidPoseError(
            f"query p {tuple(p.shape)} and q {tuple(q.shape)} do not broadcast"
        ) from exc
    if descriptors is not None:
        if kde.descriptors is None:
            raise InvalidParameterError("query descriptors given to a PoseKDE built without descriptors")
        descriptors = descriptors.to(kde.dtype)
        if descriptors.shape[-1:] != (kde.descriptor_dim,):
            raise InvalidParameterError(
                f"query descriptors must have shape (..., M, {kde.descriptor_dim}),"
                f" got {tuple(descriptors.shape)}"
            )
        try:
            shape = torch.broadcast_shapes(shape, descriptors.shape[:-1])
        except RuntimeError as exc:
            raise InvalidParameterError(
                f"query descriptors {tuple(descriptors.shape)} do not broadcast with the poses"
                f" {tuple(shape)}"
            ) from exc
        descriptors = descriptors.expand(*shape, kde.descriptor_dim)
    try:
        torch.broadcast_shapes(shape[:-1], kde.batch_shape)
    except RuntimeError as exc:
        raise InvalidPoseError(
            f"query batch dims {tuple(shape[:-1])} do not broadcast with the density's batch shape"
            f" {tuple(kde.batch_shape)} (queries are (..., M))"
        ) from exc
    p = p.expand(*shape, 3)
    q = q.expand(*shape, 4)
    if kde.validate_args:
        if not torch.isfinite(p).all():
            raise InvalidPoseError("query positions hold NaN or infinite values")
        check_unit_quaternion(q, name="query q")
        if descriptors is not None and not torch.isfinite(descriptors).all():
            raise InvalidParameterError("query descriptors hold NaN or infinite values")
    return p, q, descriptors


def query_chunk_size(kde: PoseKDE, query_batch: torch.Size, chunk_size: int | None) -> int:
    """Queries per dense ``(chunk, N)`` block: ``chunk_size`` checked, or, for None, one that keeps a block of
    every batch element near :data:`~pushtorch.kde.fused.DEFAULT_BLOCK_ELEMENTS` elements.

    Raises:
        InvalidParameterError: a ``chunk_size`` that is not a positive integer.
    """
    if chunk_size is not None:
        if isinstance(chunk_size, bool) or int(chunk_size) != chunk_size or chunk_size < 1:
            raise InvalidParameterError(f"chunk_size must be a positive integer, got {chunk_size!r}")
        return int(chunk_size)
    batch = torch.broadcast_shapes(query_batch, kde.batch_shape).numel()
    return max(1, DEFAULT_BLOCK_ELEMENTS // max(1, batch * kde.num_kernels))


def query_chunks(kde: PoseKDE, pose: Pose, descriptors: Tensor | None, chunk_size: int | None
                 ) -> Iterator[tuple[Tensor, Tensor, Tensor | None]]:
    """The prepared queries (:func:`prepare_queries`) in chunks of :func:`query_chunk_size` along M."""
    p, q, r = prepare_queries(kde, pose, descriptors)
    m = p.shape[-2]
    step = query_chunk_size(kde, p.shape[:-2], chunk_size)
    for start in range(0, m, step):
        sl = slice(start, start + step)
        yield p[..., sl, :], q[..., sl, :], (None if r is None else r[..., sl, :])
