"""Sensors rendered from the same :class:`~rtabmap_ros2.sim.world.World`: a 2D laser and a Kinect.

Both are ray casts against the wall segments (vectorised numpy, no loop over pixels), so the
laser ranges, the depth image and the colour image agree with the ground-truth geometry.

Mounts (base frame: x forward, y left, z up), the defaults of :class:`SensorRig` (:func:`sensor_rig`
mounts them elsewhere, e.g. a laser 0.2 m ahead of the base; the scans are then in the laser's
frame and the images in the camera's, as a real robot's drivers publish them):

* laser: ``T_base_laser`` = translation (0, 0, :data:`LASER_HEIGHT_M`), no rotation; 240 deg field
  of view, 0.5 deg resolution (481 beams), 0.1-30 m, gaussian range noise sigma 1 cm; beams
  beyond the range limit are ``inf``.
* RGB-D camera: 640x480, Kinect intrinsics fx=fy=525, cx=319.5, cy=239.5; optical centre at
  (0.1, 0, 0.5) m looking forward, ``T_base_camera`` rotation base <- optical
  ``[[0,0,1],[-1,0,0],[0,-1,0]]`` (optical z forward, x right, y down). The camera is level, so a
  pixel column is a vertical plane: one 2D ray per column finds the wall, and each row of the
  column then sees the wall, the floor or the ceiling (walls :data:`WALL_HEIGHT_M` high).
  Depth = optical-frame z of the hit point, valid in [0.5, 8] m (NaN outside), with Kinect-like
  noise sigma = 1.5e-3 z^2 m. The image is textured (posters with mip levels, paint, floor,
  ceiling), shaded by distance and incidence, with sensor noise sigma 2 grey levels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rtabmap_ros2.core.sensor import CameraModel, LaserScan
from rtabmap_ros2.sim.world import (
    ATLAS_LEVELS, ATLAS_SHAPE, BASEBOARD_HEIGHT_M, FLOOR_TEXEL_M, PAINT_TEXEL_M, PLAIN,
    WALL_HEIGHT_M, World,
)

LASER_HEIGHT_M = 0.3
LASER_FOV_RAD = np.deg2rad(240.0)
LASER_RESOLUTION_RAD = np.deg2rad(0.5)
LASER_RANGE_MIN_M = 0.1
LASER_RANGE_MAX_M = 30.0
LASER_NOISE_SIGMA_M = 0.01

CAMERA_XYZ_M = (0.1, 0.0, 0.5)
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
KINECT_FX = KINECT_FY = 525.0
KINECT_CX, KINECT_CY = 319.5, 239.5
IMAGE_WIDTH, IMAGE_HEIGHT = 640, 480
DEPTH_MIN_M = 0.5
DEPTH_MAX_M = 8.0
DEPTH_NOISE_COEFF = 1.5e-3  # sigma (m) = coeff * z^2
PIXEL_NOISE_SIGMA = 2.0  # grey levels
NO_HIT_M = 1e6  # a ray that leaves the building (never happens inside it)

# Shading: brightness = SHADE_FAR + (1 - SHADE_FAR) * exp(-d / SHADE_DISTANCE_M), times an
# incidence term INCIDENCE_AMBIENT + (1 - INCIDENCE_AMBIENT) * |cos(incidence)| on walls.
SHADE_FAR = 0.55
SHADE_DISTANCE_M = 15.0
INCIDENCE_AMBIENT = 0.7
BASEBOARD_GAIN = 0.45


def _rigid(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


T_BASE_LASER = _rigid(np.eye(3), (0.0, 0.0, LASER_HEIGHT_M))
T_BASE_CAMERA = _rigid(R_BASE_OPTICAL, CAMERA_XYZ_M)


def kinect_camera(T_base_camera: np.ndarray | None = None) -> CameraModel:
    """The simulated Kinect: 640x480, fx=fy=525, cx=319.5, cy=239.5, ``T_base_camera`` above by default."""
    T = T_BASE_CAMERA if T_base_camera is None else T_base_camera
    return CameraModel(KINECT_FX, KINECT_FY, KINECT_CX, KINECT_CY, IMAGE_WIDTH, IMAGE_HEIGHT, np.array(T, dtype=float))


@dataclass(frozen=True)
class SensorRig:
    """Sensor models and mounts (noise can be switched off, e.g. for geometry tests)."""

    camera: CameraModel = field(default_factory=kinect_camera)
    T_base_laser: np.ndarray = field(default_factory=lambda: T_BASE_LASER.copy())
    laser_noise_sigma_m: float = LASER_NOISE_SIGMA_M
    depth_noise_coeff: float = DEPTH_NOISE_COEFF
    pixel_noise_sigma: float = PIXEL_NOISE_SIGMA


LEVEL_TOLERANCE = 1e-4  # ~0.01 deg: 1.5708 for pi/2 is level enough


def sensor_rig(laser_mount=None, camera_mount=None) -> SensorRig:
    """A rig with the laser and/or camera mounted elsewhere than the defaults.

    Args:
        laser_mount: ``[x, y, z, roll, pitch, yaw]`` (m, rad) of the laser in the base frame; level
            (roll = pitch = 0): the simulated laser scans the horizontal plane.
        camera_mount: ``[x, y, z, roll, pitch, yaw]`` of the camera's optical frame (z forward, x
            right, y down) in the base frame; the camera must stay level (optical y pointing down,
            e.g. roll = -pi/2, pitch = 0, any yaw - pi/2): the renderer casts one vertical plane per column.

    Raises:
        RtabmapError: a mount that is not 6 numbers or not level.
    """
    from rtabmap_ros2.core.transforms import from_xyz_rpy
    from rtabmap_ros2.errors import RtabmapError

    def parse(name: str, mount) -> np.ndarray:
        try:
            return from_xyz_rpy(mount)
        except ValueError as exc:
            raise RtabmapError(f"{name} mount: {exc}") from exc

    kwargs = {}
    if laser_mount is not None:
        T = parse("laser", laser_mount)
        if abs(T[2, 2] - 1.0) > LEVEL_TOLERANCE:
            raise RtabmapError(f"laser mount {list(laser_mount)} is not level (roll and pitch must be 0): "
                               "the simulated laser scans the horizontal plane")
        kwargs["T_base_laser"] = T
    if camera_mount is not None:
        T = parse("camera", camera_mount)
        if not np.allclose(T[:3, 1], (0.0, 0.0, -1.0), atol=LEVEL_TOLERANCE):
            raise RtabmapError(f"camera mount {list(camera_mount)} is not level: the optical y axis must point "
                               "down (roll -pi/2, pitch 0, yaw -pi/2 looks forward)")
        kwargs["camera"] = kinect_camera(T)
    return SensorRig(**kwargs)


def raycast(world: World, origin_xy: np.ndarray, directions_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest wall along 2D rays ``origin + s * direction``.

    Args:
        origin_xy: (2,) ray origin (m, world frame).
        directions_xy: (M,2) ray directions (world frame, any length).

    Returns:
        s: (M,) ray parameter of the hit (m if directions are unit), NO_HIT_M without a hit;
        wall: (M,) index of the wall hit (0 without a hit); t: (M,) hit position along the wall
        in [0, 1] from ``p0``.
    """
    o = np.asarray(origin_xy, dtype=np.float64)
    d = np.asarray(directions_xy, dtype=np.float64)
    e = world.p1 - world.p0                     # (N,2)
    w = world.p0 - o                            # (N,2)
    denom = d[:, 0:1] * e[None, :, 1] - d[:, 1:2] * e[None, :, 0]   # cross(d, e): (M,N)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / denom
        t = (w[None, :, 0] * d[:, 1:2] - w[None, :, 1] * d[:, 0:1]) / denom
    eps = 1e-9
    valid = (np.abs(denom) > eps) & (s > eps) & (t >= -eps) & (t <= 1 + eps)
    s = np.where(valid, s, NO_HIT_M)
    wall = np.argmin(s, axis=1)
    rows = np.arange(len(d))
    return s[rows, wall], wall, np.clip(t[rows, wall], 0.0, 1.0)


