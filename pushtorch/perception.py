"""A virtual depth camera on open3d ray casting: the point clouds (PCOMs) the method learns from.

Paper, Experimental Setup: "At training time, a full point cloud of the object to be pushed is acquired
from multiple views of a virtual depth camera" (:func:`capture_full_cloud`), and "at prediction time, a
new point cloud is captured with a single shot of the virtual depth camera" (:func:`capture_partial_cloud`).
Background, Surface Features: the surface features are derived from such a cloud (pushtorch.features).

The object stands in a scene made of its mesh, placed at a world pose, and the ground plane z = 0. The
ground takes part in the ray casting, so it occludes what a real camera could not see, but its own hits
are dropped from the cloud. Each point remembers the camera centre that saw it (``view_origins``): a
visible surface faces its camera, which is how pushtorch.features orients normals outward.

Conventions: world frame, metres, float32 torch tensors; poses are :class:`pushtorch.se3.Pose` (wxyz).
The camera is a pinhole with square pixels; its horizontal field of view and 640×480 image default to a
Kinect v1, the camera of the paper's experiments. Depth noise is Gaussian along the viewing axis.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from pushtorch import se3
from pushtorch.errors import InvalidParameterError, InvalidPointCloudError, InvalidPoseError
from pushtorch.io import atomic_write_bytes

if TYPE_CHECKING:
    from pushtorch.objects import ObjectModel

Tensor = torch.Tensor

__all__ = [
    "DEFAULT_FULL_DISTANCE",
    "DEFAULT_PARTIAL_OFFSET",
    "DEFAULT_VOXEL_SIZE",
    "DepthCamera",
    "ObjectScene",
    "PointCloud",
    "capture_full_cloud",
    "capture_partial_cloud",
    "CLOUD_SUFFIXES",
    "default_partial_camera_position",
    "load_cloud_file",
    "orbit_viewpoints",
    "save_cloud_file",
    "voxel_down_sample",
]

#: The file endings :func:`load_cloud_file` reads: PLY and PCD (open3d) and npz (an array ``points``).
CLOUD_SUFFIXES = (".ply", ".pcd", ".npz")

#: Voxel edge (m) of the down-sampled clouds: curvature neighbourhoods see points at most ~4 mm apart.
DEFAULT_VOXEL_SIZE = 0.004
#: Distance (m) of the training cameras from the object's centre (at least; larger objects move them out).
DEFAULT_FULL_DISTANCE = 0.8
#: Default single-shot camera relative to the object's centre, world frame (m): 0.8 m behind the object
#: along -x (the robot's side: the robot pushes along +x) and at 0.6 m above the ground (a mast-mounted
#: camera on a mobile base). The z entry is an absolute height above the ground, not an offset.
DEFAULT_PARTIAL_OFFSET = (-0.8, 0.0, 0.6)

_GROUND_HALF_SIZE = 50.0
_GRID_SHIFT = math.sqrt(2.0) - 1.0


@dataclass
class PointCloud:
    """A point cloud in the world frame and, for each point, the centre of the camera that saw it.

    Attributes:
        points: ``(N, 3)`` floating tensor, metres, world frame.
        view_origins: ``(N, 3)`` camera centre per point, or ``None`` when unknown (e.g. a cloud read
            from a file); then normals are oriented away from the cloud's centroid instead.

    Raises:
        InvalidPointCloudError: on construction, if the cloud is empty, has the wrong shape, or holds
            NaN or infinite values (in points or view origins).
    """

    points: Tensor
    view_origins: Tensor | None = None

    def __post_init__(self) -> None:
        self.points = _as_float_tensor(self.points)
        if self.points.dim() != 2 or self.points.shape[-1] != 3:
            raise InvalidPointCloudError(
                f"point cloud must have shape (N, 3), got {tuple(self.points.shape)}"
            )
        if self.points.shape[0] == 0:
            raise InvalidPointCloudError("point cloud is empty (0 points)")
        bad = ~torch.isfinite(self.points).all(-1)
        if bad.any():
            raise InvalidPointCloudError(
                f"point cloud holds NaN or infinite coordinates in {int(bad.sum())} of {len(bad)} points"
            )
        if self.view_origins is not None:
            self.view_origins = _as_float_tensor(self.view_origins).to(self.points)
            if self.view_origins.shape != self.points.shape:
                raise InvalidPointCloudError(
                    f"view_origins must match points {tuple(self.points.shape)}, "
                    f"got {tuple(self.view_origins.shape)}"
                )
            if not torch.isfinite(self.view_origins).all():
                raise InvalidPointCloudError("point cloud view_origins hold NaN or infinite values")

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def device(self) -> torch.device:
        return self.points.device

    def to(self, *args, **kwargs) -> PointCloud:
        """Move/cast like ``Tensor.to`` (device and/or dtype)."""
        origins = None if self.view_origins is None else self.view_origins.to(*args, **kwargs)
        return PointCloud(self.points.to(*args, **kwargs), origins)

    def select(self, index: Tensor | slice) -> PointCloud:
        """The sub-cloud at ``index`` (an index tensor, a boolean mask or a slice)."""
        origins = None if self.view_origins is None else self.view_origins[index]
        return PointCloud(self.points[index], origins)

    __getitem__ = select

    @staticmethod
    def cat(clouds: list[PointCloud]) -> PointCloud:
        """Concatenate clouds; view origins are kept only if every cloud has them."""
        if not clouds:
            raise InvalidPointCloudError("cannot concatenate an empty list of point clouds")
        points = torch.cat([c.points for c in clouds])
        if all(c.view_origins is not None for c in clouds):
            return PointCloud(points, torch.cat([c.view_origins for c in clouds]))  # type: ignore[misc]
        return PointCloud(points)


def _as_float_tensor(x) -> Tensor:
    x = torch.as_tensor(x)
    return x if x.is_floating_point() else x.to(torch.float32)


@dataclass(frozen=True)
class DepthCamera:
    """A pinhole depth camera: image size, horizontal field of view, range and depth noise.

    Attributes:
        width, height: image size in pixels (one ray per pixel).
        fov_deg: horizontal field of view in degrees (Kinect v1: 57°).
        max_range: hits farther than this (m, along the ray) are dropped.
        noise_std: standard deviation (m) of Gaussian noise added to each depth (distance along the
            optical axis); 0 gives exact surface points.

    Raises:
        InvalidParameterError: a non-positive size, range or field of view, or a negative noise.
    """

    width: int = 640
    height: int = 480
    fov_deg: float = 57.0
    max_range: float = 4.0
    noise_std: float = 0.0

    def __post_init__(self) -> None:
        if int(self.width) < 1 or int(self.height) < 1:
            raise InvalidParameterError(
                f"camera image size must be positive, got {self.width}×{self.height}"
            )
        if not 0.0 < float(self.fov_deg) < 180.0:
            raise InvalidParameterError(f"camera fov_deg must lie in (0, 180), got {self.fov_deg}")
        if not (math.isfinite(self.max_range) and self.max_range > 0):
            raise InvalidParameterError(f"camera max_range must be positive and finite, got {self.max_range}")
        if not (math.isfinite(self.noise_std) and self.noise_std >= 0):
            raise InvalidParameterError(f"camera noise_std must be >= 0 and finite, got {self.noise_std}")

    def rays(self, eyes: Tensor, targets: Tensor) -> np.ndarray:
        """Rays ``(V, H, W, 6)`` (origin, direction) of V cameras at ``eyes (V, 3)`` looking at
        ``targets (V, 3)``; each direction has unit component along its optical axis, so the ray
        parameter of a hit is its depth. The image's up is world +z (world +x for a camera looking
        straight down or up)."""
        from pushtorch.deps import import_open3d

        o3d = import_open3d()

        eyes_np = eyes.detach().cpu().double().numpy().reshape(-1, 3)
        targets_np = np.broadcast_to(targets.detach().cpu().double().numpy(), eyes_np.shape)
        views = []
        for eye, target in zip(eyes_np, targets_np, strict=True):
            forward = target - eye
            if np.linalg.norm(forward) < 1e-9:
                raise InvalidParameterError(f"camera at {eye.tolist()} looks at its own position")
            forward /= np.linalg.norm(forward)
            up = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.999 else np.array([1.0, 0.0, 0.0])
            views.append(
                o3d.t.geometry.RaycastingScene.create_rays_pinhole(
                    fov_deg=float(self.fov_deg),
                    center=o3d.core.Tensor(target.astype(np.float32)),
                    eye=o3d.core.Tensor(eye.astype(np.float32)),
                    up=o3d.core.Tensor(up.astype(np.float32)),
                    width_px=int(self.width),
                    height_px=int(self.height),
                ).numpy()
            )
        return np.stack(views)


class ObjectScene:
    """An object placed at a world pose on the ground plane z = 0, ready for ray casting.

    Attributes:
        obj: the object.
        pose: its world pose (a single :class:`~pushtorch.se3.Pose`).
        vertices: ``(V, 3)`` float32 world-frame vertices of the placed mesh (torch).
        scene: the open3d ``RaycastingScene`` holding the object and the ground.
        object_id, ground_id: open3d geometry ids of the two.

    Raises:
        InvalidPoseError: ``pose`` is not a single pose with a finite unit quaternion.
    """

    def __init__(self, obj: ObjectModel, pose: se3.Pose | None = None) -> None:
        from pushtorch.deps import import_open3d

        o3d = import_open3d()

        pose = obj.resting_pose() if pose is None else pose
        _check_single_pose(pose)
        self.obj = obj
        self.pose = se3.Pose.unchecked(pose.p.detach().float().cpu(), pose.q.detach().float().cpu())
        local = torch.as_tensor(np.asarray(obj.mesh.vertices), dtype=torch.float32)
        self.vertices = se3.apply(self.pose, local)
        faces = np.ascontiguousarray(np.asarray(obj.mesh.faces, dtype=np.uint32))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.object_id = self.scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(self.vertices.numpy())), o3d.core.Tensor(faces)
        )
        h = _GROUND_HALF_SIZE
        ground_vertices = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]], np.float32)
        ground_faces = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
        self.ground_id = self.scene.add_triangles(
            o3d.core.Tensor(ground_vertices), o3d.core.Tensor(ground_faces)
        )

    @property
    def centre(self) -> Tensor:
        """World position ``(3,)`` of the object's centre of mass."""
        return self.pose.p

    @property
    def bounding_radius(self) -> float:
        """Radius (m) of the smallest origin-centred sphere around the object."""
        return float((self.vertices - self.pose.p).norm(dim=-1).max())

    def capture(
        self,
        camera: DepthCamera,
        eyes: Tensor,
        target: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> PointCloud:
        """The object's points seen by cameras at ``eyes (V, 3)`` (or ``(3,)``), all rays cast in one batch.

        Args:
            camera: intrinsics, range and noise.
            eyes: camera centres, world frame.
            target: ``(3,)`` or ``(V, 3)`` points looked at; default the object's centre.
            generator: seeds the depth noise (only used when ``camera.noise_std > 0``).

        Returns:
            The raw (not down-sampled) cloud of object hits, each with its camera centre.

        Raises:
            InvalidPointCloudError: no ray hit the object within range.
        """
        from pushtorch.deps import import_open3d

        o3d = import_open3d()

        eyes = torch.as_tensor(eyes, dtype=torch.float32).reshape(-1, 3)
        if not torch.isfinite(eyes).all():
            raise InvalidParameterError("camera positions must be finite")
        target = self.centre if target is None else torch.as_tensor(target, dtype=torch.float32)
        rays = camera.rays(eyes, target.expand(eyes.shape[0], 3))
        hits = self.scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
        t_hit = torch.from_numpy(hits["t_hit"].numpy().astype(np.float32)).reshape(-1)
        ids = torch.from_numpy(hits["geometry_ids"].numpy().astype(np.int64)).reshape(-1)
        rays_t = torch.from_numpy(rays).float().reshape(-1, 6)
        origins, directions = rays_t[:, :3], rays_t[:, 3:]
        in_range = t_hit * directions.norm(dim=-1) <= camera.max_range
        keep = (ids == self.object_id) & torch.isfinite(t_hit) & in_range
        if not keep.any():
            raise InvalidPointCloudError(
                f"no camera ray hit the object {self.obj.name!r} within {camera.max_range} m "
                f"(cameras at {eyes.tolist()})"
            )
        depth = t_hit[keep]
        if camera.noise_std > 0:
            depth = depth + camera.noise_std * torch.randn(depth.shape, generator=generator)
        points = origins[keep] + depth.unsqueeze(-1) * directions[keep]
        return PointCloud(points, origins[keep].clone())


def _check_single_pose(pose: se3.Pose) -> None:
    if pose.p.shape != (3,) or pose.q.shape != (4,):
        raise InvalidPoseError(
            f"the object needs one pose with p (3,) and q (4,), "
            f"got {tuple(pose.p.shape)} and {tuple(pose.q.shape)}"
        )
    if not torch.isfinite(pose.p).all():
        raise InvalidPoseError("object pose position has NaN or infinite entries")
    se3.check_unit_quaternion(pose.q, name="object pose q")


def voxel_down_sample(cloud: PointCloud, voxel_size: float = DEFAULT_VOXEL_SIZE) -> PointCloud:
    """Average the points (and their view origins) inside each cubic voxel of edge ``voxel_size`` (m).

    Uses open3d's tensor point cloud; the result is on the input's device and dtype. The mean of the
    camera centres that saw a voxel still lies on the visible side of the surface there (a half-space
    is convex), so averaged view origins still orient normals correctly.

    Raises:
        InvalidParameterError: ``voxel_size`` is not positive and finite.
    """
    from pushtorch.deps import import_open3d

    o3d = import_open3d()

    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise InvalidParameterError(f"voxel_size must be positive and finite (m), got {voxel_size}")
    device, dtype = cloud.points.device, cloud.points.dtype
    # open3d's grid has a voxel corner at the origin, so faces at round coordinates (a cube at the
    # origin) would straddle voxel boundaries and come out as two layers; shifting the grid by an
    # irrational fraction of a voxel avoids that. The mean is shift-equivariant, so nothing else changes.
    shift = _GRID_SHIFT * voxel_size
    shifted = (cloud.points.detach().cpu().double() - shift).numpy().astype(np.float32)
    o3d_cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(np.ascontiguousarray(shifted)))
    if cloud.view_origins is not None:
        o3d_cloud.point["view_origins"] = o3d.core.Tensor(
            np.ascontiguousarray(cloud.view_origins.detach().cpu().numpy().astype(np.float32))
        )
    down = o3d_cloud.voxel_down_sample(float(voxel_size))
    positions = down.point.positions.numpy()
    # open3d returns the voxels in hash-map order, which changes from call to call: sort them so the
    # same cloud always down-samples to the same point order (seeded subsets downstream depend on it)
    order = np.lexsort((positions[:, 2], positions[:, 1], positions[:, 0]))
    points = torch.from_numpy(positions[order]).to(device=device, dtype=dtype) + shift
    origins = None
    if cloud.view_origins is not None:
        origins = torch.from_numpy(down.point["view_origins"].numpy()[order]).to(device=device, dtype=dtype)
    return PointCloud(points, origins)


