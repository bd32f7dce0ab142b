"""Viewer: the rendering function against the model and brute-force oracles, the scene
checks, and the live page in a real headless browser (Debian's chromium + chromedriver)."""

import math
import os
import shutil
import socket
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.transform import resize

from llrmpp_jax import config as C
from llrmpp_jax.data.image_io import read_image
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.geometry import project_points
from llrmpp_jax.model import init_params, render
from llrmpp_jax.splat.reference import render_features_reference
from llrmpp_jax.viewer.render import ViewKey, ViewRenderer, display_image, render_view, viewport_camera
from llrmpp_jax.viewer.scene import check_gaussians, gaussian_centres, procedural_view_scene, saved_view_scene
from llrmpp_jax.viewer.server import PortInUseError, RenderWorker, Viewer, ViewerSettings, ViewRequest, check_port
from tests.helpers.environment import ROOT


@pytest.fixture(scope="module")
def demo():
    """The demo's tiny model (random init) and procedural scene 3 reconstructed by it."""
    cfg = load_experiment("demo").model
    params = init_params(jax.random.key(7), cfg, 2, 32, 32)
    return params, cfg, procedural_view_scene(params, cfg, seed=3)


_render = jax.jit(render, static_argnums=(1, 5, 6))
_render_view = jax.jit(render_view, static_argnums=(1, 5, 6, 7, 8))


def _model_rgb(params, cfg, scene, c2w, intrinsics, height, width):
    """The model's own render of one camera, through the public API."""
    out = _render(
        params,
        cfg,
        scene.gaussians,
        jnp.asarray(c2w, jnp.float32)[None, None],
        jnp.asarray(intrinsics, jnp.float32)[None, None],
        height,
        width,
    )
    return np.asarray(out.images["rgb"][0, 0])


def test_viewport_camera_spans_the_field_of_view(rng):
    """Points on the viewport's frustum edges project onto the image edges (fov exact
    in both axes although the width is rounded to the size multiple)."""
    fov_y, aspect = rng.uniform(0.4, 1.6), rng.uniform(0.5, 2.5)
    h, w, k = viewport_camera(fov_y, aspect, 64, 8)
    assert (h, w) == (64, max(8, round(64 * aspect / 8) * 8))
    ty = math.tan(fov_y / 2)
    tx = aspect * ty
    edges = np.array([[tx, 0.0, 1.0], [-tx, 0.0, 1.0], [0.0, ty, 1.0], [0.0, -ty, 1.0]]) * rng.uniform(1, 9)
    uv, _ = project_points(edges, np.eye(4), k.astype(np.float64))
    np.testing.assert_allclose(uv, [[w, h / 2], [0, h / 2], [w / 2, h], [w / 2, 0]], atol=1e-4)
    with pytest.raises(ValueError, match="multiple of 8"):
        viewport_camera(fov_y, aspect, 60, 8)


def test_render_view_is_the_model_render(demo):
    """All S copies: exactly ``model.render``. One copy: the model with partitioning off,
    i.e. a config with S=1 and any partition kernel (here a fresh random one)."""
    params, cfg, scene = demo
    c2w, k = scene.input_c2w[1], np.array([40.0, 44.0, 24.0, 16.0], np.float32)
    got = _render_view(params, cfg, scene.gaussians, jnp.asarray(c2w), jnp.asarray(k), 32, 48, "rgb", None)
    np.testing.assert_allclose(got, _model_rgb(params, cfg, scene, c2w, k, 32, 48), atol=1e-6)

    cfg1 = replace(cfg, decoder=replace(cfg.decoder, partitions=1))
    kernel = jax.random.normal(jax.random.key(1), (cfg.head.feature_dim, 1), jnp.float32)
    params1 = {**params, "partition": {"kernel": kernel}}
    got1 = _render_view(params, cfg, scene.gaussians, jnp.asarray(c2w), jnp.asarray(k), 32, 48, "rgb", 1)
    np.testing.assert_allclose(got1, _model_rgb(params1, cfg1, scene, c2w, k, 32, 48), atol=1e-6)
    assert np.abs(got1 - got).max() > 1e-4  # the two settings really differ
    with pytest.raises(ValueError, match=r"partitions must be in \[1, 2\]"):
        render_view(params, cfg, scene.gaussians, jnp.asarray(c2w), jnp.asarray(k), 32, 48, partitions=3)