def render_scan(world: World, T_world_base: np.ndarray, rng: np.random.Generator | None = None,
                rig: SensorRig = SensorRig()) -> LaserScan:
    """Laser scan at the base pose ``T_world_base`` (4x4, planar): ranges (481,) m, ``inf`` = no return."""
    T = T_world_base @ rig.T_base_laser
    n = int(round(LASER_FOV_RAD / LASER_RESOLUTION_RAD)) + 1
    angle_min = -LASER_FOV_RAD / 2
    angles = angle_min + LASER_RESOLUTION_RAD * np.arange(n)
    yaw = np.arctan2(T[1, 0], T[0, 0])
    dirs = np.stack([np.cos(yaw + angles), np.sin(yaw + angles)], axis=1)
    ranges, _, _ = raycast(world, T[:2, 3], dirs)
    if rng is not None and rig.laser_noise_sigma_m > 0:
        ranges = ranges + rng.normal(0.0, rig.laser_noise_sigma_m, size=n)
    ranges = np.where((ranges >= LASER_RANGE_MIN_M) & (ranges < LASER_RANGE_MAX_M), ranges, np.inf)
    return LaserScan(ranges=ranges.astype(np.float32), angle_min=float(angle_min),
                     angle_increment=float(LASER_RESOLUTION_RAD), range_min=LASER_RANGE_MIN_M,
                     range_max=LASER_RANGE_MAX_M, T_base_laser=rig.T_base_laser.copy())