def orbit_viewpoints(
    target: Tensor,
    distance: float,
    n_azimuths: int = 8,
    elevations_deg: tuple[float, ...] = (20.0, 50.0),
    include_top: bool = True,
) -> Tensor:
    """Camera centres ``(V, 3)`` on a sphere of radius ``distance`` around ``target (3,)``.

    ``n_azimuths`` evenly spaced azimuths (starting at -x, the robot's side) at each elevation, plus
    one camera straight above when ``include_top``. ``V = n_azimuths * len(elevations_deg) + include_top``.

    Raises:
        InvalidParameterError: non-positive distance or azimuth count, or no view at all.
    """
    if not (math.isfinite(distance) and distance > 0):
        raise InvalidParameterError(f"camera distance must be positive and finite (m), got {distance}")
    if n_azimuths < 1 and elevations_deg:
        raise InvalidParameterError(f"n_azimuths must be >= 1, got {n_azimuths}")
    target = torch.as_tensor(target, dtype=torch.float32).reshape(3)
    azimuth = math.pi + torch.arange(n_azimuths, dtype=torch.float32) * (2 * math.pi / max(n_azimuths, 1))
    elevation = torch.deg2rad(torch.as_tensor(elevations_deg, dtype=torch.float32))
    az, el = torch.meshgrid(azimuth, elevation, indexing="xy")
    directions = torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1).reshape(-1, 3)
    if include_top:
        directions = torch.cat([directions, torch.tensor([[0.0, 0.0, 1.0]])])
    if directions.shape[0] == 0:
        raise InvalidParameterError("orbit_viewpoints needs at least one elevation or include_top=True")
    return target + distance * directions


