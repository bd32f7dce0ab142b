"""The live viewer: a viser web page whose view is rendered by our model.

The browser does the orbit / pan / zoom (viser's camera controls) and reports its camera;
the server renders that camera with :class:`~llrmpp_jax.viewer.render.ViewRenderer` and
sends the image back as the page's background. The input cameras are drawn as frustums
(with their thumbnails), the Gaussian centres as a point cloud; the panel chooses RGB or
depth, the render height while the camera moves and once it stops, the partition count S,
and shows the time per frame.

Responsiveness: each browser tab has one render worker thread (rendering never runs on
viser's event loop). Camera messages only overwrite the tab's pending request, so a
worker that falls behind skips straight to the latest camera. While the camera moves the
worker renders at the "moving" height; once the camera has been still for
``still_seconds`` it renders the same camera at full height. Each (size, output, S) is
compiled once (cached by the renderer); while a first compile runs the page shows a
progress notification.
"""

from __future__ import annotations

import dataclasses
import errno
import socket
import sys
import threading
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import viser
import viser.transforms as vtf

from llrmpp_jax.errors import UserError
from llrmpp_jax.viewer.render import OUTPUTS, Frame, ViewKey, ViewRenderer, display_image, viewport_camera
from llrmpp_jax.viewer.scene import ViewerScene, gaussian_centres


class PortInUseError(UserError):
    """The requested port is taken; the message names it and a free one to use instead."""


@dataclasses.dataclass(frozen=True)
class ViewerSettings:
    """Initial state of the panel (all but the point budget can be changed in the page)."""

    height: int = 256  # render height (px) once the camera is still
    moving_height: int = 128  # render height while the camera moves
    still_seconds: float = 0.25  # camera unchanged this long -> full-height render
    output: str = "rgb"
    partitions: int | None = None  # None: the model's S
    show_points: bool = False  # the centres are drawn over the render (no occlusion): off until asked for
    show_cameras: bool = True
    max_points: int = 100_000
    image_format: str = "png"  # how frames travel to the page: "png" (lossless) or "jpeg" (smaller)


class ViewRequest(NamedTuple):
    """A browser camera: OpenCV c2w, vertical field of view (radians), width / height."""

    c2w: np.ndarray
    fov_y: float
    aspect: float
    moving: bool


def _bind_error(host: str, port: int) -> OSError | None:
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, port))
    except OSError as e:
        return e
    return None


def check_port(host: str, port: int) -> None:
    """Raise if the page cannot be served on ``host:port`` (0 = any free port):
    :class:`PortInUseError` naming a free port nearby if it is taken, ``ValueError`` for
    any other reason the bind fails (a privileged port, an unknown host, a port outside
    0..65535)."""
    if not 0 <= port <= 65535:
        raise UserError(f"--port must be in 0..65535, got {port}")
    err = None if port == 0 else _bind_error(host, port)
    if err is None:
        return
    if err.errno == errno.EADDRINUSE:
        free = next((p for p in range(port + 1, min(port + 100, 65536)) if _bind_error(host, p) is None), None)
        raise PortInUseError(f"port {port} on {host} is already in use" + (f"; try --port {free}" if free else ""))
    raise UserError(f"cannot serve on {host}:{port}: {err.strerror or err}")


def camera_c2w(wxyz: np.ndarray, position: np.ndarray) -> np.ndarray:
    """viser camera (``P_world = R p_camera + t``, OpenCV axes) -> c2w ``[4, 4]`` float32."""
    c2w = np.eye(4, dtype=np.float32)
    c2w[:3, :3] = vtf.SO3(np.asarray(wxyz, np.float64)).as_matrix()
    c2w[:3, 3] = position
    return c2w


def _request(camera: viser.CameraHandle, moving: bool) -> ViewRequest:
    return ViewRequest(camera_c2w(camera.wxyz, camera.position), float(camera.fov), float(camera.aspect), moving)