def _shade(distance_m: np.ndarray) -> np.ndarray:
    return SHADE_FAR + (1.0 - SHADE_FAR) * np.exp(-distance_m / SHADE_DISTANCE_M)


def render_rgbd(world: World, T_world_base: np.ndarray, rng: np.random.Generator | None = None,
                rig: SensorRig = SensorRig()) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth images at the base pose ``T_world_base`` (4x4, planar).

    Returns:
        rgb: (480,640,3) uint8 RGB; depth_m: (480,640) float32 optical-frame z (m), NaN invalid.
        Without ``rng`` the images are noise-free (exact geometry).
    """
    cam = rig.camera
    T_world_cam = T_world_base @ cam.T_base_camera
    centre = T_world_cam[:2, 3]
    cam_height = T_world_cam[2, 3]
    forward = T_world_cam[:2, 2]   # optical z in the world plane
    right = T_world_cam[:2, 0]     # optical x in the world plane
    H, W = cam.height, cam.width

    # One ray per column: direction forward + k_u * right, so the ray parameter is the optical z.
    k_u = (np.arange(W) - cam.cx) / cam.fx                     # (W,)
    dirs = forward[None] + k_u[:, None] * right[None]          # (W,2)
    s_wall, wall, t = raycast(world, centre, dirs)             # (W,)
    k_v = (np.arange(H) - cam.cy) / cam.fy                     # (H,) rows below the centre look down
    height = cam_height - k_v[:, None] * s_wall[None, :]       # (H,W) height of the wall point seen

    is_wall = (height >= 0.0) & (height <= WALL_HEIGHT_M)
    is_floor = height < 0.0
    is_ceiling = height > WALL_HEIGHT_M
    with np.errstate(divide="ignore"):
        s_floor = np.where(k_v > 0, cam_height / np.where(k_v > 0, k_v, 1.0), np.inf)               # (H,)
        s_ceiling = np.where(k_v < 0, (WALL_HEIGHT_M - cam_height) / np.where(k_v < 0, -k_v, 1.0), np.inf)
    depth = np.where(is_wall, s_wall[None, :], np.where(is_floor, s_floor[:, None], s_ceiling[:, None]))

    rgb = np.empty((H, W, 3), dtype=np.float32)
    # Walls: paint (tiled noise, baseboard) then posters, looked up per pixel.
    u_along = t * world.lengths[wall]                          # (W,) m from p0
    rows_w, cols_w = np.nonzero(is_wall)
    h_w = height[rows_w, cols_w]
    wall_px = wall[cols_w]
    noise = world.paint_noise
    tn = noise.shape[0]
    paint = world.paint_rgb[wall_px] * (1.0 + noise[(h_w / PAINT_TEXEL_M).astype(np.int64) % tn,
                                                   (u_along[cols_w] / PAINT_TEXEL_M).astype(np.int64) % tn])[:, None]
    paint[h_w < BASEBOARD_HEIGHT_M] *= BASEBOARD_GAIN
    rect = world.poster_rect[wall_px]                           # (P,4) u0 u1 v0 v1, NaN if plain
    with np.errstate(invalid="ignore"):
        in_poster = ((world.kind[wall_px] != PLAIN) & (u_along[cols_w] >= rect[:, 0]) & (u_along[cols_w] < rect[:, 1])
                     & (h_w >= rect[:, 2]) & (h_w < rect[:, 3]))
    if in_poster.any():
        # Mip level per column from the pixel footprint on the wall vs the texel size.
        e = world.p1[wall] - world.p0[wall]
        normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.maximum(world.lengths[wall], 1e-9)[:, None]
        ray_len = np.linalg.norm(dirs, axis=1)
        cos_inc = np.abs((dirs * normal).sum(axis=1)) / ray_len
        footprint = s_wall * ray_len / (cam.fx * np.maximum(cos_inc, 0.05))   # m per pixel along the wall
        rect_c = world.poster_rect[wall]
        texel = (rect_c[:, 1] - rect_c[:, 0]) / ATLAS_SHAPE[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            level = np.clip(np.floor(np.log2(np.maximum(footprint / texel, 1.0))), 0, ATLAS_LEVELS - 1)
        level = np.nan_to_num(level).astype(np.int64)
        idx = np.flatnonzero(in_poster)
        r = rect[idx]
        fu = (u_along[cols_w[idx]] - r[:, 0]) / (r[:, 1] - r[:, 0])
        fv = (r[:, 3] - h_w[idx]) / (r[:, 3] - r[:, 2])
        tex_id = world.texture_id[wall_px[idx]]
        lev = level[cols_w[idx]]
        for lv in range(ATLAS_LEVELS):
            sel = lev == lv
            if not sel.any():
                continue
            atlas = world.atlas[lv]
            th, tw = atlas.shape[1:3]
            ti = np.minimum((fv[sel] * th).astype(np.int64), th - 1)
            tj = np.minimum((fu[sel] * tw).astype(np.int64), tw - 1)
            flat = (tex_id[sel] * th + ti) * tw + tj
            paint[idx[sel]] = np.take(atlas.reshape(-1, 3), flat, axis=0)
        incidence = INCIDENCE_AMBIENT + (1.0 - INCIDENCE_AMBIENT) * cos_inc
    else:
        e = world.p1[wall] - world.p0[wall]
        normal = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.maximum(world.lengths[wall], 1e-9)[:, None]
        incidence = INCIDENCE_AMBIENT + (1.0 - INCIDENCE_AMBIENT) * np.abs((dirs * normal).sum(1)) / np.linalg.norm(dirs, axis=1)
    rgb[rows_w, cols_w] = paint * (incidence * _shade(s_wall))[cols_w, None]

    # Floor and ceiling: world point of each pixel, tiled texture.
    for mask, s_row, tex, texel in ((is_floor, s_floor, world.floor_tex, FLOOR_TEXEL_M),
                                    (is_ceiling, s_ceiling, world.ceiling_tex, FLOOR_TEXEL_M)):
        rr, cc = np.nonzero(mask)
        s = s_row[rr]
        xy = centre[None] + s[:, None] * dirs[cc]
        tn = tex.shape[0]
        flat = ((xy[:, 1] / texel).astype(np.int64) % tn) * tn + (xy[:, 0] / texel).astype(np.int64) % tn
        rgb[rr, cc] = np.take(tex.reshape(-1, 3), flat, axis=0) * _shade(s)[:, None]

    depth = depth.astype(np.float32)
    if rng is not None:
        if rig.pixel_noise_sigma > 0:
            rgb += (rig.pixel_noise_sigma * rng.standard_normal(size=(H, W, 1), dtype=np.float32))
        if rig.depth_noise_coeff > 0:
            depth = depth + (rig.depth_noise_coeff * depth * depth
                             * rng.standard_normal(size=(H, W), dtype=np.float32))
    depth[(depth < DEPTH_MIN_M) | (depth > DEPTH_MAX_M) | ~np.isfinite(depth)] = np.nan
    return np.clip(rgb, 0, 255).astype(np.uint8), depth
