"""The fast path's fused functions and when they are compiled (:func:`declare_long_run`,
:func:`fast_path_compiled`, :func:`fused_function`): exact distances and cut-offs in single passes over
(queries × kernels), no kernel the cut-offs let reach a query left out."""

from __future__ import annotations

import math
import os
import shutil
import warnings
from collections.abc import Callable, Sequence

import torch

from pushtorch.errors import InvalidParameterError

Tensor = torch.Tensor

# Elements of one dense (queries x kernels) block per chunk when no chunk size is given: about 8 MB
# per float32 temporary, so the few temporaries of a chunk stay in a CPU's last-level cache (faster
# here than one 500 x 25,500 block) while the matmuls stay efficient.
_DEFAULT_BLOCK_ELEMENTS = 1 << 21

# --------------------------------------------------------------------------------------------------
# Fast path: kernels pruned by the hard cut-offs, fused evaluation
# --------------------------------------------------------------------------------------------------
#
# The cut-offs make every kernel exactly zero beyond a translation radius and a rotation angle. For a
# density with many kernels (a query density: 3,000), kernels are put once into leaf blocks of a k-d
# tree over (position, rotation); a query visits only the blocks whose bounding box and rotation cap
# come within the cut-offs (a bound: nothing that could survive is skipped) and each visited block is
# evaluated with the exact distances in one fused pass. A density with few kernels (an expert of the
# product: ~500, most of them near every candidate) is evaluated in one fused dense pass instead.
# Sums run in the linear domain relative to each density's largest weight: a surviving kernel factor is
# at least e^(−δ_p−δ_q), so nothing underflows unless weights span ~e^60 (then the dense reference
# path is used). With a C++ compiler (CPU) or Triton (CUDA) the fused functions are compiled by
# torch.compile in processes that declared a long run (``PUSHTORCH_COMPILE``: ``auto`` default, ``1``
# insist, ``0`` never); otherwise the same functions run eagerly, in chunks.

FAST_LEAF_SIZE = 16  # kernels per leaf block: prunes best on the paper-scale query densities (measured)
# Densities with at most this many kernels skip the blocks: pruning cannot pay for its bookkeeping.
FAST_DENSE_KERNELS = 1024
# Relative slack on the pruning bounds: float rounding of a bound must never skip a live kernel.
_BOUND_SLACK = 1e-3
_COMPILE_ENV = "PUSHTORCH_COMPILE"
_compiled_functions: dict[str, Callable] = {}
_compile_failed: set[str] = set()
_compiler_found: list[bool] = []  # cached shutil.which answer
_long_run = [False]  # declare_long_run: compiling pays in this process
# Inductor stores an intermediate that is read twice (the distance d in `where(d < δ, exp(w − d), 0)`)
# as a full (queries × kernels) buffer and reduces it in a second loop; recomputing it in the one fused
# loop is ~7× faster on CPU (measured on the query density's group sums: 12.3 → 1.6 ms).
_INDUCTOR_OPTIONS = {"realize_reads_threshold": 1000}


def _compile_mode() -> str:
    mode = os.environ.get(_COMPILE_ENV, "auto").strip().lower()
    if mode not in ("auto", "1", "0"):
        raise InvalidParameterError(f"{_COMPILE_ENV} must be auto, 1 or 0, got {mode!r}")
    return mode


def declare_long_run(enabled: bool = True) -> None:
    """Tell the fast path that this process makes many predictions, so compiling pays (``auto`` mode).

    torch.compile traces and generates code on a function's first calls: 5-9 s on a 2-core CPU before the
    first prediction, against ~0.2 s of eager evaluation saved per prediction at the quickstart's sizes
    (``tools/bench_cold.py``). A library user's single ``predict`` therefore runs eagerly; the experiment
    app (``python -m pushtorch``), the paper reproduction and the prediction benchmark declare a long run.
    """
    _long_run[0] = bool(enabled)


def fast_path_compiled(device: torch.device | str = "cpu") -> bool:
    """Whether the fast path's fused functions are compiled with torch.compile on ``device``.

    ``PUSHTORCH_COMPILE=0`` never compiles; ``1`` always tries; ``auto`` (default) compiles in a process
    that declared a long run (:func:`declare_long_run`), on CUDA and on CPU when a C++ compiler is on the
    PATH (Inductor needs one), and otherwise runs eagerly, so a first prediction is never slower than
    eager evaluation. A compilation that fails at run time falls back to eager evaluation with a warning,
    once.
    """
    mode = _compile_mode()
    if mode == "0":
        return False
    if mode == "1":
        return True
    if not _long_run[0]:
        return False
    if torch.device(device).type == "cuda":
        return True
    if not _compiler_found:
        _compiler_found.append(any(shutil.which(cc) is not None for cc in ("g++", "c++", "clang++", "cl")))
    return _compiler_found[0]


