"""How the fast path's fused functions run: compiled by torch.compile or eagerly, and in chunks of a bounded
size (:func:`declare_long_run`, :func:`fast_path_compiled`, :func:`fused_function`, :func:`compile_failed`,
:func:`chunk_bounds`, :data:`DEFAULT_BLOCK_ELEMENTS`).

Paper, Background → Kernel Density Estimation: the weighted kernel sums with hard cut-offs (Eq.
surface_feature_probability) are evaluated on the fast path in single fused passes over (queries × kernels)
(:mod:`pushtorch.kde.kernel_sums`), no kernel the cut-offs let reach a query left out. This module decides how
those passes run. With a C++ compiler (CPU) or Triton (CUDA) the fused functions are compiled by torch.compile
in processes that declared a long run (``PUSHTORCH_COMPILE``: ``auto`` default, ``1`` insist, ``0`` never);
otherwise the same functions run eagerly, in chunks.

A process that starts many others on the same code (a Ray or Slurm run's submitter) can share the compiled
functions with them (:func:`share_compiled`): each is compiled ahead of time once (``torch.compile``'s
``aot_compile``) and saved under Inductor's cache folder, keyed by everything its code depends on (torch and
Python versions, the CPU's features, this package's source); a worker that shares them loads them
in about 2 s instead of tracing them again (9-11 s on a 2-core CPU). A loaded function runs the same generated
code as one compiled in the process, so results are equal bit for bit; a call that none of the saved functions
was compiled for (another specialisation) is compiled in the process as usual.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import platform
import shutil
import sys
import uuid
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

from pushtorch.errors import InvalidParameterError

Tensor = torch.Tensor

__all__ = [
    "DEFAULT_BLOCK_ELEMENTS",
    "chunk_bounds",
    "compile_failed",
    "declare_long_run",
    "fast_path_compiled",
    "fused_function",
    "share_compiled",
    "shared_compiled_folder",
]

log = logging.getLogger(__name__)

#: Elements of one dense (queries x kernels) block per chunk when no chunk size is given: about 8 MB
#: per float32 temporary, so the few temporaries of a chunk stay in a CPU's last-level cache (faster
#: here than one 500 x 25,500 block) while the matmuls stay efficient.
DEFAULT_BLOCK_ELEMENTS = 1 << 21

_COMPILE_ENV = "PUSHTORCH_COMPILE"
_compiled_functions: dict[str, Callable] = {}
_compile_failed: set[str] = set()
_compiler_found: list[bool] = []  # cached shutil.which answer
_long_run = [False]  # declare_long_run: compiling pays in this process
# Inductor stores an intermediate that is read twice (the distance d in `where(d < δ, exp(w − d), 0)`)
# as a full (queries × kernels) buffer and reduces it in a second loop; recomputing it in the one fused
# loop is ~7× faster on CPU (measured on the query density's group sums: 12.3 → 1.6 ms).
_INDUCTOR_OPTIONS = {"realize_reads_threshold": 1000}
# share_compiled: {"produce": bool} while on; the loaded or saved functions per name and device; names whose
# ahead-of-time compilation failed here (they compile in the process); the folder, once known
_shared: dict[str, bool] = {}
_shared_variants: dict[str, list] = {}
_not_shared: set[str] = set()
_shared_folder: list[Path] = []
_MISS = object()


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


def compile_failed(name: str) -> bool:
    """Whether the compilation of the fused function ``name`` failed in this process, so that it runs eagerly
    (and its callers chunk it as eager code)."""
    return name in _compile_failed


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
                    if _shared and key not in _not_shared:
                        result = _shared_call(key, fn, options, args)
                        if result is not _MISS:
                            return result
                    return compiled(*args)
            except Exception as exc:  # a missing/broken compiler surfaces here, on first use
                _compile_failed.add(name)
                warnings.warn(f"torch.compile of the fast kernel path failed ({type(exc).__name__}: {exc});"
                              f" running it eagerly (set {_COMPILE_ENV}=0 to skip compiling)", stacklevel=2)
                return fn(*args)

        _compiled_functions[key] = call
    return _compiled_functions[key]


def shared_compiled_folder() -> Path:
    """Where shared compiled functions of this code on this machine kind live: a folder under Inductor's cache
    (``TORCHINDUCTOR_CACHE_DIR``; a cluster may point it at a shared disk) named by the torch and Python
    versions, the machine, its CPU's capability and feature flags, Inductor's options and a hash of this
    package's source files (module notes)."""
    if not _shared_folder:
        try:
            from torch._inductor.runtime.cache_dir_utils import cache_dir
        except ImportError:  # where another torch keeps it elsewhere: Inductor's documented default
            def cache_dir() -> str:
                user = "".join(c if c.isalnum() else "_" for c in os.environ.get("USER", "user"))
                return os.environ.get("TORCHINDUCTOR_CACHE_DIR") or str(Path("/tmp") / f"torchinductor_{user}")

        package = Path(__file__).resolve().parents[1]
        digest = hashlib.sha256()
        for path in sorted(package.rglob("*.py")):
            digest.update(str(path.relative_to(package)).encode())
            digest.update(path.read_bytes())
        for part in (torch.__version__, sys.version, platform.machine(), torch.backends.cpu.get_cpu_capability(),
                     _cpu_flags(), repr(sorted(_INDUCTOR_OPTIONS.items()))):
            digest.update(part.encode())
        _shared_folder.append(Path(cache_dir()) / "pushtorch_shared" / digest.hexdigest()[:24])
    return _shared_folder[0]