def test_depth_without_head_is_the_splatted_depth(demo):
    """No depth head: alpha-normalised splatted z, against the brute-force splatter in float64."""
    params, cfg, scene = demo
    assert "depth" not in cfg.outputs
    c2w, k = scene.input_c2w[2], np.array([30.0, 30.0, 16.0, 16.0], np.float32)
    got = np.asarray(
        _render_view(params, cfg, scene.gaussians, jnp.asarray(c2w), jnp.asarray(k), 32, 32, "depth", None)
    )
    g = jax.tree.map(lambda a: jnp.asarray(a[0], jnp.float64), scene.gaussians)
    _, trans, depth = render_features_reference(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.means[:, :1] * 0,
        jnp.asarray(c2w, jnp.float64),
        jnp.asarray(k, jnp.float64),
        32,
        32,
        cfg.splat,
    )
    alpha = 1.0 - np.asarray(trans)
    covered = alpha > 1e-3
    assert covered.mean() > 0.5
    np.testing.assert_allclose(got[..., 0][covered], np.asarray(depth)[covered] / alpha[covered], rtol=1e-4)


def test_display_image(rng):
    rgb = rng.uniform(-0.2, 1.2, (5, 7, 3)).astype(np.float32)
    np.testing.assert_array_equal(display_image(rgb, "rgb"), np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    depth = rng.uniform(0.5, 9.0, (20, 30, 1)).astype(np.float32)
    depth[0, :5] = 0.0  # empty pixels
    shown = display_image(depth, "depth")
    assert shown.dtype == np.uint8 and shown.shape == (20, 30, 3) and (shown[0, :5] == 0).all()
    d, s = depth[1:, :, 0].ravel(), shown[1:, :, 0].ravel().astype(np.int64)
    order = np.argsort(d)
    assert (np.diff(s[order]) <= 0).all()  # nearer is brighter
    assert s.max() == 255 and s.min() == 0  # stretched over the range


def test_renderer_compiles_once_per_key(demo):
    params, cfg, scene = demo
    renderer = ViewRenderer(params, cfg, scene.gaussians)
    h, w, k = viewport_camera(0.9, 1.5, 32, 8)
    key = ViewKey(h, w, "rgb", 2)
    first = renderer.render(key, scene.input_c2w[0], k)
    second = renderer.render(key, scene.input_c2w[3], k)
    assert first.compile_s > 0 and second.compile_s == 0 and renderer.is_compiled(key)
    np.testing.assert_allclose(second.image, _model_rgb(params, cfg, scene, scene.input_c2w[3], k, h, w), atol=1e-6)


def test_check_gaussians(demo, rng):
    _, cfg, scene = demo
    check_gaussians(cfg, scene.gaussians, "scene.gs")
    wide = replace(cfg, head=replace(cfg.head, feature_dim=32))
    with pytest.raises(ValueError, match=r"scene.gs: Gaussians carry 16 values .* expects F=32 features"):
        check_gaussians(wide, scene.gaussians, "scene.gs")
    colour = C.long_lrm()
    with pytest.raises(ValueError, match=r"expects 48 SH coefficients of degree 3 \(colour mode\)"):
        check_gaussians(colour, scene.gaussians, "scene.gs")
    two = jax.tree.map(lambda a: jnp.concatenate([a, a]), scene.gaussians)
    with pytest.raises(ValueError, match=r"'means' has shape \(2, 1024, 3\)"):
        check_gaussians(cfg, two, "scene.gs")


def test_gaussian_centres_colours(rng):
    n = 300
    sh = rng.normal(size=(1, n, 12)).astype(np.float32)  # degree 1
    g = Gaussians(rng.normal(size=(1, n, 3)), np.zeros((1, n, 4)), np.ones((1, n, 3)), np.ones((1, n)), sh)  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    colour = replace(C.long_lrm(), head=replace(C.long_lrm().head, sh_degree=1))
    pts, cols = gaussian_centres(colour, g, 1000, rng)
    np.testing.assert_array_equal(pts, g.means[0].astype(np.float32))
    want = np.round(np.clip(0.5 + 0.28209479177387814 * sh[0, :, :3], 0, 1) * 255)
    np.testing.assert_array_equal(cols, want.astype(np.uint8))
    feat = rng.normal(size=(1, n, 16)).astype(np.float32)
    pts, cols = gaussian_centres(C.tiny(), g._replace(features=feat), 100, rng)
    assert pts.shape == (100, 3) and cols.shape == (100, 3)
    assert np.isin(pts, g.means[0].astype(np.float32)).all()
    assert (cols.min(axis=0) == 0).all() and (cols.max(axis=0) == 255).all()


def test_worker_renders_the_latest_camera_then_full_height():
    """Requests that arrive during a render are dropped but the latest; a moving render is
    followed by the same camera at full height once no request came for ``still_seconds``."""
    import threading

    gate, done, rendered = threading.Event(), threading.Semaphore(0), []

    def render(req):
        gate.wait()
        rendered.append(req)
        done.release()

    reqs = [ViewRequest(np.eye(4) * (i + 1), 1.0, 1.5, moving=i > 0) for i in range(6)]
    worker = RenderWorker(render, still_seconds=0.05, name="test")
    worker.request(reqs[0])
    while not rendered and worker._pending is not None:  # the worker has taken request 0
        threading.Event().wait(0.01)
    for r in reqs[1:]:
        worker.request(r)
    gate.set()
    for _ in range(3):
        assert done.acquire(timeout=30)
    worker.close(wait=True)
    assert [(r.c2w[0, 0], r.moving) for r in rendered] == [(1.0, False), (6.0, True), (6.0, False)]


def test_port_in_use_names_it_and_a_free_one():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        with pytest.raises(
            PortInUseError, match=rf"port {taken} on 127.0.0.1 is already in use; try --port (\d+)"
        ) as e:
            check_port("127.0.0.1", taken)
        suggested = int(str(e.value).rsplit(" ", 1)[1])
        check_port("127.0.0.1", suggested)  # free indeed
    for bad in (-1, 65536, 99999):  # checked before the OS's bind() raises OverflowError
        with pytest.raises(ValueError, match=rf"^--port must be in 0\.\.65535, got {bad}$"):
            check_port("127.0.0.1", bad)


# -- the page in a real browser -------------------------------------------------------------

VIEWPORT = (960, 640)  # CSS px = screenshot px (device scale 1)
BAND = slice(280, 570)  # rows compared: below the notifications and the control panel, above the axes


@pytest.fixture
def browser():
    """Headless chromium through chromedriver (selenium). Missing browser: skip locally,
    fail in CI (``CI`` set), where ``.ci/run`` installs it."""
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not (chromium and driver):
        msg = "chromium and chromedriver are needed (apt-get install chromium chromium-driver)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--enable-unsafe-swiftshader",
        "--use-angle=swiftshader",
        f"--window-size={VIEWPORT[0]},{VIEWPORT[1] + 200}",
    ):
        opts.add_argument(arg)
    d = webdriver.Chrome(service=Service(driver), options=opts)
    d.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": VIEWPORT[0], "height": VIEWPORT[1], "deviceScaleFactor": 1, "mobile": False},
    )
    yield d
    d.quit()