def capture_full_cloud(
    obj: ObjectModel,
    pose: se3.Pose | None = None,
    camera: DepthCamera | None = None,
    distance: float | None = None,
    n_azimuths: int = 8,
    elevations_deg: tuple[float, ...] = (20.0, 50.0),
    include_top: bool = True,
    voxel_size: float | None = DEFAULT_VOXEL_SIZE,
    generator: torch.Generator | None = None,
) -> PointCloud:
    """The training cloud: the object seen from several views around it, merged and down-sampled.

    Paper, Experimental Setup: "a full point cloud of the object ... is acquired from multiple views of a
    virtual depth camera". Views: :func:`orbit_viewpoints` (default 8 azimuths × elevations 20° and 50°,
    plus one from the top: 17 views) all looking at the object's centre. The face on the ground is never
    seen, as in the paper's setup.

    Args:
        obj: the object (catalogue or user mesh).
        pose: its world pose; default ``obj.resting_pose()`` (upright at the origin).
        camera: default ``DepthCamera()`` (640×480, 57°, no noise).
        distance: camera distance from the object's centre (m); default
            ``max(DEFAULT_FULL_DISTANCE, 3 × bounding radius)`` so large meshes stay in view.
        n_azimuths, elevations_deg, include_top: the views, see :func:`orbit_viewpoints`.
        voxel_size: down-sampling voxel (m); ``None`` keeps every hit.
        generator: seeds the depth noise; same seed, same cloud.

    Returns:
        A :class:`PointCloud` ``(N, 3)`` float32 on the CPU, with view origins.

    Raises:
        InvalidPoseError, InvalidParameterError, InvalidPointCloudError (nothing seen).
    """
    scene = ObjectScene(obj, pose)
    camera = DepthCamera() if camera is None else camera
    if distance is None:
        distance = max(DEFAULT_FULL_DISTANCE, 3.0 * scene.bounding_radius)
    eyes = orbit_viewpoints(scene.centre, distance, n_azimuths, elevations_deg, include_top)
    cloud = scene.capture(camera, eyes, generator=generator)
    return cloud if voxel_size is None else voxel_down_sample(cloud, voxel_size)


