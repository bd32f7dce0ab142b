"""PLY export: the standard 3DGS layout, exact round trips through plyfile, the world transform."""

import jax
import numpy as np
import plyfile
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import expit, logit

from llrmpp_jax import config as C
from llrmpp_jax.export_ply import export_ply, ply_fields, read_ply
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.model import partition_logits
from tests.oracles.sh import scipy_real_sh

N = 40
COLOUR = C.ModelConfig(head=C.GaussianHeadConfig(mode="color", sh_degree=3))
# The 3DGS save_ply list for SH degree 3, written out by hand.
STANDARD_DEG3 = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def random_gaussians(rng, n, f, batch=True) -> Gaussians:
    q = rng.normal(size=(n, 4))
    g = Gaussians(
        means=rng.normal(size=(n, 3)),
        quats=q / np.linalg.norm(q, axis=-1, keepdims=True),
        scales=np.exp(rng.uniform(-5, -1, (n, 3))),
        opacities=rng.uniform(0.01, 0.99, n),
        features=rng.normal(size=(n, f)),
    )
    return Gaussians(*(np.asarray(a, np.float32)[None] if batch else np.asarray(a, np.float32) for a in g))  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work


def random_similarity(rng) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    s = rng.uniform(0.3, 3.0)
    rot = Rotation.random(random_state=rng)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    t = rng.normal(size=3) * 5
    m = np.eye(4)
    m[:3, :3] = s * rot.as_matrix()
    m[:3, 3] = t
    return s, rot, t, m


def _read_vertex(path):
    data = plyfile.PlyData.read(path)
    return data["vertex"].data, list(data["vertex"].data.dtype.names)


def test_colour_ply_is_the_standard_layout_and_round_trips_exactly(tmp_path, rng):
    g = random_gaussians(rng, N, 48)
    m = random_similarity(rng)[3]
    path = str(tmp_path / "c.ply")
    assert export_ply(path, g, COLOUR, m) == N
    vertex, names = _read_vertex(path)
    assert names == STANDARD_DEG3
    assert all(vertex.dtype[k] == np.dtype("<f4") for k in names)
    for k, want in ply_fields(g, COLOUR, m).items():  # bit-exact
        np.testing.assert_array_equal(vertex[k], want, err_msg=k)
    header = open(path, "rb").read(200)
    assert header.startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_feature_ply_fields_round_trip_exactly(tmp_path, rng):
    cfg = C.tiny()
    g = random_gaussians(rng, N, cfg.head.feature_dim)
    kernel = rng.normal(size=(16, 2)).astype(np.float32)
    logits = partition_logits({"partition": {"kernel": kernel}}, cfg, g)
    np.testing.assert_allclose(np.asarray(logits[0]), g.features[0].astype(np.float64) @ kernel, rtol=1e-5, atol=1e-6)
    m = random_similarity(rng)[3]
    path = str(tmp_path / "f.ply")
    export_ply(path, g, cfg, m, partition_logits=logits)
    vertex, names = _read_vertex(path)
    want_names = (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_feat_{i}" for i in range(16)]
        + ["partition_0", "partition_1", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert names == want_names
    for k, want in ply_fields(g, cfg, m, logits).items():
        np.testing.assert_array_equal(vertex[k], want, err_msg=k)
    np.testing.assert_array_equal(np.stack([vertex[f"f_feat_{i}"] for i in range(16)], -1), g.features[0])
    back = read_ply(path)
    assert back.mode == "feature"
    np.testing.assert_array_equal(back.partition_logits, np.asarray(logits[0], np.float32))
    np.testing.assert_allclose(back.world_from_scene, m, rtol=1e-15)  # pyright: ignore[reportArgumentType, reportCallIssue] -- this PLY records world_from_scene


def test_world_transform_matches_scipy(tmp_path, rng):
    """Means, quaternions, scales and opacities against scipy; float32 tolerance 1e-5 relative."""
    g = random_gaussians(rng, N, 48, batch=False)
    s, rot, t, m = random_similarity(rng)
    path = str(tmp_path / "w.ply")
    export_ply(path, g, COLOUR, m)
    vertex, _ = _read_vertex(path)
    col = lambda *ks: np.stack([vertex[k].astype(np.float64) for k in ks], -1)  # noqa: E731
    g64 = Gaussians(*(a.astype(np.float64) for a in g))
    np.testing.assert_allclose(col("x", "y", "z"), s * rot.apply(g64.means) + t, rtol=1e-6, atol=1e-5)  # pyright: ignore[reportAttributeAccessIssue] -- rot is a scipy Rotation; its random() overloads miss random_state
    want_q = (rot * Rotation.from_quat(g64.quats, scalar_first=True)).as_quat(scalar_first=True)
    got_q = col("rot_0", "rot_1", "rot_2", "rot_3")
    sign = np.sign(np.sum(got_q * want_q, axis=-1, keepdims=True))  # q and -q are one rotation
    np.testing.assert_allclose(got_q, sign * want_q, atol=2e-7)
    np.testing.assert_allclose(col("scale_0", "scale_1", "scale_2"), np.log(s * g64.scales), atol=2e-6)
    np.testing.assert_allclose(col("opacity")[:, 0], logit(g64.opacities), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(col("nx", "ny", "nz"), 0.0)
    # DC is rotation-invariant, and the colour seen along the same physical ray is unchanged.
    np.testing.assert_allclose(col("f_dc_0", "f_dc_1", "f_dc_2"), g64.features[:, :3], rtol=1e-6, atol=1e-6)
    dirs = rng.normal(size=(N, 3))
    coeffs = g64.features.reshape(N, 16, 3)
    rest = col(*(f"f_rest_{i}" for i in range(45))).reshape(N, 3, 15).transpose(0, 2, 1)
    world = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None], rest], axis=1)
    want = np.einsum("nk,nkc->nc", scipy_real_sh(dirs, 3), coeffs)
    got = np.einsum("nk,nkc->nc", scipy_real_sh(rot.apply(dirs), 3), world)  # pyright: ignore[reportAttributeAccessIssue] -- rot is a scipy Rotation; its random() overloads miss random_state
    np.testing.assert_allclose(got, want, atol=2e-5 * np.abs(want).max())


