"""A 2D world of walls and boxes with textured faces, for the closed-loop simulation.

Everything stands on the floor (z = 0) and is a vertical face over a segment of the floor plan
(x east, y north, metres): a wall is one segment, a box its four sides. Faces and the floor carry
procedural textures (sums of plane waves with random directions and 3–25 cm wavelengths, seeded
per surface) so that a rendered stereo pair can be matched, as real surfaces can. A point of the
world is a clearance query (distance to the nearest face) and a ray cast (nearest face along
horizontal rays), which is all the renderer and the collision check need.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from common.errors import UserError

DEFAULT_HEIGHT_M = 0.8
# Plane waves per texture and their wavelength range: fine enough for disparities at 0.3–3 m,
# coarse enough not to alias between the two views at the distances the robot stops from.
TEXTURE_WAVES = 12
MIN_WAVELENGTH_M = 0.03
MAX_WAVELENGTH_M = 0.25


@dataclass(frozen=True)
class Texture:
    """Grey level 0..255 as a function of two surface coordinates (metres)."""

    directions: np.ndarray  # (waves, 2) wave vectors, rad/m
    phases: np.ndarray  # (waves,)
    amplitudes: np.ndarray  # (waves,)
    tint: np.ndarray  # (3,) RGB gain

    @classmethod
    def random(cls, rng: np.random.Generator) -> Texture:
        angles = rng.uniform(0, math.pi, TEXTURE_WAVES)
        wavelengths = np.exp(
            rng.uniform(math.log(MIN_WAVELENGTH_M), math.log(MAX_WAVELENGTH_M), TEXTURE_WAVES)
        )
        k = 2 * math.pi / wavelengths
        directions = np.stack([k * np.cos(angles), k * np.sin(angles)], axis=-1)
        amplitudes = rng.uniform(0.5, 1.0, TEXTURE_WAVES)
        return cls(
            directions,
            rng.uniform(0, 2 * math.pi, TEXTURE_WAVES),
            amplitudes / amplitudes.sum(),
            rng.uniform(0.6, 1.0, 3),
        )

    def grey(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Grey level at surface coordinates (s, t), any matching shapes."""
        phase = s[..., None] * self.directions[:, 0] + t[..., None] * self.directions[:, 1]
        wave = np.sin(phase + self.phases) @ self.amplitudes
        return 128.0 + 110.0 * wave


@dataclass(frozen=True)
class Face:
    """A vertical face over the floor segment a → b, ``height_m`` tall."""

    a: tuple[float, float]
    b: tuple[float, float]
    height_m: float = DEFAULT_HEIGHT_M

    @property
    def length_m(self) -> float:
        return math.dist(self.a, self.b)


@dataclass
class World:
    """Faces with their textures, and the floor's."""

    faces: list[Face]
    seed: int = 0
    textures: list[Texture] = field(init=False)
    floor: Texture = field(init=False)

    def __post_init__(self) -> None:
        if not self.faces:
            raise UserError("a world needs at least one wall or box")
        for face in self.faces:
            if face.length_m <= 0 or face.height_m <= 0:
                raise UserError(f"face {face} has no extent")
        rng = np.random.default_rng(self.seed)
        self.textures = [Texture.random(rng) for _ in self.faces]
        self.floor = Texture.random(rng)
        self._a = np.array([f.a for f in self.faces], dtype=np.float64)
        self._b = np.array([f.b for f in self.faces], dtype=np.float64)
        self._heights = np.array([f.height_m for f in self.faces])

    @staticmethod
    def wall(
        a: tuple[float, float], b: tuple[float, float], height_m: float = DEFAULT_HEIGHT_M
    ) -> list[Face]:
        return [Face(a, b, height_m)]

    @staticmethod
    def box(
        centre: tuple[float, float], size: tuple[float, float], height_m: float = DEFAULT_HEIGHT_M
    ) -> list[Face]:
        """An axis-aligned box: its four sides."""
        (cx, cy), (w, d) = centre, size
        corners = [
            (cx - w / 2, cy - d / 2),
            (cx + w / 2, cy - d / 2),
            (cx + w / 2, cy + d / 2),
            (cx - w / 2, cy + d / 2),
        ]
        return [Face(corners[i], corners[(i + 1) % 4], height_m) for i in range(4)]

    def clearance(self, x: float, y: float) -> float:
        """Distance from (x, y) to the nearest face (metres)."""
        p = np.array([x, y])
        ab = self._b - self._a
        u = np.clip(np.einsum("ij,ij->i", p - self._a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1)
        nearest = self._a + u[:, None] * ab
        return float(np.min(np.linalg.norm(p - nearest, axis=1)))

    def cast(
        self, origin: np.ndarray, directions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Nearest face along each horizontal ray origin + λ·direction (λ > 0): λ (inf where
        none), the face index, the position along the face (m from a) and the face height."""
        ab = self._b - self._a  # (M, 2)
        ao = self._a - origin  # (M, 2)
        r = directions[:, None, :]  # (N, 1, 2)
        denom = r[..., 0] * ab[:, 1] - r[..., 1] * ab[:, 0]  # cross(r, ab): (N, M)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (ao[:, 0] * ab[:, 1] - ao[:, 1] * ab[:, 0]) / denom
            u = (ao[:, 0] * r[..., 1] - ao[:, 1] * r[..., 0]) / denom
        hit = (lam > 1e-9) & (u >= 0) & (u <= 1) & np.isfinite(lam)
        lam = np.where(hit, lam, np.inf)
        face = np.argmin(lam, axis=1)
        rows = np.arange(len(directions))
        best = lam[rows, face]
        along = u[rows, face] * np.linalg.norm(ab, axis=1)[face]
        return best, face, np.where(np.isfinite(best), along, 0.0), self._heights[face]


def corridor_with_wall(distance_m: float = 3.0, half_width_m: float = 1.5) -> World:
    """A corridor heading north from the origin, closed by a wall ``distance_m`` ahead."""
    return World(
        World.wall((-half_width_m, distance_m), (half_width_m, distance_m))
        + World.wall((-half_width_m, -1.0), (-half_width_m, distance_m))
        + World.wall((half_width_m, distance_m), (half_width_m, -1.0))
    )
