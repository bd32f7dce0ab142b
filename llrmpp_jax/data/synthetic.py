"""Procedural multi-view scenes with exact ground truth, made on the CPU on the fly.

A seed fixes everything: a room (z up, floor at z = 0; floor, ceiling and four walls each
with its own tiled texture) furnished with boxes, spheres and posters, a camera path (orbit / walk / sweep,
:mod:`camera_paths`) and one
pinhole camera. Views are rendered by analytic ray casting in NumPy: every pixel centre's
ray is intersected with every primitive, the nearest hit gives the exact z-depth, and the
colour is a mip-mapped texture lookup at the surface UV times a view-independent
(Lambertian) shading, so all views agree on the colour of a surface point.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.data.camera_paths import PATH_KINDS, PathKind, orbit_path, pinhole_intrinsics, sweep_path, walk_path
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.textures import POSTER_TEXTURES, sample_texture, texture_bank, texture_ids
from llrmpp_jax.geometry import pixel_rays

_EPS = 1e-4  # minimum hit distance (m)


@dataclass(frozen=True)
class Layout:
    """Scene geometry and materials (world metres, z up). Per-primitive arrays:

    * boxes: ``box_center [boxes, 3]``, ``box_rot [boxes, 3, 3]`` (world-from-box),
      ``box_half [boxes, 3]``.
    * spheres: ``sphere_center [spheres, 3]``, ``sphere_radius [spheres]``.
    * quads: two-sided rectangles ``quad_center [quads, 3]`` with unit in-plane axes
      ``quad_u`` (texture right), ``quad_v`` (texture up) ``[quads, 3]`` and half sizes
      ``quad_half [quads, 2]``: the room's six faces and the posters.
    * materials, one per primitive in the order boxes, spheres, quads
      (``boxes+spheres+quads`` of them): ``texture`` (index into
      :func:`~llrmpp_jax.data.textures.texture_bank`), ``tint [.., 3]`` and ``texels_per_m``:
      the texture tiles at that density, or, for a quad with 0, is stretched once over the
      rectangle (posters).
    """

    box_center: Float[np.ndarray, "boxes 3"]
    box_rot: Float[np.ndarray, "boxes 3 3"]
    box_half: Float[np.ndarray, "boxes 3"]
    sphere_center: Float[np.ndarray, "spheres 3"]
    sphere_radius: Float[np.ndarray, " spheres"]
    quad_center: Float[np.ndarray, "quads 3"]
    quad_u: Float[np.ndarray, "quads 3"]
    quad_v: Float[np.ndarray, "quads 3"]
    quad_half: Float[np.ndarray, "quads 2"]
    texture: Int[np.ndarray, " boxes+spheres+quads"]
    tint: Float[np.ndarray, "boxes+spheres+quads 3"]
    texels_per_m: Float[np.ndarray, " boxes+spheres+quads"]
    light_dir: Float[np.ndarray, " 3"] = field(
        default_factory=lambda: np.array([0.35, 0.25, 0.9]) / np.linalg.norm([0.35, 0.25, 0.9])
    )

    @property
    def num_primitives(self) -> int:
        return self.box_center.shape[0] + self.sphere_center.shape[0] + self.quad_center.shape[0]


@dataclass(frozen=True)
class Rendered:
    """Ray-cast views: ``rgb [frames, H, W, 3]`` float32 in [0, 1], ``depth [frames, H, W]`` float32
    z-depth (0 where a ray hits nothing), ``primitive [frames, H, W]`` int32 index of the hit
    primitive in boxes-spheres-quads order (-1 = none), ``normal [frames, H, W, 3]`` float32
    world-space unit surface normal turned towards the camera (0 where nothing is hit)."""

    rgb: Float[np.ndarray, "frames H W 3"]
    depth: Float[np.ndarray, "frames H W"]
    primitive: Int[np.ndarray, "frames H W"]
    normal: Float[np.ndarray, "frames H W 3"]


# Ray batches are stored transposed, ``[3, R]`` (one contiguous row per axis), and cast in
# chunks of _CHUNK rays: every operation below is then an elementwise pass over a little
# contiguous memory, with no small-matrix BLAS calls (slow, and they oversubscribe threads
# for R x 3 inputs).


def _dot(a: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise dot of ``a [3, R]`` with a fixed vector ``v [3]`` -> ``[R]``."""
    return a[0] * v[0] + a[1] * v[1] + a[2] * v[2]