class RenderWorker:
    """One browser tab's render thread.

    :meth:`request` only replaces the pending request, so requests that arrive while a
    render runs are dropped except the latest. After a ``moving`` request has been rendered
    and nothing new arrived for ``still_seconds``, the same camera is rendered again with
    ``moving=False`` (full height). ``render`` is called on the worker thread only.
    """

    def __init__(self, render: Callable[[ViewRequest], None], still_seconds: float, name: str):
        self._render, self._still_seconds = render, still_seconds
        self._cond = threading.Condition()
        self._pending: ViewRequest | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def request(self, req: ViewRequest) -> None:
        """Replace the pending request (an older one not yet started is dropped)."""
        with self._cond:
            self._pending = req
            self._cond.notify()

    @property
    def alive(self) -> bool:
        """The worker's thread is running (False once closed and finished)."""
        return self._thread.is_alive()

    def close(self, wait: bool = False) -> None:
        """Stop the worker after its current render (``wait``: until it has stopped)."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        if wait:
            self._thread.join()

    def _run(self) -> None:
        last: ViewRequest | None = None  # the latest camera, if rendered only while moving
        while True:
            with self._cond:
                if self._pending is None and not self._closed:
                    self._cond.wait(timeout=self._still_seconds if last else None)
                if self._closed:
                    return
                req, self._pending = self._pending, None
            if req is None:  # still for still_seconds after a moving render: full height
                req, last = last._replace(moving=False), None  # pyright: ignore[reportOptionalMemberAccess] -- the wait times out only when last is set, and a notify sets _pending or _closed
            elif req.moving:
                last = req
            self._render(req)


class Viewer:
    """Serve ``scene`` rendered by ``renderer`` on ``http://host:port`` (viser).

    Starts serving on construction; :meth:`stop` shuts it down. ``port=0`` picks a free
    port (see :attr:`port`). A taken port raises :class:`PortInUseError` before anything
    starts.
    """

    def __init__(
        self,
        renderer: ViewRenderer,
        scene: ViewerScene,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        settings: ViewerSettings = ViewerSettings(),
    ):
        m, most = renderer.cfg.size_multiple, renderer.max_partitions
        if settings.height <= 0 or settings.moving_height <= 0 or settings.height % m or settings.moving_height % m:
            raise UserError(
                f"viewer heights must be positive multiples of {m}, got {settings.height} and {settings.moving_height}"
            )
        if settings.output not in OUTPUTS or not 1 <= (settings.partitions or most) <= most:
            raise UserError(
                f"viewer output must be one of {OUTPUTS} and partitions in [1, {most}], got "
                f"{settings.output!r} and {settings.partitions}"
            )
        check_port(host, port)
        self.renderer, self.scene, self.settings = renderer, scene, settings
        self._last: Frame | None = None  # the latest frame sent to any tab
        self._frame_count = 0
        self._frame_cond = threading.Condition()
        self._workers: dict[int, RenderWorker] = {}
        self._tab_frames: dict[int, tuple[int, Frame]] = {}  # tab (client id) -> (frames sent, latest)
        self._stopped = False
        self.server = viser.ViserServer(host=host, port=port, label="llrmpp view", verbose=False)
        if port and self.server.get_port() != port:  # taken between our check and viser's bind
            self.server.stop()
            raise PortInUseError(f"port {port} on {host} is already in use; try --port {self.server.get_port() + 1}")
        self._add_scene()
        self._add_gui()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def port(self) -> int:
        return self.server.get_port()

    # -- scene --------------------------------------------------------------------------
    def _add_scene(self) -> None:
        sc, s = self.scene, self.settings
        centres = sc.input_c2w[:, :3, 3]
        extent = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0))) or 1.0
        up = -sc.input_c2w[:, :3, 1].mean(axis=0)  # mean of the inputs' up (-y) axes
        self.server.scene.set_up_direction(up / max(np.linalg.norm(up), 1e-12))
        h, w = sc.input_hw
        self._frustums = []
        for i, (c2w, k) in enumerate(zip(sc.input_c2w, sc.input_intrinsics)):
            self._frustums.append(
                self.server.scene.add_camera_frustum(
                    f"/inputs/{i}",
                    fov=float(2.0 * np.arctan(h / (2.0 * k[1]))),
                    aspect=w / h,
                    scale=0.08 * extent,
                    wxyz=vtf.SO3.from_matrix(c2w[:3, :3].astype(np.float64)).wxyz,
                    position=c2w[:3, 3],
                    image=None if sc.thumbnails is None else sc.thumbnails[i],
                    visible=s.show_cameras,
                    color=(200, 60, 40),
                    thickness=1.5,
                    thickness_units="screen",
                )
            )
        points, colours = gaussian_centres(self.renderer.cfg, sc.gaussians, s.max_points, np.random.default_rng(0))
        size = float(np.median(np.asarray(sc.gaussians.scales[0]).max(axis=-1)))  # a typical Gaussian's radius
        self._points = self.server.scene.add_point_cloud(
            "/gaussians", points, colours, point_size=size, point_shape="rounded", visible=s.show_points
        )
        # New tabs open at the first input camera.
        c2w, k = sc.input_c2w[0], sc.input_intrinsics[0]
        cam = self.server.initial_camera
        cam.fov = float(2.0 * np.arctan(h / (2.0 * k[1])))
        cam.position = c2w[:3, 3]
        cam.look_at = c2w[:3, 3] + c2w[:3, 2] * extent
        cam.up = -c2w[:3, 1]

    # -- panel --------------------------------------------------------------------------
    def _add_gui(self) -> None:
        gui, s, m = self.server.gui, self.settings, self.renderer.cfg.size_multiple
        top = max(1024, s.height)
        self._output = gui.add_dropdown("view", OUTPUTS, initial_value=s.output)
        self._height = gui.add_slider("height (still)", min=m, max=top, step=m, initial_value=s.height)
        self._moving = gui.add_slider("height (moving)", min=m, max=top, step=m, initial_value=s.moving_height)
        most = self.renderer.max_partitions  # 1 (colour mode, or S=1): a disabled slider, as min < max is needed
        self._partitions = gui.add_slider(
            "partitions S",
            min=1,
            max=max(most, 2),
            step=1,
            initial_value=most if s.partitions is None else s.partitions,
            disabled=most == 1,
        )
        show_points = gui.add_checkbox("Gaussian centres", initial_value=s.show_points)
        show_cameras = gui.add_checkbox("input cameras", initial_value=s.show_cameras)
        self._readout = gui.add_markdown("waiting for the browser's camera...")

        @show_points.on_update
        def _(_) -> None:
            self._points.visible = show_points.value

        @show_cameras.on_update
        def _(_) -> None:
            for f in self._frustums:
                f.visible = show_cameras.value

        for handle in (self._output, self._height, self._partitions):
            handle.on_update(lambda _: self._rerender_all())

    def _rerender_all(self) -> None:
        for client in self.server.get_clients().values():
            if client.client_id in self._workers:
                self._workers[client.client_id].request(_request(client.camera, moving=False))

    def _report(self, text: str) -> None:
        self._readout.content = text

    # -- clients ------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        worker = RenderWorker(
            lambda req: self._render_safely(client, req),
            self.settings.still_seconds,
            name=f"llrmpp-view-{client.client_id}",
        )
        self._workers[client.client_id] = worker

        @client.camera.on_update
        def _(camera: viser.CameraHandle) -> None:  # a lower-resolution render first unless both heights agree
            worker.request(_request(camera, moving=self._moving.value != self._height.value))

        worker.request(_request(client.camera, moving=False))

    def _disconnect(self, client: viser.ClientHandle) -> None:
        worker = self._workers.pop(client.client_id, None)
        if worker is not None:
            worker.close()
        with self._frame_cond:
            self._tab_frames.pop(client.client_id, None)

    def _render_safely(self, client: viser.ClientHandle, req: ViewRequest) -> None:
        try:
            self._render_for(client, req)
        except Exception as e:  # keep the worker alive; say what went wrong in the page and on stderr
            self._report(f"render failed: {type(e).__name__}: {e}")
            print(f"llrmpp view: render failed: {e!r}", file=sys.stderr)

    def _render_for(self, client: viser.ClientHandle, req: ViewRequest) -> None:
        """Render ``req`` with the panel's current settings and show it in ``client``'s page."""
        height = int(self._moving.value if req.moving else self._height.value)
        output, partitions = str(self._output.value), min(int(self._partitions.value), self.renderer.max_partitions)
        height, width, intrinsics = viewport_camera(req.fov_y, req.aspect, height, self.renderer.cfg.size_multiple)
        key = ViewKey(height, width, output, partitions)
        if not self.renderer.is_compiled(key):
            what = f"{width}x{height} {output}, S={partitions}"
            self._report(f"compiling the renderer for {what} (once per size)...")
            note = client.add_notification(
                "Compiling", f"first view at {what}; later views reuse it", loading=True, with_close_button=False
            )
            try:
                compile_s = self.renderer.compile(key)
            finally:
                note.remove()
        else:
            compile_s = 0.0
        frame = self.renderer.render(key, req.c2w, intrinsics)
        frame = dataclasses.replace(frame, compile_s=compile_s)
        client.scene.set_background_image(display_image(frame.image, output), format=self.settings.image_format)  # pyright: ignore[reportArgumentType] -- a str checked against the Literal's values at run time
        compiled = f" (compiled: {self.renderer.compile_notes[key]})" if compile_s else ""
        self._report(
            f"**{1e3 * frame.render_s:.0f} ms** per frame at {width}x{height} {output}, "
            f"S={partitions}{' (moving)' if req.moving else ''}{compiled}"
        )
        with self._frame_cond:
            self._last = frame
            self._frame_count += 1
            if client.client_id in self._workers:  # a tab closed meanwhile keeps no record
                count = self._tab_frames.get(client.client_id, (0, frame))[0]
                self._tab_frames[client.client_id] = (count + 1, frame)
            self._frame_cond.notify_all()

    # -- control from Python ------------------------------------------------------------
    @property
    def frame_count(self) -> int:
        """Frames rendered and sent so far (all tabs)."""
        with self._frame_cond:
            return self._frame_count

    def wait_for_frame(self, after: int, timeout: float) -> Frame:
        """Block until more than ``after`` frames have been sent; the latest one
        (``TimeoutError`` after ``timeout`` seconds)."""
        with self._frame_cond:
            if not self._frame_cond.wait_for(lambda: self._frame_count > after, timeout=timeout):
                raise TimeoutError(f"no frame after frame {after} within {timeout} s")
            return self._last  # pyright: ignore[reportReturnType] -- a frame was counted, so _last is set

    def tabs(self) -> dict[int, tuple[int, Frame]]:
        """Open tabs (viser client ids) that have been sent a frame: ``(frames sent, the
        latest frame)`` each."""
        with self._frame_cond:
            return dict(self._tab_frames)

    @property
    def workers(self) -> dict[int, RenderWorker]:
        """The render worker of each open tab."""
        return dict(self._workers)

    def set_camera(self, c2w: np.ndarray, fov_y: float | None = None, tab: int | None = None) -> None:
        """Move every open tab's camera (or only tab ``tab``'s, a viser client id) to the
        OpenCV ``c2w [4, 4]`` (and vertical field of view, radians) and render it at full
        height."""
        c2w = np.asarray(c2w, np.float64)
        for client in self.server.get_clients().values():
            if tab is not None and client.client_id != tab:
                continue
            with client.atomic():
                cam = client.camera
                look = float(np.linalg.norm(cam.look_at - cam.position)) or 1.0
                if fov_y is not None:
                    cam.fov = fov_y
                cam.position = c2w[:3, 3]
                cam.look_at = c2w[:3, 3] + c2w[:3, 2] * look
                cam.up_direction = -c2w[:3, 1]
            worker = self._workers.get(client.client_id)
            if worker is not None:
                worker.request(_request(cam, moving=False))

    def serve_forever(self) -> None:
        """Block until Ctrl-C, then stop."""
        try:
            while True:
                time.sleep(3600.0)
        finally:
            self.stop()

    def stop(self) -> None:
        """Stop the server and the render workers (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        self.server.stop()
        for worker in list(self._workers.values()):
            worker.close(wait=True)
        self._workers.clear()