def _cpu_flags() -> str:
    """The CPU's feature flags (Linux), which the generated code may use: machines that differ in one do not
    share compiled functions."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor()


def share_compiled(produce: bool = False) -> Path:
    """Use the shared compiled functions of :func:`shared_compiled_folder` in this process (module notes).

    A fused function's call runs the first saved function whose guards accept its arguments. With ``produce``, a
    call that none accepts is compiled ahead of time and saved for the others (about three times as long as an
    in-process compilation, once per code version and machine kind); without, it is compiled in the process as
    usual. CPU functions only (a GPU compiles in the process). Returns the folder."""
    _shared["produce"] = bool(produce) or _shared.get("produce", False)
    return shared_compiled_folder()


def _shared_call(key: str, fn: Callable, options: dict, args: tuple):
    """``fn(*args)`` by a shared compiled function (:func:`share_compiled`); ``_MISS`` where there is none."""
    name, device = key.split(":")
    if device != "cpu":
        return _MISS
    folder = shared_compiled_folder()
    variants = _shared_variants.get(key)
    if variants is None:
        variants = _shared_variants[key] = []
        for path in sorted(folder.glob(f"{name}.*.bin")):
            try:
                with open(path, "rb") as file:
                    loaded = torch.compiler.load_compiled_function(file, f_globals=fn.__globals__)
                loaded.disable_guard_check()  # checked below, once, to choose among the saved functions
                variants.append(loaded)
            except Exception as exc:  # noqa: BLE001 - an unreadable or foreign file is skipped
                log.debug("shared compiled function %s not loaded: %s", path, exc)
    for variant in variants:
        if variant.guard_check(*args):
            return variant(*args)
    if not _shared.get("produce"):
        return _MISS
    try:
        made = torch.compile(fn, dynamic=True, fullgraph=True, options=options).aot_compile((args, {}))
        folder.mkdir(parents=True, exist_ok=True)
        made.save_compiled_function(str(folder / f"{name}.{uuid.uuid4().hex}.bin"))  # written atomically
    except Exception as exc:  # noqa: BLE001 - a function that cannot be compiled ahead of time compiles here
        log.debug("fused function %s not compiled ahead of time: %s", name, exc)
        _not_shared.add(key)
        return _MISS
    made.disable_guard_check()
    variants.append(made)
    return made(*args)