def _grey_corr(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.mean(axis=-1).ravel(), b.mean(axis=-1).ravel()
    a, b = a - a.mean(), b - b.mean()
    return float(a @ b / np.sqrt((a @ a) * (b @ b)))


def _screen_vs_render(shot: np.ndarray, rgb: np.ndarray) -> float:
    """Correlation of the screenshot with a render stretched (bilinear, as the page's
    texture) over the whole page, which the 3D canvas fills, in the rows of ``BAND``."""
    stretched = resize(rgb, (*shot.shape[:2], 3), order=1, anti_aliasing=False)
    return _grey_corr(shot[BAND], stretched[BAND])  # pyright: ignore[reportArgumentType] -- NumPy arrays


def _wait_for_view(driver, path, rgb, others, deadline_s=30.0) -> tuple[np.ndarray, float]:
    """Screenshots until one correlates with ``rgb`` better than with any of ``others``
    (the page shows a frame shortly after the server sends it)."""
    t_end = time.monotonic() + deadline_s
    while True:
        driver.save_screenshot(str(path))
        shot = read_image(str(path))
        c = _screen_vs_render(shot, rgb)
        if c > 0.95 and all(c > _screen_vs_render(shot, o) + 0.2 for o in others) or time.monotonic() > t_end:
            return shot, c
        time.sleep(0.3)


def _wait_for_camera(viewer, c2w, timeout_s=60.0):
    """The first frame sent at camera ``c2w`` (the page may report other cameras first)."""
    count = 0
    while not np.allclose((frame := viewer.wait_for_frame(count, timeout=timeout_s)).c2w, c2w, atol=1e-4):
        count = viewer.frame_count
    return frame


@pytest.mark.slow
def test_viewer_in_browser(demo, browser, tmp_path):
    """Start the viewer, open it in chromium, compare the page with the model's own render
    of the browser's camera; move the camera from the server and compare again."""
    params, cfg, scene = demo
    renderer = ViewRenderer(params, cfg, scene.gaussians)
    settings = ViewerSettings(height=64, moving_height=64, show_points=False, show_cameras=False)
    viewer = Viewer(renderer, scene, host="127.0.0.1", port=0, settings=settings)
    try:
        browser.get(f"http://127.0.0.1:{viewer.port}/")
        first = _wait_for_camera(viewer, scene.input_c2w[0], timeout_s=120.0)  # opens at the first input
        w, h = VIEWPORT
        fov_y = 2.0 * math.atan(scene.input_hw[0] / (2.0 * scene.input_intrinsics[0, 1]))
        rh, rw = 64, round(64 * w / h / 8) * 8
        ty = math.tan(fov_y / 2.0)
        k = np.array([rw / (2.0 * ty * w / h), rh / (2.0 * ty), rw / 2.0, rh / 2.0])
        assert (first.key.height, first.key.width) == (rh, rw)
        own0 = _model_rgb(params, cfg, scene, scene.input_c2w[0], k, rh, rw)
        own2 = _model_rgb(params, cfg, scene, scene.input_c2w[2], k, rh, rw)
        assert _grey_corr(own0, own2) < 0.5  # the two views are distinguishable

        shot0, c0 = _wait_for_view(browser, tmp_path / "view0.png", own0, [own2])
        assert shot0[BAND].std() > 0.01  # not blank
        assert c0 > 0.95, f"page vs model render: correlation {c0:.3f}"

        viewer.set_camera(scene.input_c2w[2])
        frame = _wait_for_camera(viewer, scene.input_c2w[2])
        shot2, c2 = _wait_for_view(browser, tmp_path / "view2.png", own2, [own0])
        assert c2 > 0.95, f"page vs model render after the move: correlation {c2:.3f}"
        assert c2 > _screen_vs_render(shot2, own0) + 0.2
        assert _grey_corr(shot0[BAND], shot2[BAND]) < 0.6
        np.testing.assert_allclose(frame.image, own2, atol=1e-5)
    finally:
        viewer.stop()


def _rss_bytes() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmRSS:"))


def _other_interface_address() -> str | None:
    """An IPv4 address of this machine that is not loopback (None if it has none)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("10.255.255.255", 1))  # UDP: no packet is sent
            address = s.getsockname()[0]
        except OSError:
            return None
    return None if address.startswith("127.") else address


def test_default_host_serves_this_machine_only(demo):
    """``llrmpp view``'s default ``--host`` binds loopback: the page answers on 127.0.0.1 and
    the same port refuses connections on this machine's other interface."""
    from llrmpp_jax.cli import build_parser

    other = _other_interface_address()
    if other is None:
        pytest.skip("this machine has no interface besides loopback")
    host = build_parser().parse_args(["view", "--procedural", "0"]).host
    assert host == "127.0.0.1"
    params, cfg, scene = demo
    settings = ViewerSettings(height=64, moving_height=64, show_points=False, show_cameras=False)
    viewer = Viewer(ViewRenderer(params, cfg, scene.gaussians), scene, host=host, port=0, settings=settings)
    try:
        with socket.create_connection(("127.0.0.1", viewer.port), timeout=5.0):
            pass
        with pytest.raises(OSError):
            socket.create_connection((other, viewer.port), timeout=5.0).close()
    finally:
        viewer.stop()


@pytest.mark.slow
def test_four_tabs_under_load(demo, browser):
    """Four tabs of one page, each moved to its own cameras three times in a row: every tab
    gets the frame of its newest camera (per-tab latency under a bound), the server's
    memory stays bounded, and closing two tabs stops their render workers."""
    params, cfg, scene = demo
    settings = ViewerSettings(height=64, moving_height=64, show_points=False, show_cameras=False)
    viewer = Viewer(ViewRenderer(params, cfg, scene.gaussians), scene, host="127.0.0.1", port=0, settings=settings)
    try:
        url = f"http://127.0.0.1:{viewer.port}/"
        browser.get(url)
        for _ in range(3):
            browser.switch_to.new_window("tab")
            browser.get(url)
        deadline = time.monotonic() + 180.0  # the first frame compiles the renderer once
        while len(viewer.tabs()) < 4 and time.monotonic() < deadline:
            time.sleep(0.2)
        tabs = sorted(viewer.tabs())
        assert len(tabs) == 4, f"{len(tabs)} of 4 tabs got a frame"
        rss_before = _rss_bytes()
        cams = scene.input_c2w
        latencies = {t: [] for t in tabs}
        for round_ in range(3):
            # Two requests per tab back to back: the worker may skip the first, never the second.
            starts = {}
            for i, t in enumerate(tabs):
                viewer.set_camera(cams[(i + round_ + 1) % len(cams)], tab=t)
                viewer.set_camera(cams[(i + round_) % len(cams)], tab=t)
                starts[t] = time.monotonic()
            pending = set(tabs)
            deadline = time.monotonic() + 60.0
            while pending and time.monotonic() < deadline:
                for t, (_, frame) in viewer.tabs().items():
                    want = cams[(tabs.index(t) + round_) % len(cams)]
                    if t in pending and np.allclose(frame.c2w, want, atol=1e-4):
                        pending.discard(t)
                        latencies[t].append(time.monotonic() - starts[t])
                time.sleep(0.02)
            assert not pending, f"round {round_}: tabs {sorted(pending)} never showed their newest camera"
        worst = max(max(v) for v in latencies.values())
        assert worst < 30.0, latencies  # 64 px renders on 2 shared cores: seconds, not minutes
        grown = _rss_bytes() - rss_before
        assert grown < 300 * 2**20, f"server memory grew by {grown / 2**20:.0f} MiB over 24 camera moves"

        workers = viewer.workers
        handles = browser.window_handles
        for h in handles[2:]:
            browser.switch_to.window(h)
            browser.close()
        browser.switch_to.window(handles[0])
        deadline = time.monotonic() + 60.0
        while len(viewer.workers) > 2 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(viewer.workers) == 2, f"{len(viewer.workers)} workers after closing 2 of 4 tabs"
        closed = [w for t, w in workers.items() if t not in viewer.workers]
        deadline = time.monotonic() + 30.0
        while any(w.alive for w in closed) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(closed) == 2 and not any(w.alive for w in closed)
        print(
            f"four tabs: latency per tab (s) {[[round(x, 2) for x in latencies[t]] for t in tabs]}, "
            f"RSS {rss_before / 2**20:.0f} -> {(rss_before + grown) / 2**20:.0f} MiB"
        )
    finally:
        viewer.stop()


def test_renderer_sizes_its_splat_buffer_from_the_input_cameras(rng):
    """With the scene's input cameras, a render size's buffer holds what the wide Gaussians of
    ``tests.helpers.wide_gaussians`` need (the trace-time 8 per Gaussian would drop some), also
    at twice the inputs' size: the render equals "RGB" ``rasterize`` with room for every Gaussian in
    every block (atol 1e-5). Without cameras the config's buffer is kept."""
    from llrmpp_jax.splat import SplatConfig, rasterize
    from tests.helpers.wide_gaussians import INTRINSICS, SIZE, wide_colour_scene

    g, cfg, c2w = wide_colour_scene(rng)
    batch = jax.tree.map(lambda x: jnp.asarray(x)[None], g)
    renderer = ViewRenderer({}, cfg, batch, cameras=(c2w[:1], INTRINSICS[None], (SIZE, SIZE)))
    assert ViewRenderer({}, cfg, batch).config_for(SIZE, SIZE) == cfg
    for size in (SIZE, 2 * SIZE):
        k = (INTRINSICS * size / SIZE).astype(np.float32)
        frame = renderer.render(ViewKey(size, size, "rgb", 1), c2w[1], k)
        room = SplatConfig(max_intersections=g.means.shape[0] * (size // 8) ** 2)
        want = rasterize(
            g.means,
            g.quats,
            g.scales,
            g.opacities,
            g.features[:, None, :],
            c2w[1].astype(np.float32),
            k,
            size,
            size,
            room,
            render_mode="RGB",
            background=np.ones(3, np.float32),
        ).features
        np.testing.assert_allclose(frame.image, np.asarray(want), atol=1e-5)


# -- command line ---------------------------------------------------------------------------


def _saved_scene(rng, cfg, feature_dim: int):
    from llrmpp_jax.capture import SavedScene

    n, v = 64, 3
    g = Gaussians(
        rng.normal(size=(n, 3)).astype(np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        np.full((n, 3), 0.05, np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        np.full((n,), 0.5, np.float32),  # pyright: ignore[reportArgumentType] -- as above
        rng.normal(size=(n, feature_dim)).astype(np.float32),
    )
    c2w = np.tile(np.eye(4, dtype=np.float32), (v, 1, 1))
    c2w[:, 2, 3] = -3.0 - np.arange(v)
    intr = np.float32([32, 32, 16, 16]) * np.arange(1, v + 1, dtype=np.float32)[:, None]  # pyright: ignore[reportArgumentType] -- a list of four numbers makes a float32 array
    return SavedScene(
        g,
        cfg,
        c2w,
        intr,
        np.eye(4),
        ("a", "b", "c"),
        np.array([0, 2]),
        np.array([1]),
        (32, 32),
        (32, 32),
        (0, 0, 32, 32),
        "/no/capture",
        "colmap",
    )


def test_saved_view_scene(rng):
    cfg = load_experiment("demo").model
    saved = _saved_scene(rng, cfg, cfg.head.feature_dim)
    photos = rng.uniform(-0.1, 1.1, (2, 32, 32, 3)).astype(np.float32)
    scene = saved_view_scene(saved, photos)
    for got, want in zip(scene.gaussians, saved.gaussians):
        np.testing.assert_array_equal(got, want[None])
    np.testing.assert_array_equal(scene.input_c2w, saved.c2w[[0, 2]])
    np.testing.assert_array_equal(scene.input_intrinsics, saved.intrinsics[[0, 2]])
    np.testing.assert_array_equal(scene.thumbnails, np.round(np.clip(photos, 0, 1) * 255).astype(np.uint8))
    assert scene.input_hw == (32, 32) and scene.name == "capture" and saved_view_scene(saved).thumbnails is None


def test_cli_bad_input_is_one_line(tmp_path, rng, capsys):
    """A port in use, a feature-mode .gs without a checkpoint, a .gs whose Gaussians or whose
    checkpoint do not fit its model config: exit status 2 and one line each."""
    from llrmpp_jax.capture import save_gs
    from llrmpp_jax.cli import main
    from llrmpp_jax.model import expected_shapes
    from llrmpp_jax.params_io import save_params

    cfg = load_experiment("demo").model

    def one_line(argv, pattern):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert __import__("re").search(pattern, err), err

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        one_line(
            ["view", "--procedural", "0", "--random-init", "--host", "127.0.0.1", "--port", str(taken)],
            rf"port {taken} on 127.0.0.1 is already in use; try --port \d+",
        )
    good, bad = str(tmp_path / "good.gs"), str(tmp_path / "bad.gs")
    save_gs(good, _saved_scene(rng, cfg, cfg.head.feature_dim))
    save_gs(bad, _saved_scene(rng, cfg, 8))
    one_line(["view", "--gaussians", good], r"good.gs: a feature-mode scene needs --checkpoint")
    one_line(["view", "--gaussians", bad], r"bad.gs: Gaussians carry 8 values per Gaussian .* expects F=16 features")
    narrow = replace(cfg, head=replace(cfg.head, feature_dim=8))
    save_params(
        str(tmp_path / "narrow"), jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), expected_shapes(narrow)), narrow
    )
    one_line(
        ["view", "--gaussians", good, "--checkpoint", str(tmp_path / "narrow")],
        r"narrow: parameters do not fit the model config: first mismatch",
    )


def _other_address() -> str:
    """An address of this machine that is not 127.0.0.1: the interface a packet out would
    leave by, else 127.0.1.1 (a loopback address, but not the one a 127.0.0.1 bind accepts)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("10.255.255.255", 1))  # no packet is sent; picks the outgoing interface
            address = s.getsockname()[0]
        except OSError:
            address = "127.0.0.1"
    return address if address != "127.0.0.1" else "127.0.1.1"


def _view(*args: str):
    import signal
    import subprocess
    import sys

    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "llrmpp_jax.cli",
            "view",
            "--procedural",
            "1",
            "--random-init",
            "--port",
            "0",
            "--height",
            "64",
            "--moving-height",
            "32",
            *args,
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # xdist workers ignore SIGINT and a child inherits that: restore Ctrl-C
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def test_cli_serves_the_page_to_this_machine_only(tmp_path):
    """``llrmpp view --procedural`` serves viser's page until interrupted; by default on
    127.0.0.1 only: the same port on another address of this machine refuses the connection."""
    import signal
    import urllib.error
    import urllib.request

    proc = _view()
    try:
        line = ""
        while not line.startswith("llrmpp view:"):  # after viser's own banner
            line = proc.stdout.readline()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
            assert line, proc.stderr.read()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
        assert "1,024 feature-mode Gaussians" in line and "anyone" not in line, line
        url = line.split(" at ")[1].split(" ")[0]
        port = int(url.rsplit(":", 1)[1].strip("/"))
        page = urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=30).read().decode()
        assert "<html" in page.lower() and "viser" in page.lower()
        elsewhere = f"http://{_other_address()}:{port}"
        with pytest.raises(urllib.error.URLError, match="refused"):
            urllib.request.urlopen(elsewhere, timeout=10)
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 130


@pytest.mark.parametrize("after_s", [0.0, 2.0])
def test_cli_shared_on_the_network_says_so_first(after_s):
    """``--host 0.0.0.0`` prints, before anything is loaded, that anyone who can reach the port
    sees the scene and its photos. A Ctrl-C while JAX starts (``after_s`` later) is one line and
    status 130 (it once hung, or crashed in the interpreter's teardown)."""
    import signal
    import time

    proc = _view("--host", "0.0.0.0")
    try:
        first = proc.stdout.readline()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
        assert first.startswith("llrmpp view: serving on 0.0.0.0: anyone who can reach port"), first
        assert "sees the scene and its photos" in first
        time.sleep(after_s)
    finally:
        proc.send_signal(signal.SIGINT)
        status = proc.wait(timeout=30)
    err = proc.stderr.read()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
    assert status == 130 and err.endswith("llrmpp: interrupted\n") and "Traceback" not in err, (status, err)
