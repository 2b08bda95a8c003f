"""Rendering the stereo pair a robot's camera sees in a :class:`nav.world.World`.

Both views are ideal pinhole cameras with the same intrinsics and parallel optical axes, level,
``height_m`` above the floor (a rectified pair, as the stereo graph expects): the left camera on
the robot's centre line ``forward_m`` ahead of the axle, the right one ``baseline_m`` to its
right. A pixel's ray is cast horizontally through the floor plan; it meets the nearest face if
the face is tall enough there, else the floor (below the horizon) or the sky (above). Each view
gets its own sensor noise, so matching is not trivially exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nav.camera import CameraModel
from nav.world import World

SKY_GREY = 200.0
NOISE_GREY = 2.0


@dataclass(frozen=True)
class Pose:
    """Robot pose on the floor plan: axle centre (m) and heading (rad, 0 = east, CCW)."""

    x: float
    y: float
    theta: float

    def forward(self) -> np.ndarray:
        return np.array([math.cos(self.theta), math.sin(self.theta)])

    def right(self) -> np.ndarray:
        return np.array([math.sin(self.theta), -math.cos(self.theta)])


class StereoRenderer:
    """Renders rectified RGB uint8 pairs, H×W×3, of a world from a robot pose."""

    def __init__(self, camera: CameraModel, width: int, height: int, seed: int = 0) -> None:
        self.camera = camera
        self.width = width
        self.height = height
        self._rng = np.random.default_rng(seed)
        self._u = (np.arange(width) - camera.cx_px) / camera.fx_px  # lateral slope per column
        self._v = (np.arange(height) - camera.cy_px) / camera.fx_px  # downward slope per row

    def pair(self, world: World, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        centre = np.array([pose.x, pose.y]) + self.camera.forward_m * pose.forward()
        left = self._view(world, pose, centre)
        right = self._view(world, pose, centre + self.camera.baseline_m * pose.right())
        return left, right

    def _view(self, world: World, pose: Pose, origin: np.ndarray) -> np.ndarray:
        forward, right = pose.forward(), pose.right()
        # Ray of column u: forward + slope·right; λ along it is the depth Z of what it meets.
        directions = forward[None, :] + self._u[:, None] * right[None, :]  # (W, 2)
        depth, face, along, tall = world.cast(origin, directions)
        h_cam = self.camera.height_m
        rows = self._v[:, None]  # (H, 1)
        z_face = h_cam - rows * depth[None, :]  # height where the ray meets the face
        with np.errstate(divide="ignore"):
            floor_depth = np.where(rows > 0, h_cam / rows, np.inf)  # (H, 1)
        on_face = (z_face >= 0) & (z_face <= tall[None, :]) & np.isfinite(depth)[None, :]
        on_floor = (floor_depth < depth[None, :]) | (~on_face & (rows > 0))
        grey = np.full((self.height, self.width), SKY_GREY)
        tint = np.ones((self.height, self.width, 3))

        face_px = on_face & ~on_floor
        if face_px.any():
            columns = np.broadcast_to(np.arange(self.width), grey.shape)[face_px]
            which = face[columns]
            s = along[columns]
            t = z_face[face_px]
            values = np.empty(s.shape)
            for i in np.unique(which):
                mine = which == i
                values[mine] = world.textures[i].grey(s[mine], t[mine])
                tint[face_px.nonzero()[0][mine], columns[mine]] = world.textures[i].tint
            grey[face_px] = values

        if on_floor.any():
            lam = np.broadcast_to(floor_depth, grey.shape)[on_floor]
            columns = np.broadcast_to(np.arange(self.width), grey.shape)[on_floor]
            points = origin + lam[:, None] * directions[columns]
            grey[on_floor] = world.floor.grey(points[:, 0], points[:, 1])
            tint[on_floor] = world.floor.tint

        noisy = grey[..., None] * tint + self._rng.normal(0.0, NOISE_GREY, tint.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