def _hit_boxes(lay: Layout, o: np.ndarray, d: np.ndarray) -> Iterator[np.ndarray]:
    for c, rot, half in zip(lay.box_center, lay.box_rot, lay.box_half):
        oc = o - c[:, None]
        tmin = np.full(o.shape[1], -np.inf)
        tmax = np.full(o.shape[1], np.inf)
        for k in range(3):  # slab test along each box axis, in box coordinates R^T (o - c)
            ol, dl = _dot(oc, rot[:, k]), _dot(d, rot[:, k])
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-half[k] - ol) / dl
                t2 = (half[k] - ol) / dl
            # fmin/fmax skip the NaN of a ray lying exactly in a slab plane.
            tmin = np.fmax(tmin, np.fmin(t1, t2))
            tmax = np.fmin(tmax, np.fmax(t1, t2))
        t = np.where(tmin > _EPS, tmin, tmax)
        yield np.where((tmax >= tmin) & (t > _EPS), t, np.inf)


def _hit_spheres(lay: Layout, o: np.ndarray, d: np.ndarray) -> Iterator[np.ndarray]:
    for c, r in zip(lay.sphere_center, lay.sphere_radius):
        oc = o - c[:, None]
        b = (oc * d).sum(axis=0)
        disc = b * b - ((oc * oc).sum(axis=0) - r * r)
        root = np.sqrt(np.maximum(disc, 0.0))
        t = np.where(-b - root > _EPS, -b - root, -b + root)
        yield np.where((disc >= 0) & (t > _EPS), t, np.inf)