def chunk_bounds(n: int, step: int) -> list[tuple[int, int]]:
    """``[start, end)`` bounds of chunks of about ``step`` rows covering ``n``: of even size, and a lone last
    row joined to the chunk before. A chunk of one row is a size-1 dimension, which the compiler specialises
    and so recompiles a fused function for (measured: two recompiles of a 48-condition batched run)."""
    if n <= 0:
        return []
    step = math.ceil(n / math.ceil(n / max(1, step)))
    starts = list(range(0, n, step))
    if len(starts) > 1 and n - starts[-1] == 1:
        starts.pop()
    return list(zip(starts, [*starts[1:], n], strict=True))


def _no_duck_sizing():
    """Within this block Dynamo gives every size its own symbol (torch's shape-environment setting, read
    when a graph is traced)."""
    from torch.fx.experimental import _config as shape_config

    return shape_config.patch(use_duck_shape=False)


def fused_function(name: str, fn: Callable, device: torch.device | str) -> Callable:
    """``fn`` compiled with torch.compile if :func:`fast_path_compiled` allows it, else ``fn`` itself.

    For the fast paths' pure tensor functions (no generators, no data-dependent shapes inside). One
    compiled function per ``name`` and device type, shared by every caller. What it is compiled for does
    not depend on the data it meets, so a warm process never recompiles:

    - sizes are symbolic from the first call (``dynamic=True``): kernel counts that vary with the data (a
      float path that prunes one kernel more) do not meet a graph specialised to the warm-up's sizes; two
      sizes that happen to be equal on the first call are not taken to be one size (no duck sizing: a
      batch of 7 problems would otherwise be tied to the 7 rows of a pose);
    - tensor arguments are passed contiguous, so a strided view cannot fail a stride guard;
    - calls run under ``torch.no_grad``, so the caller's grad mode is not guarded on; an argument that
      requires grad is evaluated eagerly instead (compiled code is for annealing, not for autograd).

    A failing compilation warns once and falls back to ``fn``.
    """
    device = torch.device(device)
    if name in _compile_failed or not fast_path_compiled(device):
        return fn
    key = f"{name}:{device.type}"
    if key not in _compiled_functions:
        from torch._inductor import config as inductor_config

        # torch.compile refuses option names its Inductor does not know (older torch): leave those out
        options = {k: v for k, v in _INDUCTOR_OPTIONS.items() if hasattr(inductor_config, k)}
        compiled = torch.compile(fn, dynamic=True, options=options)

        def call(*args):
            if name in _compile_failed or (
                    torch.is_grad_enabled() and any(isinstance(a, Tensor) and a.requires_grad for a in args)):
                return fn(*args)
            args = tuple(a.contiguous() if isinstance(a, Tensor) else a for a in args)
            try:
                with torch.no_grad(), _no_duck_sizing():
                    return compiled(*args)
            except Exception as exc:  # a missing/broken compiler surfaces here, on first use
                _compile_failed.add(name)
                warnings.warn(f"torch.compile of the fast kernel path failed ({type(exc).__name__}: {exc});"
                              f" running it eagerly (set {_COMPILE_ENV}=0 to skip compiling)", stacklevel=2)
                return fn(*args)

        _compiled_functions[key] = call
    return _compiled_functions[key]