def default_partial_camera_position(pose: se3.Pose) -> Tensor:
    """The default single-shot camera centre ``(3,)`` for an object at ``pose``.

    ``DEFAULT_PARTIAL_OFFSET``: 0.8 m from the object along world -x (the robot's side, since the robot
    pushes along +x), 0.6 m above the ground, like a depth camera on the robot's mast.
    """
    dx, dy, height = DEFAULT_PARTIAL_OFFSET
    p = pose.p.detach().float().cpu()
    return torch.stack([p[0] + dx, p[1] + dy, torch.tensor(height)])


def capture_partial_cloud(
    obj: ObjectModel,
    pose: se3.Pose | None = None,
    camera_position: Tensor | None = None,
    target: Tensor | None = None,
    camera: DepthCamera | None = None,
    voxel_size: float | None = DEFAULT_VOXEL_SIZE,
    generator: torch.Generator | None = None,
) -> PointCloud:
    """The prediction cloud: one shot of the depth camera (paper, Experimental Setup).

    Only the surface visible from ``camera_position`` is returned: faces turned away from it and parts
    hidden behind the object itself or the ground are absent.

    Args:
        obj: the object.
        pose: its world pose; default ``obj.resting_pose()``.
        camera_position: camera centre ``(3,)`` in the world frame; default
            :func:`default_partial_camera_position` (robot side, -x, elevated).
        target: point looked at ``(3,)``; default the object's centre.
        camera: default ``DepthCamera()`` (640×480, 57°, no noise).
        voxel_size: down-sampling voxel (m); ``None`` keeps every hit.
        generator: seeds the depth noise.

    Returns:
        A :class:`PointCloud` float32 on the CPU, with the camera centre as every point's view origin.

    Raises:
        InvalidPoseError, InvalidParameterError, InvalidPointCloudError (the object is out of view).
    """
    scene = ObjectScene(obj, pose)
    camera = DepthCamera() if camera is None else camera
    eye = default_partial_camera_position(scene.pose) if camera_position is None else camera_position
    eye = torch.as_tensor(eye, dtype=torch.float32)
    if eye.shape != (3,):
        raise InvalidParameterError(f"camera_position must have shape (3,), got {tuple(eye.shape)}")
    cloud = scene.capture(camera, eye, target=target, generator=generator)
    return cloud if voxel_size is None else voxel_down_sample(cloud, voxel_size)