def test_identity_transform_keeps_sh_layout_channel_major(tmp_path, rng):
    """With the identity: f_rest_{c*15 + k-1} is coefficient k of channel c (3DGS order)."""
    g = random_gaussians(rng, N, 48, batch=False)
    path = str(tmp_path / "i.ply")
    export_ply(path, g, COLOUR, np.eye(4))
    vertex, _ = _read_vertex(path)
    sh = g.features.reshape(N, 16, 3)
    for c in range(3):
        np.testing.assert_allclose(vertex[f"f_dc_{c}"], sh[:, 0, c], atol=1e-7)
        for k in range(1, 16):
            np.testing.assert_allclose(vertex[f"f_rest_{c * 15 + k - 1}"], sh[:, k, c], atol=1e-6)


def test_read_ply_decodes_to_world_gaussians(tmp_path, rng):
    g = random_gaussians(rng, N, 48)
    s, rot, t, m = random_similarity(rng)
    path = str(tmp_path / "r.ply")
    export_ply(path, g, COLOUR, m)
    back = read_ply(path)
    assert back.mode == "color" and back.partition_logits is None
    np.testing.assert_allclose(
        back.gaussians.means,
        s * rot.apply(g.means[0].astype(np.float64)) + t,  # pyright: ignore[reportAttributeAccessIssue] -- rot is a scipy Rotation; its random() overloads miss random_state
        rtol=1e-6,
        atol=1e-5,
    )
    np.testing.assert_allclose(back.gaussians.scales, s * g.scales[0], rtol=2e-6)
    np.testing.assert_allclose(back.gaussians.opacities, g.opacities[0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(back.gaussians.features[:, :3], g.features[0, :, :3], atol=1e-6)
    # A standard 3DGS file (no llrmpp comments) reads too, as colour mode.
    data = plyfile.PlyData.read(path)
    plyfile.PlyData([data["vertex"]], byte_order="<").write(str(tmp_path / "plain.ply"))
    plain = read_ply(str(tmp_path / "plain.ply"))
    assert plain.mode == "color" and plain.world_from_scene is None
    np.testing.assert_array_equal(plain.gaussians.features, back.gaussians.features)


def test_expit_inverts_opacity_logit_clip(tmp_path, rng):
    """Opacities of exactly 0 and 1 (float32 sigmoid saturates) give finite logits."""
    g = random_gaussians(rng, 4, 48, batch=False)
    g = g._replace(opacities=np.array([0.0, 1.0, 0.5, 1e-3], np.float32))
    vertex = ply_fields(g, COLOUR, np.eye(4))
    assert np.all(np.isfinite(vertex["opacity"]))
    np.testing.assert_allclose(expit(vertex["opacity"].astype(np.float64)), [2**-24, 1 - 2**-24, 0.5, 1e-3], rtol=1e-6)


@pytest.mark.parametrize(
    "case, match",
    [
        ("reflection", "determinant"),
        ("shear", "uniform scale"),
        ("batch", "one scene"),
        ("no_logits", "partition_logits"),
        ("nan", "non-finite"),
    ],
)
def test_bad_input(rng, case, match):
    g = random_gaussians(rng, N, 48)
    cfg, m, logits = COLOUR, np.eye(4), None
    if case == "reflection":
        m = np.diag([1.0, 1.0, -1.0, 1.0])
    elif case == "shear":
        m[0, 1] = 0.3
    elif case == "batch":
        g = Gaussians(*(np.concatenate([a, a]) for a in g))  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    elif case == "no_logits":
        cfg = C.tiny()
        g = random_gaussians(rng, N, 16)
    else:
        g = g._replace(means=g.means.copy())
        g.means[0, 3, 1] = np.nan
    with pytest.raises(ValueError, match=match):
        ply_fields(jax.tree.map(np.asarray, g), cfg, m, logits)
