"""Camera trajectories of the kinds real multi-view datasets hold, for procedural scenes.

World frame: z up, floor at z = 0. All paths return OpenCV camera-to-world ``[frames, 4, 4]``.

* ``orbit`` -- circling an object while looking at it (object-centric captures, GSO-like).
* ``walk`` -- forward walk-through with head sway and bob (DL3DV / RealEstate10K videos).
* ``sweep`` -- standing near one spot and panning across a wide angle (ScanNet-style
  indoor sweeps).
"""

from __future__ import annotations

import typing
from typing import Literal

import numpy as np

from llrmpp_jax.array_typing import Float
from llrmpp_jax.errors import UserError

PathKind = Literal["orbit", "walk", "sweep"]
PATH_KINDS: tuple[str, ...] = typing.get_args(PathKind)
WORLD_UP = np.array([0.0, 0.0, 1.0])


def look_at(
    eye: Float[np.ndarray, "frames 3"],
    target: Float[np.ndarray, "frames 3"],
    roll: Float[np.ndarray, " frames"] | None = None,
) -> Float[np.ndarray, "frames 4 4"]:
    """OpenCV camera-to-world looking from ``eye`` at ``target`` with world z up (image
    rows point down the world), optionally rolled by ``roll`` radians about the view axis."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    fwd /= np.linalg.norm(fwd, axis=-1, keepdims=True)
    right = np.cross(fwd, WORLD_UP[None, :])
    norm = np.linalg.norm(right, axis=-1, keepdims=True)
    if (norm < 1e-6).any():
        raise UserError("look_at: viewing direction is parallel to world up; choose another target")
    right /= norm
    down = np.cross(fwd, right)
    if roll is not None:
        c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
        right, down = c * right + s * down, -s * right + c * down
    c2w = np.tile(np.eye(4), (eye.shape[0], 1, 1))
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, fwd, eye
    return c2w


def orbit_path(
    rng: np.random.Generator, n: int, center: Float[np.ndarray, " 3"], min_radius: float, max_radius: float
) -> Float[np.ndarray, "frames 4 4"]:
    """Orbit of ``n`` views around ``center`` over a random arc of 120-360 degrees, with
    radius and height drifting smoothly (radius in ``[min_radius, max_radius]``)."""
    arc = np.deg2rad(rng.uniform(120, 360))
    start = rng.uniform(0, 2 * np.pi)
    t = np.linspace(0.0, 1.0, n)
    angle = start + arc * t * (1 if rng.random() < 0.5 else -1)
    radius = rng.uniform(min_radius, max_radius) + 0.15 * (max_radius - min_radius) * np.sin(
        2 * np.pi * t + rng.uniform(0, 6.3)
    )
    radius = np.clip(radius, min_radius, max_radius)
    height = rng.uniform(0.7, 2.0) + 0.25 * np.sin(np.pi * t * rng.uniform(1, 3))
    eye = np.stack([center[0] + radius * np.cos(angle), center[1] + radius * np.sin(angle), height], axis=1)
    target = center[None, :] + rng.normal(0.0, 0.05, size=(n, 3))
    return look_at(eye, target, roll=rng.normal(0.0, 0.02, size=n))


def walk_path(rng: np.random.Generator, n: int, half_x: float, half_y: float) -> Float[np.ndarray, "frames 4 4"]:
    """Forward walk of ``n`` views across a room of half extents ``(half_x, half_y)``,
    keeping 0.8 m from the walls, with yaw sway (±20°), pitch and head bob."""
    margin = 0.8
    axis = int(rng.random() < 0.5)  # walk along x or along y
    half = (half_x, half_y)
    length = 2 * (half[axis] - margin)
    t = np.linspace(0.0, 1.0, n)
    along = -half[axis] + margin + length * rng.uniform(0.5, 1.0) * t
    lateral0 = rng.uniform(-0.4, 0.4) * (half[1 - axis] - margin)
    lateral = lateral0 + 0.3 * np.sin(2 * np.pi * t * rng.uniform(0.5, 1.5))
    lateral = np.clip(lateral, -half[1 - axis] + margin, half[1 - axis] - margin)
    direction = 1 if rng.random() < 0.5 else -1
    along = along * direction
    eye = np.zeros((n, 3))
    eye[:, axis], eye[:, 1 - axis] = along, lateral
    eye[:, 2] = rng.uniform(1.3, 1.7) + 0.03 * np.sin(2 * np.pi * t * 6)
    yaw = np.deg2rad(20.0) * np.sin(2 * np.pi * t * rng.uniform(0.5, 2.0) + rng.uniform(0, 6.3))
    pitch = np.deg2rad(rng.uniform(-12, 4)) + np.deg2rad(4.0) * np.sin(2 * np.pi * t * rng.uniform(0.5, 2))
    heading = np.zeros((n, 3))
    heading[:, axis] = direction
    cos_y, sin_y = np.cos(yaw), np.sin(yaw)
    fwd = np.stack(
        [heading[:, 0] * cos_y - heading[:, 1] * sin_y, heading[:, 0] * sin_y + heading[:, 1] * cos_y, np.tan(pitch)],
        axis=1,
    )
    return look_at(eye, eye + fwd, roll=rng.normal(0.0, 0.02, size=n))


def sweep_path(rng: np.random.Generator, n: int, half_x: float, half_y: float) -> Float[np.ndarray, "frames 4 4"]:
    """Wide indoor pan of ``n`` views: the camera drifts inside a 0.4 m circle near the room
    centre while its heading turns through 120-300 degrees and its pitch nods."""
    t = np.linspace(0.0, 1.0, n)
    base = np.array([rng.uniform(-0.3, 0.3) * half_x, rng.uniform(-0.3, 0.3) * half_y])
    phase = rng.uniform(0, 2 * np.pi)
    eye = np.zeros((n, 3))
    eye[:, 0] = base[0] + 0.4 * t * np.cos(phase + 3 * t)
    eye[:, 1] = base[1] + 0.4 * t * np.sin(phase + 3 * t)
    eye[:, 2] = rng.uniform(1.2, 1.8)
    heading = rng.uniform(0, 2 * np.pi) + np.deg2rad(rng.uniform(120, 300)) * t * (1 if rng.random() < 0.5 else -1)
    pitch = np.deg2rad(rng.uniform(-10, 5)) + np.deg2rad(12.0) * np.sin(2 * np.pi * t * rng.uniform(0.5, 1.5))
    fwd = np.stack([np.cos(heading), np.sin(heading), np.tan(pitch)], axis=1)
    return look_at(eye, eye + fwd, roll=rng.normal(0.0, 0.02, size=n))


def pinhole_intrinsics(
    rng: np.random.Generator, n: int, height: int, width: int, fov_deg: tuple[float, float]
) -> Float[np.ndarray, "frames 4"]:
    """One random camera for the whole path: horizontal field of view drawn from
    ``fov_deg``, square pixels, principal point within 2% of the image centre."""
    fov = np.deg2rad(rng.uniform(*fov_deg))
    f = 0.5 * width / np.tan(0.5 * fov)
    cx = width * (0.5 + rng.uniform(-0.02, 0.02))
    cy = height * (0.5 + rng.uniform(-0.02, 0.02))
    return np.tile(np.array([[f, f, cx, cy]]), (n, 1))