def _hit_quads(lay: Layout, o: np.ndarray, d: np.ndarray) -> Iterator[np.ndarray]:
    for c, u, v, half in zip(lay.quad_center, lay.quad_u, lay.quad_v, lay.quad_half):
        n = np.cross(u, v)
        oc = o - c[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -_dot(oc, n) / _dot(d, n)
        p = oc + t[None, :] * d
        inside = (np.abs(_dot(p, u)) <= half[0]) & (np.abs(_dot(p, v)) <= half[1])
        yield np.where(inside & (t > _EPS) & np.isfinite(t), t, np.inf)


def _nearest_hit(lay: Layout, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the ray ``[R]`` (inf = miss) and index ``[R]`` of the nearest primitive
    (boxes, spheres, quads order; -1 = miss), as a running minimum over primitives."""
    best = np.full(o.shape[1], np.inf)
    prim = np.full(o.shape[1], -1, dtype=np.int64)
    hits = itertools.chain(_hit_boxes(lay, o, d), _hit_spheres(lay, o, d), _hit_quads(lay, o, d))
    for k, t in enumerate(hits):
        closer = t < best
        best = np.where(closer, t, best)
        prim = np.where(closer, k, prim)
    return best, prim


def _surface(lay: Layout, k: int, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normal (unoriented) ``[3, R]``, texture coords u, v ``[R]`` (in texture repeats) and
    texels per metre of the base level along the surface ``[R]`` at hit points ``p [3, R]``
    on primitive k."""
    nb, ns = lay.box_center.shape[0], lay.sphere_center.shape[0]
    tex_h, tex_w = (float(v) for v in texture_bank()[lay.texture[k]].levels[0].shape[:2])
    count = p.shape[1]
    if k < nb:
        rot, half = lay.box_rot[k], lay.box_half[k]
        rel = p - lay.box_center[k][:, None]
        pl = np.stack([_dot(rel, rot[:, a]) for a in range(3)])
        axis = np.argmax(np.abs(pl) / half[:, None], axis=0)
        sign = np.sign(pl[axis, np.arange(count)])
        normal = rot[:, axis] * sign[None, :]
        # In-face coordinates: horizontal along the face, vertical = -z so images stand upright.
        a = np.where(axis == 0, pl[1], pl[0])
        b = np.where(axis == 2, pl[1], -pl[2])
        density = lay.texels_per_m[k]
        return normal, a * (density / tex_w), b * (density / tex_h), np.full(count, density)
    if k < nb + ns:
        j = k - nb
        normal = (p - lay.sphere_center[j][:, None]) / lay.sphere_radius[j]
        circumference = 2 * np.pi * lay.sphere_radius[j]
        repeats = max(1.0, np.round(circumference * lay.texels_per_m[k] / tex_w))
        u = (np.arctan2(normal[1], normal[0]) / (2 * np.pi)) * repeats
        v = np.arccos(np.clip(normal[2], -1.0, 1.0)) / np.pi * repeats / 2
        return normal, u, v, np.full(count, repeats * tex_w / circumference)
    j = k - nb - ns
    u_ax, v_ax, half = lay.quad_u[j], lay.quad_v[j], lay.quad_half[j]
    rel = p - lay.quad_center[j][:, None]
    a, b = _dot(rel, u_ax), _dot(rel, v_ax)
    normal = np.broadcast_to(np.cross(u_ax, v_ax)[:, None], p.shape)
    density = lay.texels_per_m[k]
    if density > 0:  # tiled
        return normal, a * (density / tex_w), -b * (density / tex_h), np.full(count, density)
    return normal, 0.5 + 0.5 * a / half[0], 0.5 - 0.5 * b / half[1], np.full(count, tex_w / (2 * half[0]))


_CHUNK = 1 << 14  # rays per pass: keeps every temporary (~128 KiB) in cache


def render_views(
    lay: Layout,
    c2w: Float[np.ndarray, "frames 4 4"],
    intrinsics: Float[np.ndarray, "frames 4"],
    height: int,
    width: int,
) -> Rendered:
    """Ray-cast one view per camera of ``lay`` at ``height x width`` (pixel centres, OpenCV cameras)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    n, pixels = c2w.shape[0], height * width
    rgb = np.zeros((n * pixels, 3), dtype=np.float32)
    normals = np.zeros((n * pixels, 3), dtype=np.float32)
    depth = np.zeros(n * pixels, dtype=np.float32)
    prims = np.full(n * pixels, -1, dtype=np.int32)
    bank = texture_bank()
    for view in range(n):
        origins, dirs = pixel_rays(c2w[view], intrinsics[view], height, width)
        o_all = np.ascontiguousarray(origins.reshape(-1, 3).T)
        d_all = np.ascontiguousarray(dirs.reshape(-1, 3).T)
        fwd, focal = c2w[view, :3, 2], intrinsics[view, 0]
        for start in range(0, pixels, _CHUNK):
            o, d = o_all[:, start : start + _CHUNK], d_all[:, start : start + _CHUNK]
            out = slice(view * pixels + start, view * pixels + start + o.shape[1])
            t, prim = _nearest_hit(lay, o, d)
            zdot = _dot(d, fwd)
            hit = prim >= 0
            prims[out] = prim
            depth[out] = np.where(hit, t * zdot, 0.0)
            chunk_rgb = np.zeros((o.shape[1], 3), dtype=np.float32)
            chunk_normal = np.zeros((o.shape[1], 3), dtype=np.float32)
            for k in np.unique(prim[hit]):
                sel = np.flatnonzero(prim == k)
                ds = d[:, sel]
                p = o[:, sel] + t[sel][None, :] * ds
                normal, u, v, texels_per_m = _surface(lay, int(k), p)
                # Mip level: texels under one pixel ~ (metres per pixel) * texels per metre, with
                # a mild allowance for oblique viewing (geometric mean of the two footprint axes).
                ndotd = (normal * ds).sum(axis=0)
                metres_per_px = t[sel] * zdot[sel] / focal / np.sqrt(np.maximum(np.abs(ndotd), 0.1))
                lod = np.log2(np.maximum(metres_per_px * texels_per_m, 1e-6))
                color = sample_texture(bank[lay.texture[k]], u, v, lod) * lay.tint[k][None, :].astype(np.float32)
                facing = normal * -np.sign(ndotd)[None, :]  # normal turned towards the viewer
                shade = 0.55 + 0.45 * _dot(facing, lay.light_dir)
                chunk_rgb[sel] = np.clip(color * shade[:, None].astype(np.float32), 0.0, 1.0)
                chunk_normal[sel] = facing.T
            rgb[out] = chunk_rgb
            normals[out] = chunk_normal
    return Rendered(
        rgb=rgb.reshape(n, height, width, 3),
        depth=depth.reshape(n, height, width),
        primitive=prims.reshape(n, height, width),
        normal=normals.reshape(n, height, width, 3),
    )


@dataclass(frozen=True)
class ProceduralConfig:
    """What a seed may draw. ``num_*`` are inclusive ranges; ``path_kinds`` a subset of
    ``("orbit", "walk", "sweep")``; ``fov_deg`` the horizontal field-of-view range."""

    height: int = 128
    width: int = 128
    num_frames: int = 32
    path_kinds: tuple[PathKind, ...] = PATH_KINDS  # pyright: ignore[reportAssignmentType] -- PATH_KINDS holds PathKind values
    fov_deg: tuple[float, float] = (50.0, 75.0)
    num_boxes: tuple[int, int] = (2, 6)
    num_spheres: tuple[int, int] = (1, 4)
    num_posters: tuple[int, int] = (2, 6)

    def __post_init__(self) -> None:
        if self.height <= 0 or self.width <= 0 or self.num_frames <= 0:
            raise ValueError(f"ProceduralConfig: height, width, num_frames must be positive, got {self}")
        bad = set(self.path_kinds) - set(PATH_KINDS)
        if bad or not self.path_kinds:
            raise ValueError(
                f"ProceduralConfig: path_kinds must be a non-empty subset of {PATH_KINDS}, got {self.path_kinds}"
            )


def _tint(rng: np.random.Generator, grey: bool) -> np.ndarray:
    if grey:  # colour a grey texture with a random saturated-but-light hue
        return (0.35 + 0.65 * rng.random(3)).astype(np.float64)
    return 0.85 + 0.15 * rng.random(3)


def _yaw_rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def procedural_layout(
    seed: int, cfg: ProceduralConfig = ProceduralConfig()
) -> tuple[Layout, np.ndarray, np.ndarray, str]:
    """Scene layout, cameras and path kind for ``seed``: ``(layout, c2w [frames, 4, 4],
    intrinsics [frames, 4], kind)``. Deterministic: the same seed and config give the same scene.
    Objects never contain a camera (0.35 m clearance)."""
    rng = np.random.default_rng([seed, 0x5CE4E])
    bank = texture_bank()
    n_tex = len(bank)
    poster_ids = texture_ids(POSTER_TEXTURES)
    tiled_ids = np.array([i for i in range(n_tex) if bank[i].name not in ("text", "page")])
    hx, hy, hz = rng.uniform(2.5, 5.0), rng.uniform(2.5, 5.0), rng.uniform(1.3, 1.8)
    kind = str(rng.choice(list(cfg.path_kinds)))

    boxes: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    spheres: list[tuple[np.ndarray, float]] = []
    if kind == "orbit":
        size = rng.uniform(0.3, 0.6)
        min_r = size * 1.8 + 0.6
        slack_x, slack_y = (max(0.0, h - 0.6 - min_r) for h in (hx, hy))
        centre = np.array([rng.uniform(-slack_x, slack_x), rng.uniform(-slack_y, slack_y), 0.0])
        if rng.random() < 0.5:
            boxes.append(
                (
                    centre + [0, 0, size],
                    _yaw_rot(rng.uniform(0, np.pi)),
                    np.array([size, size * rng.uniform(0.6, 1.2), size]),
                )
            )
            top = 2 * size
        else:
            spheres.append((centre + [0, 0, size], size))
            top = 2 * size
        if rng.random() < 0.5:  # something on top, so the object has structure
            r = size * 0.5
            spheres.append((centre + [0, 0, top + r], r))
        room_left = min(hx - abs(centre[0]), hy - abs(centre[1])) - 0.5
        c2w = orbit_path(rng, cfg.num_frames, centre + [0, 0, size], min_r, max(min_r + 0.1, room_left))
    elif kind == "walk":
        c2w = walk_path(rng, cfg.num_frames, hx, hy)
    else:
        c2w = sweep_path(rng, cfg.num_frames, hx, hy)
    eyes = c2w[:, :3, 3]

    def clear(center: np.ndarray, radius: float) -> bool:
        return bool((np.linalg.norm(eyes - center[None, :], axis=1) > radius + 0.35).all())

    for _ in range(int(rng.integers(cfg.num_boxes[0], cfg.num_boxes[1] + 1))):
        half = rng.uniform([0.15, 0.15, 0.15], [0.7, 0.7, 0.8])
        c = np.array([rng.uniform(-hx + half[0], hx - half[0]), rng.uniform(-hy + half[1], hy - half[1]), half[2]])
        if rng.random() < 0.3:
            c[2] += rng.uniform(0.3, 1.2)  # floating / shelved
        if clear(c, float(np.linalg.norm(half))):
            boxes.append((c, _yaw_rot(rng.uniform(0, np.pi)), half))
    for _ in range(int(rng.integers(cfg.num_spheres[0], cfg.num_spheres[1] + 1))):
        r = rng.uniform(0.15, 0.5)
        c = np.array(
            [
                rng.uniform(-hx + r, hx - r),
                rng.uniform(-hy + r, hy - r),
                r + (rng.uniform(0, 1.2) if rng.random() < 0.4 else 0),
            ]
        )
        if clear(c, r):
            spheres.append((c, r))
    # Room faces, 1 mm oversized so that rays into an edge or corner cannot slip between faces.
    ex, ey, ez, grow = np.eye(3)[0], np.eye(3)[1], np.eye(3)[2], 1e-3
    quads = [  # (centre, u, v, half sizes, texture or -1 for a tiled texture drawn below)
        (np.zeros(3), ex, ey, np.array([hx, hy]) + grow, -1),
        (2 * hz * ez, ex, -ey, np.array([hx, hy]) + grow, -1),
        (hx * ex + hz * ez, -ey, ez, np.array([hy, hz]) + grow, -1),
        (-hx * ex + hz * ez, ey, ez, np.array([hy, hz]) + grow, -1),
        (hy * ey + hz * ez, ex, ez, np.array([hx, hz]) + grow, -1),
        (-hy * ey + hz * ez, -ex, ez, np.array([hx, hz]) + grow, -1),
    ]
    for _ in range(int(rng.integers(cfg.num_posters[0], cfg.num_posters[1] + 1))):
        wall = int(rng.integers(4))
        tex = int(rng.choice(poster_ids))
        th, tw = bank[tex].levels[0].shape[:2]
        half_w = rng.uniform(0.3, 1.1)
        half_h = min(half_w * th / tw, hz * 0.8)
        half_w = half_h * tw / th
        along = (hy if wall < 2 else hx) - half_w - 0.05
        if along <= 0:
            continue
        s = rng.uniform(-along, along)
        height = rng.uniform(half_h + 0.2, max(half_h + 0.2, 2 * hz - half_h - 0.2))
        sign = 1.0 if wall % 2 == 0 else -1.0
        # u is the viewer's right when facing the wall from inside the room (no mirrored text).
        if wall < 2:  # on the wall x = sign * hx
            c, u = np.array([sign * (hx - 0.01), s, height]), np.array([0.0, -sign, 0.0])
        else:  # on the wall y = sign * hy
            c, u = np.array([s, sign * (hy - 0.01), height]), np.array([sign, 0.0, 0.0])
        quads.append((c, u, ez, np.array([half_w, half_h]), tex))

    mats_tex, mats_tint, mats_density = [], [], []
    for tex in [-1] * (len(boxes) + len(spheres)) + [q[4] for q in quads]:
        if tex < 0:  # tiled: one tile spans 0.6-2.5 m
            tex = int(rng.choice(tiled_ids))
            density = bank[tex].levels[0].shape[1] / rng.uniform(0.6, 2.5)
        else:
            density = 0.0
        mats_tex.append(tex)
        mats_tint.append(_tint(rng, bank[tex].grey) if bank[tex].grey or density > 0 else np.ones(3))
        mats_density.append(density)
    lay = Layout(
        box_center=np.array([b[0] for b in boxes]).reshape(-1, 3),
        box_rot=np.array([b[1] for b in boxes]).reshape(-1, 3, 3),
        box_half=np.array([b[2] for b in boxes]).reshape(-1, 3),
        sphere_center=np.array([s[0] for s in spheres]).reshape(-1, 3),
        sphere_radius=np.array([s[1] for s in spheres], dtype=np.float64).reshape(-1),
        quad_center=np.array([q[0] for q in quads]).reshape(-1, 3),
        quad_u=np.array([q[1] for q in quads]).reshape(-1, 3),
        quad_v=np.array([q[2] for q in quads]).reshape(-1, 3),
        quad_half=np.array([q[3] for q in quads]).reshape(-1, 2),
        texture=np.array(mats_tex, dtype=np.int64),
        tint=np.array(mats_tint, dtype=np.float64).reshape(-1, 3),
        texels_per_m=np.array(mats_density, dtype=np.float64),
    )
    intrinsics = pinhole_intrinsics(rng, cfg.num_frames, cfg.height, cfg.width, cfg.fov_deg)
    return lay, c2w, intrinsics, kind


def procedural_scene(
    seed: int,
    cfg: ProceduralConfig = ProceduralConfig(),
    cameras: tuple[Float[np.ndarray, "frames 4 4"], Float[np.ndarray, "frames 4"]] | None = None,
) -> Scene:
    """A lazily rendered :class:`Scene` (RGB + exact depth) for ``seed``; each frame is
    ray-cast on first access and kept for the scene's lifetime. ``cameras`` (``c2w``,
    ``intrinsics``) replaces the drawn camera path: the same layout seen from other views."""
    lay, c2w, intrinsics, kind = procedural_layout(seed, cfg)
    if cameras is not None:
        c2w, intrinsics = (np.asarray(a, dtype=np.float64) for a in cameras)

    @functools.cache
    def frame(i: int) -> Rendered:
        return render_views(lay, c2w[i : i + 1], intrinsics[i : i + 1], cfg.height, cfg.width)

    n = len(c2w)
    return Scene(
        name=f"procedural-{kind}-{seed}",
        c2w=c2w,
        intrinsics=intrinsics,
        hw=np.tile(np.array([[cfg.height, cfg.width]], dtype=np.int64), (n, 1)),
        frame_names=tuple(f"procedural-{seed}/{i}" for i in range(n)),
        image_fn=lambda i: frame(i).rgb[0],
        depth_fn=lambda i: frame(i).depth[0],
    )