def _pose_distances(x: Sequence[Tensor], t: Sequence[Tensor], scale_p: Tensor, scale_q: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """The fused passes' kernel distances from the rows of queries ``x`` and kernels ``t`` (p then q, in
    any broadcastable layout): ``(β_p/σ_p |x_p − μ_p|², <x_q, μ_q>, β_q/σ_q (1 − |<x_q, μ_q>|))`` — the
    scaled terms :meth:`PoseKDE.log_prob` cuts off and sums (written out: compiled, nothing is stored)."""
    d_p = ((x[0] - t[0]) ** 2 + (x[1] - t[1]) ** 2 + (x[2] - t[2]) ** 2) * scale_p
    dot = x[3] * t[3] + x[4] * t[4] + x[5] * t[5] + x[6] * t[6]
    return d_p, dot, (1.0 - dot.abs()).clamp_min(0.0) * scale_q


def _dense_sums(x: Tensor, table: Tensor, scale: Tensor, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) for every query against every kernel of its density: ``(Q, M)``.

    x: queries ``(Q, 7, M)`` (rows p, q); table: kernels ``(Q, 8, N)`` (rows p, q, log w relative to the
    largest); scale: ``(Q, 2)`` (β_p/σ_p, β_q/σ_q). Exact distances, the cut-offs of
    :meth:`PoseKDE.log_prob`; compiled, no ``(Q, M, N)`` tensor is stored.
    """
    t = table.unsqueeze(2)  # (Q, 8, 1, N)
    sc = scale[:, :, None, None]
    d_p, _, d_q = _pose_distances(x.unsqueeze(-1).unbind(1), t.unbind(1), sc[:, 0], sc[:, 1])  # x: (Q, 7, M, 1)
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)).sum(-1)


def _linear_sums_exact(relative_log_w: Tensor) -> bool:
    """Whether weights given relative to the largest (``≤ 0``, ``-inf`` padding) can be summed in the
    linear domain: exactly unless a kernel weighs ~e^-60 less than the largest (float32)."""
    live = relative_log_w[relative_log_w > -math.inf]
    return bool((live > math.log(torch.finfo(relative_log_w.dtype).tiny) + 25.0).all())


def _descriptor_sums(x: Tensor, table: Tensor, scale: Tensor, r_scale: Tensor, delta_p: float, delta_q: float,
                     delta_r: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) with descriptors for queries ``x (7 + k, M)`` (rows p, q, r) against kernels
    ``table (8 + k, N)`` (rows p, q, relative log w, r): ``(M,)``. scale: ``(3,)`` (β_p/σ_p, β_q/σ_q,
    β_r), r_scale: ``(k,)`` 1/σ_r. Exact distances and every cut-off of :meth:`PoseKDE.log_prob`."""
    xs = x.unsqueeze(-1)  # (7 + k, M, 1)
    t = table.unsqueeze(1)  # (8 + k, 1, N)
    d_p, _, d_q = _pose_distances(xs, t, scale[0], scale[1])
    d_r = sum((xs[7 + k] - t[8 + k]) ** 2 * r_scale[k] for k in range(r_scale.shape[0])) * scale[2]
    keep = (d_p < delta_p) & (d_q < delta_q) & (d_r < delta_r)
    return torch.where(keep, torch.exp(t[7] - d_p - d_q - d_r), torch.zeros_like(d_p)).sum(-1)


def _reachable_blocks(
    x: Tensor, lo: Tensor, hi: Tensor, centre: Tensor, cos_reach: Tensor, r2: Tensor
) -> Tensor:
    """Which blocks each query may touch: ``(Q, M, nb)``, 1.0 where it may (float: compiles ~10× faster).

    x: queries ``(Q, 7, M)``; lo, hi: block bounding boxes ``(Q, 3, nb)``; centre: block rotation centres
    ``(Q, 4, nb)``; cos_reach: ``(Q, nb)`` cosine of half the largest angle at which the block can
    still hold a live kernel (−1: any, 2: none); r2: ``(Q, 1)`` squared translation reach (m²).
    """
    xs = x.unsqueeze(-1)  # (Q, 7, M, 1)
    lo, hi, centre = lo.unsqueeze(2), hi.unsqueeze(2), centre.unsqueeze(2)  # (Q, k, 1, nb)
    g0 = torch.clamp(torch.maximum(lo[:, 0] - xs[:, 0], xs[:, 0] - hi[:, 0]), min=0.0)
    g1 = torch.clamp(torch.maximum(lo[:, 1] - xs[:, 1], xs[:, 1] - hi[:, 1]), min=0.0)
    g2 = torch.clamp(torch.maximum(lo[:, 2] - xs[:, 2], xs[:, 2] - hi[:, 2]), min=0.0)
    near = g0 * g0 + g1 * g1 + g2 * g2 <= r2.unsqueeze(-1)
    dot = (xs[:, 3] * centre[:, 0] + xs[:, 4] * centre[:, 1] + xs[:, 5] * centre[:, 2]
           + xs[:, 6] * centre[:, 3]).abs()
    return (near & (dot >= cos_reach.unsqueeze(1))).to(x.dtype)


def _pair_kernels(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                  pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """``w K`` of every kernel of every (query, block) pair ``(P, L)``, with the pairs' blocks
    ``(P, 8, L)`` and the quaternion dot products ``(P, L)``; arguments as :func:`_block_sums`."""
    density = query_density[pair_query]
    t = table[density * num_blocks + pair_block]  # (P, 8, L)
    xs = x[pair_query].unsqueeze(-1)  # (P, 7, 1)
    sc = scale[density]
    d_p, dot, d_q = _pose_distances(xs.unbind(1), t.unbind(1), sc[:, 0:1], sc[:, 1:2])
    keep = (d_p < delta_p) & (d_q < delta_q)
    return torch.where(keep, torch.exp(t[:, 7] - d_p - d_q), torch.zeros_like(d_p)), t, dot


def _block_sums(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """Σ_i w_i K(x | μ_i) per query ``(R,)`` over its (query, block) pairs.

    x: ``(R, 7)`` queries; table: ``(D·nb + 1, 8, L)`` blocks (rows p, q, relative log w; kernels along
    L); scale: ``(D, 2)``; query_density: ``(R,)`` each query's density row; pair_query, pair_block:
    ``(P,)`` the pairs. Exact distances and the cut-offs of :meth:`PoseKDE.log_prob`.
    """
    k, _, _ = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p, delta_q)
    return torch.zeros_like(x[:, 0]).index_add(0, pair_query, k.sum(-1))


def _block_moments(x: Tensor, table: Tensor, scale: Tensor, query_density: Tensor, pair_query: Tensor,
                   pair_block: Tensor, num_blocks: int, delta_p: float, delta_q: float) -> Tensor:
    """The mean-shift moments of each query over its (query, block) pairs: ``(R, 8)``, columns
    ``Σ w K``, ``Σ w K μ_p`` (3) and ``Σ w K s μ_q`` (4) with ``s = sign<x_q, μ_q>``; arguments as
    :func:`_block_sums`."""
    k, t, dot = _pair_kernels(x, table, scale, query_density, pair_query, pair_block, num_blocks, delta_p,
                              delta_q)
    ks = torch.where(dot < 0, -k, k)
    moments = torch.stack([k.sum(-1)] + [(k * t[:, i]).sum(-1) for i in range(3)]
                          + [(ks * t[:, i]).sum(-1) for i in range(3, 7)], -1)  # (P, 8)
    return torch.zeros(x.shape[0], 8, dtype=x.dtype, device=x.device).index_add(0, pair_query, moments)


_DENSE_ROW_GROUPS = 4  # at most this many kernel-count groups per dense evaluation (one call each)
# Cost of one more fused call, in kernel evaluations (~100 µs of dispatch against ~0.5 ns per kernel
# and query, measured on CPU): grouping rows only pays when it skips more padding than this.
_CALL_COST_KERNELS = 200_000


def _row_groups(counts: Tensor, queries: int, max_groups: int) -> list[tuple[Tensor | None, int]]:
    """Rows split into groups of similar kernel counts, ``[(rows, width)]``, minimising padded work.

    Candidates are 1 … ``max_groups`` quantile splits of the rows sorted by count; each group is
    evaluated up to its largest count (≥ 1). A single group of every row is ``[(None, width)]``.
    """
    order = torch.argsort(counts, stable=True)
    ordered = [max(1, int(c)) for c in counts[order].tolist()]
    d = len(ordered)
    best, best_cost = [(None, ordered[-1])], _CALL_COST_KERNELS + queries * d * ordered[-1]
    for k in range(2, min(max_groups, d) + 1):
        bounds = sorted({round(d * j / k) for j in range(1, k + 1)})
        groups, start, cost = [], 0, 0
        for end in bounds:
            if end > start:
                groups.append((order[start:end], ordered[end - 1]))
                cost += _CALL_COST_KERNELS + queries * (end - start) * ordered[end - 1]
                start = end
        if cost < best_cost:
            best, best_cost = groups, cost
    return best


def _kd_leaf_order(features: Tensor, valid: Tensor, leaf: int) -> Tensor:
    """Kernel order ``(D, S)`` grouping kernels into leaf blocks of a k-d tree (median splits).

    features: ``(D, N, F)`` split coordinates; valid: ``(D, N)``. ``S = leaf · 2^levels ≥ N``; index
    ``N`` marks padding. Invalid kernels sort last and end up in padding-only blocks where possible.
    """
    d, n, f = features.shape
    levels = max(0, math.ceil(math.log2(max(1.0, n / leaf))))
    size = leaf * 2**levels
    feats = torch.where(valid.unsqueeze(-1), features, torch.full_like(features, math.inf))
    filler = torch.full((d, size - n, f), math.inf, dtype=feats.dtype, device=feats.device)
    feats = torch.cat([feats, filler], 1)
    order = torch.arange(size, device=features.device).expand(d, size).contiguous()
    for level in range(levels):
        nodes = 2**level
        node = torch.gather(feats, 1, order.unsqueeze(-1).expand(-1, -1, f)).reshape(d, nodes, -1, f)
        finite = torch.isfinite(node)
        low = torch.where(finite, node, torch.full_like(node, math.inf)).amin(2)
        high = torch.where(finite, node, torch.full_like(node, -math.inf)).amax(2)
        axis = torch.nan_to_num(high - low, nan=0.0, posinf=0.0, neginf=0.0).argmax(-1)  # (D, nodes)
        values = torch.gather(node, 3, axis[:, :, None, None].expand(-1, -1, node.shape[2], 1)).squeeze(-1)
        split = values.argsort(dim=-1, stable=True)
        order = torch.gather(order.reshape(d, nodes, -1), 2, split).reshape(d, size)
    return torch.where(order < n, order, torch.full_like(order, n))