def load_cloud_file(path) -> PointCloud:
    """A point cloud from a file: ``.ply`` or ``.pcd`` (open3d's reader) or ``.npz`` (an ``(N, 3)`` array
    ``points`` and optionally ``view_origins``), metres, in the frame it was written in (push tables: world).

    Raises:
        InvalidPointCloudError: a missing file, another ending, an unreadable file, or a cloud that is empty,
            of the wrong shape or not finite (the message names the file).
    """
    path = Path(path)
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise InvalidPointCloudError(f"{path}: a point cloud file must end in {', '.join(CLOUD_SUFFIXES)}")
    if not path.is_file():
        raise InvalidPointCloudError(f"point cloud file not found: {path}")
    origins = None
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as arrays:
                if "points" not in arrays:
                    raise InvalidPointCloudError(f"{path} holds no array 'points' "
                                                 f"(it has {', '.join(arrays) or 'none'})")
                points = np.asarray(arrays["points"], dtype=np.float64)
                origins = np.asarray(arrays["view_origins"], dtype=np.float64) if "view_origins" in arrays else None
        else:
            from pushtorch.deps import import_open3d

            points = np.asarray(import_open3d().io.read_point_cloud(str(path)).points, dtype=np.float64)
    except InvalidPointCloudError:
        raise
    except Exception as exc:  # numpy and open3d raise many types on a bad file: the cause is the file
        raise InvalidPointCloudError(f"could not read a point cloud from {path} ({type(exc).__name__}: {exc})") from exc
    try:
        return PointCloud(torch.as_tensor(points, dtype=torch.float32),
                          None if origins is None else torch.as_tensor(origins, dtype=torch.float32))
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f"{path}: {exc}") from exc


def save_cloud_file(cloud: PointCloud, path) -> None:
    """Write ``cloud`` as ``.npz`` (its points and view origins, float32, exact), atomically."""
    arrays = {"points": cloud.points.detach().cpu().float().numpy()}
    if cloud.view_origins is not None:
        arrays["view_origins"] = cloud.view_origins.detach().cpu().float().numpy()
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(Path(path), buffer.getvalue())
