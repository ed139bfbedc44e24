"""Optional heavy imports in one place, so a missing system library is one clear error (no paper section).

open3d (ray casting, nearest neighbours, normals: :mod:`pushtorch.perception`, :mod:`pushtorch.features`,
:mod:`pushtorch.objects`, :mod:`pushtorch.models`) loads the system library libusb-1.0 when imported; where
it is missing the import fails deep inside open3d with an ``OSError``/``ImportError`` about a shared
object. :func:`import_open3d` turns that into a :class:`~pushtorch.errors.MissingDependencyError` with the
command that installs the library.
"""

from __future__ import annotations

from types import ModuleType

from pushtorch.errors import MissingDependencyError

__all__ = ["LIBUSB_INSTALL", "OPEN3D_THREADS", "import_open3d"]

#: The one-line install of open3d's system library, per platform.
LIBUSB_INSTALL = (
    "sudo apt-get install -y libusb-1.0-0 (Debian/Ubuntu; Fedora: sudo dnf install libusbx; "
    "macOS: brew install libusb)"
)

#: Threads open3d may use, process-wide (``open3d.utility.set_max_threads``, set on import): one. open3d runs on
#: TBB, whose threads a fork does not copy: a worker forked from a parent whose TBB threads had been at work waited
#: forever in its own ``cast_rays`` (the installed package's tiny quickstart hung there, in a futex). Unlimited, a
#: cloud's capture starts a TBB thread (its voxel down-sampling); at one, no capture, cast or query starts any, so
#: a fork inherits none. The casts are small, and the experiments' workers run one thread each anyway.
OPEN3D_THREADS = 1
_OPEN3D: ModuleType | None = None


def import_open3d() -> ModuleType:
    """``import open3d`` (cached, limited to :data:`OPEN3D_THREADS`), or a clear error naming what is missing and
    how to install it.

    Raises:
        MissingDependencyError: open3d or one of its system libraries cannot be loaded.
    """
    global _OPEN3D
    if _OPEN3D is None:
        try:
            import open3d
        except (ImportError, OSError) as exc:
            text = str(exc)
            if "libusb" in text:
                raise MissingDependencyError(
                    f"open3d needs the system library libusb-1.0, which is missing ({text}); install it: "
                    f"{LIBUSB_INSTALL}"
                ) from exc
            if isinstance(exc, ModuleNotFoundError) and exc.name == "open3d":
                raise MissingDependencyError(
                    "open3d is not installed: pip install open3d-cpu (Linux x86-64) or pip install open3d"
                ) from exc
            raise MissingDependencyError(f"open3d cannot be imported: {text}") from exc
        open3d.utility.set_max_threads(OPEN3D_THREADS)
        _OPEN3D = open3d
    return _OPEN3D
