"""Plain NumPy float64 oracle of gsplat's classic rasterisation.

The oracle follows gsplat's PyTorch reference (``_fully_fused_projection``,
``_isect_tiles``, the CUDA blend rules) literally: full covariances, per-pixel loop over
depth-sorted Gaussians. The splatter's tests import it; its own tests are
``tests/splat/test_oracle.py``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

TILE = 16  # gsplat's tile: which Gaussians a pixel sees
BLOCK = 8  # the splatter's compositor block (SplatConfig.composite_tile)


def oracle_rotmat(quats: np.ndarray) -> np.ndarray:
    """[N, 3, 3] from (w, x, y, z) quaternions, normalised (zero -> identity)."""
    q = quats / np.maximum(np.linalg.norm(quats, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y**2 + z**2), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x**2 + z**2), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x**2 + y**2)], -1),
        ],
        axis=-2,
    )


def oracle_project(means, quats, scales, c2w, intr, height, width, eps2d=0.3, near=0.01, far=1e6):
    """gsplat ``_fully_fused_projection`` (pinhole, v1.4 3-sigma radius), float64."""
    means, quats, scales, c2w, intr = (np.asarray(a, np.float64) for a in (means, quats, scales, c2w, intr))
    view = np.linalg.inv(c2w)
    rot_w, t_w = view[:3, :3], view[:3, 3]
    rot = oracle_rotmat(quats)
    cov = rot @ (scales[:, :, None] ** 2 * np.swapaxes(rot, 1, 2))
    mc = means @ rot_w.T + t_w
    cov_c = rot_w @ cov @ rot_w.T
    fx, fy, cx, cy = intr
    tx, ty, tz = mc.T
    with np.errstate(divide="ignore", invalid="ignore"):
        tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
        txc = tz * np.clip(tx / tz, -(cx / fx + 0.3 * tan_fovx), (width - cx) / fx + 0.3 * tan_fovx)
        tyc = tz * np.clip(ty / tz, -(cy / fy + 0.3 * tan_fovy), (height - cy) / fy + 0.3 * tan_fovy)
        jac = np.zeros((len(means), 2, 3))
        jac[:, 0, 0] = fx / tz
        jac[:, 0, 2] = -fx * txc / tz**2
        jac[:, 1, 1] = fy / tz
        jac[:, 1, 2] = -fy * tyc / tz**2
        cov2d = jac @ cov_c @ np.swapaxes(jac, 1, 2) + eps2d * np.eye(2)
        det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
        conics = np.stack([cov2d[:, 1, 1] / det, -cov2d[:, 0, 1] / det, cov2d[:, 0, 0] / det], -1)
        b = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1])
        radius = np.ceil(3.0 * np.sqrt(b + np.sqrt(np.maximum(b * b - det, 0.01))))
        means2d = np.stack([fx * tx / tz + cx, fy * ty / tz + cy], -1)
        visible = (det > 0) & (tz > near) & (tz < far)
        visible &= (means2d[:, 0] + radius > 0) & (means2d[:, 0] - radius < width)
        visible &= (means2d[:, 1] + radius > 0) & (means2d[:, 1] - radius < height)
    return dict(
        means2d=means2d, conics=conics, cov2d=cov2d, depths=tz, radii=np.where(visible, radius, 0.0), visible=visible
    )


def oracle_tile_boxes(proj, height, width, opacities=None, block=TILE):
    """gsplat ``_isect_tiles`` box per Gaussian, in blocks of ``block`` pixels (``TILE``:
    gsplat's own tiles): half-open [x0, x1) x [y0, y1).

    The box covers the 16x16 tiles of the 3-sigma square. With ``opacities``, it is cut on
    each axis to where ``o exp(-sigma)`` can reach 1/255 (gsplat's optional
    opacity-tightened boxes, PR #597; 0.01 of slack on ``sigma``), the half-width
    ``sqrt(2 (ln(255 o) + 0.01) cov2d_ii)``; a Gaussian that cannot reach it has no box."""
    bw, bh = -(-width // block), -(-height // block)
    r = proj["radii"]
    reach_x = reach_y = np.full(len(r), np.inf)
    drawn = proj["visible"]
    if opacities is not None:
        level = np.log(np.maximum(np.asarray(opacities, np.float64), 1e-30) * 255.0) + 0.01
        with np.errstate(invalid="ignore"):
            reach_x = np.sqrt(2.0 * np.maximum(level, 0.0) * proj["cov2d"][:, 0, 0])
            reach_y = np.sqrt(2.0 * np.maximum(level, 0.0) * proj["cov2d"][:, 1, 1])
        drawn = drawn & (level > 0)
    boxes = []
    for m, reach, n in ((proj["means2d"][:, 0], reach_x, bw), (proj["means2d"][:, 1], reach_y, bh)):
        lo = np.maximum(np.floor((m - r) / TILE) * TILE, m - reach)
        hi = np.minimum(np.ceil((m + r) / TILE) * TILE, m + reach)
        b0 = np.clip(np.floor(lo / block), 0, n).astype(int)
        boxes += [b0, np.maximum(np.clip(np.ceil(hi / block), 0, n).astype(int), b0)]
    x0, x1, y0, y1 = boxes
    return x0, np.where(drawn, x1, x0), y0, np.where(drawn, y1, y0)


def oracle_block_reached(proj, opacities, g: int, bx: int, by: int, height: int, width: int, block=BLOCK) -> bool:
    """Brute force: does Gaussian ``g`` reach ``alpha >= 1/255`` at any pixel centre of block
    ``(bx, by)`` inside the canvas (float64, the full 2D covariance)."""
    xs = np.arange(bx * block, min((bx + 1) * block, width)) + 0.5
    ys = np.arange(by * block, min((by + 1) * block, height)) + 0.5
    d = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2) - proj["means2d"][g]
    sigma = 0.5 * np.einsum("pi,ij,pj->p", d, np.linalg.inv(proj["cov2d"][g]), d)
    return bool(np.any(float(opacities[g]) * np.exp(-sigma) >= 1.0 / 255.0))


def oracle_tile_lists(proj, height, width, capacity=None, opacities=None, block=TILE):
    """Per block of ``block`` pixels (row-major), the depth-sorted Gaussian ids; with
    ``capacity``, the entries of the farthest Gaussians beyond that many are dropped
    (emission in depth order, each Gaussian's blocks row-major in its box; boxes trimmed by
    ``opacities`` when given, see :func:`oracle_tile_boxes`). Returns (lists, number of
    entries needed)."""
    bw, bh = -(-width // block), -(-height // block)
    x0, x1, y0, y1 = oracle_tile_boxes(proj, height, width, opacities, block)
    vis = np.flatnonzero(proj["visible"])
    order = vis[np.lexsort((vis, proj["depths"][vis]))]  # depth, then index
    lists = [[] for _ in range(bw * bh)]
    used = 0
    for g in order:
        for ty in range(y0[g], y1[g]):
            for tx in range(x0[g], x1[g]):
                if capacity is None or used < capacity:
                    lists[ty * bw + tx].append(int(g))
                used += 1
    return lists, used


def oracle_render(
    means, quats, scales, opacities, features, c2w, intr, height, width, capacity=None, with_margin=False
):
    """Brute force: every pixel against every Gaussian of its tile's list, front to back.

    The lists are gsplat v1.4's (3-sigma boxes, 16x16 tiles) unless ``capacity`` is given:
    the splatter keeps lists per 8x8 block and trims each box to where the Gaussian can be
    drawn, which changes no pixel (the tests of the full lists check that) but does change
    which entries an overflowing buffer keeps, so with a capacity the oracle uses the
    splatter's blocks and trimmed boxes.

    Returns (features [H, W, F], transmittance [H, W], depth [H, W]) in float64, and with
    ``with_margin`` also ``margin [H, W]``: the smallest relative distance of any alpha to
    1/255 or of any would-be transmittance to 1e-4 met at that pixel. Where it is tiny,
    rounding (float32 vs float64) may legitimately flip gsplat's discrete decisions.
    """
    proj = oracle_project(means, quats, scales, c2w, intr, height, width)
    opacities = np.asarray(opacities, np.float64)
    block = TILE if capacity is None else BLOCK
    lists, _ = oracle_tile_lists(proj, height, width, capacity, None if capacity is None else opacities, block)
    feats = np.concatenate([np.asarray(features, np.float64), proj["depths"][:, None]], -1)
    tw = -(-width // block)
    out = np.zeros((height, width, feats.shape[1]))
    trans_out = np.ones((height, width))
    margin_out = np.full((height, width), np.inf)
    for t, gaussians in enumerate(lists):
        # The pixels of tile t, all handled at once; the loop over its list is sequential.
        ys, xs = np.meshgrid(
            np.arange((t // tw) * block, min((t // tw + 1) * block, height)),
            np.arange((t % tw) * block, min((t % tw + 1) * block, width)),
            indexing="ij",
        )
        ys, xs = ys.ravel(), xs.ravel()
        trans = np.ones(len(ys))
        margin = np.full(len(ys), np.inf)
        done = np.zeros(len(ys), bool)
        acc = np.zeros((len(ys), feats.shape[1]))
        for g in gaussians:
            dx = proj["means2d"][g, 0] - (xs + 0.5)
            dy = proj["means2d"][g, 1] - (ys + 0.5)
            a, b, c = proj["conics"][g]
            sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
            alpha = np.minimum(0.999, opacities[g] * np.exp(-sigma))
            margin = np.where(done, margin, np.minimum(margin, np.abs(alpha * 255.0 - 1.0)))
            use = ~done & (sigma >= 0) & (alpha >= 1.0 / 255.0)
            nxt = trans * (1.0 - alpha)
            margin = np.where(use, np.minimum(margin, np.abs(nxt * 1e4 - 1.0)), margin)
            stop = use & (nxt <= 1e-4)  # this Gaussian is not used, nor any later one
            done |= stop
            use &= ~stop
            acc[use] += (alpha * trans)[use, None] * feats[g][None, :]
            trans = np.where(use, nxt, trans)
        out[ys, xs] = acc
        trans_out[ys, xs] = trans
        margin_out[ys, xs] = margin
    f = feats.shape[1] - 1
    if with_margin:
        return out[..., :f], trans_out, out[..., f], margin_out
    return out[..., :f], trans_out, out[..., f]


def assert_render_close(got, expected, atol):
    """``got`` and ``expected``: (features, transmittance, depth) triples or SplatOutputs."""
    for g, e in zip(got[:3], expected[:3]):
        np.testing.assert_allclose(np.asarray(g), np.asarray(e), rtol=0, atol=atol)


def random_scene(rng: np.random.Generator, n: int, f: int, height: int, width: int, conditioned: bool = False):
    """A hard random scene: in front / behind / beside the camera, tiny and huge scales,
    opacities at and near 0 and 1, centres on tile and image borders, unnormalised quats,
    a random rigid camera.

    ``conditioned``: for float32 comparisons, leave out what float32 itself cannot resolve
    to 1e-5: the camera is the identity (no rigid-transform rounding of world points) and
    huge scales apply to all three axes (no 1e-6 x 2.7 needles, whose projection seen
    nearly end-on is a difference of large numbers)."""
    fx, fy = 0.8 * width * rng.uniform(0.8, 1.2), 0.8 * width * rng.uniform(0.8, 1.2)
    intr = np.array([fx, fy, width * rng.uniform(0.4, 0.6), height * rng.uniform(0.4, 0.6)])
    # Depths: in front (>= 0.25: closer, float32 rounding of the camera transform alone moves
    # a projected centre by ~1e-4 px, more than the 1e-5 comparisons allow), behind the
    # camera, and between the camera and the near plane.
    z = rng.uniform(0.25, 8.0, n)
    where = rng.random(n)
    z[where < 0.15] = rng.uniform(-1.0, 0.0, int((where < 0.15).sum()))
    z[where > 0.95] = 0.005
    # Pick pixel targets, a quarter of them exactly on tile / image borders.
    u = rng.uniform(-0.2 * width, 1.2 * width, n)
    v = rng.uniform(-0.2 * height, 1.2 * height, n)
    k = n // 4
    u[:k] = TILE * rng.integers(0, width // TILE + 2, k) + rng.normal(0, 0.5, k)
    v[k : 2 * k] = rng.choice([0.0, float(height)], k) + rng.normal(0, 1.0, k)
    means_c = np.stack([(u - intr[2]) / fx * z, (v - intr[3]) / fy * z, z], -1)
    log_s = rng.uniform(-4.5, -1.0, (n, 3))
    log_s[rng.random(n) < 0.1] = -14.0  # near-degenerate: all axes ~1e-6
    if conditioned:
        log_s[rng.random(n) < 0.05] = 1.0  # very large
    else:
        log_s[rng.random((n, 3)) < 0.05] = 1.0  # very large along some axes
    scales = np.exp(log_s)
    quats = rng.normal(size=(n, 4)) * rng.uniform(0.2, 3.0, (n, 1))
    opac = rng.uniform(0.0, 1.0, n)
    special = rng.random(n)
    opac[special < 0.1] = 1.0
    opac[(special >= 0.1) & (special < 0.2)] = rng.uniform(0.99, 1.0, int(((special >= 0.1) & (special < 0.2)).sum()))
    opac[(special >= 0.2) & (special < 0.3)] = rng.uniform(0.0, 0.01, int(((special >= 0.2) & (special < 0.3)).sum()))
    feats = rng.normal(size=(n, f))
    c2w = np.eye(4)
    if not conditioned:  # express the Gaussians in the world frame of a random rigid camera
        c2w[:3, :3], c2w[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    means = means_c @ c2w[:3, :3].T + c2w[:3, 3]
    return means, quats, scales, opac, feats, c2w, intr
