"""Camera poses from a folder of photos or a video, with COLMAP (``pycolmap``): the step
before everything else for a capture that has no poses yet.

:func:`estimate_poses` runs COLMAP's pipeline -- SIFT features (on the CPU, photos
downscaled to ``max_image_size`` for it), matching (``"sequential"``: each image against
its ``overlap`` successors in name order, for video frames and ordered walks;
``"exhaustive"``: every pair, for small unordered sets; ``"auto"``: sequential for video
frames or more than ``EXHAUSTIVE_UP_TO`` images, else exhaustive), incremental mapping --
keeps the largest model and writes a standard COLMAP capture that every other command
reads (``--scene CAPTURE``).

Folds: with a symmetric or repetitive object, exhaustive matching links look-alike views from
different sides and the model can come out folded (:mod:`llrmpp_jax.capture.pose_check`).
The model is checked for it; under ``matcher="auto"`` a folded exhaustive model is rebuilt
from sequential matching (photos in capture order), and the one with fewer breaks is kept.
Breaks that remain are a warning in the report. The capture::

    CAPTURE/images/        the photos (or the video's frames), full size
    CAPTURE/sparse/0/      cameras.bin, images.bin, points3D.bin (COLMAP's binary model)
    CAPTURE/database.db    COLMAP's features and matches (rerunning mapping needs only it)
    CAPTURE/poses_report.json

:func:`extract_frames` first turns a video into frames (``imageio-ffmpeg``), ``fps`` a
second. The camera model is COLMAP's ``SIMPLE_RADIAL`` by default (one focal length, one
radial term; the focal length starts from the photos' EXIF when they have it, as COLMAP
does), shared by all images when they all have one size (one device) and per image
otherwise; the readers remove the distortion when loading.

Repeatability: on several threads COLMAP's result varies from run to run (its RANSAC and
bundle adjustment see work in a different order; on the beer photos one run in ~6 put part
of a model out of tolerance). ``seed`` makes a run repeat exactly: COLMAP's random seed is
set and everything runs on one thread, at the cost of
the other cores.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from llrmpp_jax.capture.pose_check import continuity_breaks
from llrmpp_jax.data.formats.colmap import import_pycolmap
from llrmpp_jax.data.image_io import image_size, write_image
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.file_kinds import check_video

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr", ".bmp", ".webp")
# Camera models the capture readers undistort (llrmpp_jax.data.formats.colmap).
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
# "auto" matches every pair up to this many images (COLMAP's own advice: exhaustive for a
# few hundred images at most; on a CPU the pairs grow quadratically).
EXHAUSTIVE_UP_TO = 150
Matcher = Literal["auto", "sequential", "exhaustive"]


@dataclass(frozen=True)
class PosesConfig:
    """How :func:`estimate_poses` runs COLMAP."""

    matcher: Matcher = "auto"
    camera_model: str = "SIMPLE_RADIAL"
    max_image_size: int = 1600  # longest side (px) the features are extracted at
    overlap: int = 10  # sequential matching: successors each image is matched with
    min_registered: int = 3  # fewer registered images is a failure
    threads: int = -1  # -1: all cores
    seed: int | None = None  # set: COLMAP's random seed, on one thread, so the run repeats exactly

    def __post_init__(self) -> None:
        if self.matcher not in ("auto", "sequential", "exhaustive"):
            raise UserError(f"--matcher must be auto, sequential or exhaustive, got {self.matcher!r}")
        if self.camera_model not in CAMERA_MODELS:
            raise UserError(f"--camera-model must be one of {', '.join(CAMERA_MODELS)}, got {self.camera_model!r}")
        if self.max_image_size < 64:
            raise UserError(f"--max-image-size must be >= 64 px, got {self.max_image_size}")
        if self.overlap < 1 or self.min_registered < 2:
            raise UserError(f"need overlap >= 1 and min_registered >= 2, got {self.overlap}, {self.min_registered}")
        if self.threads == 0 or self.threads < -1:
            raise UserError(f"--threads must be >= 1 (or -1: all cores), got {self.threads}")
        if self.seed is not None:
            if self.seed < 0:
                raise UserError(f"--seed must be >= 0, got {self.seed}")
            if self.threads not in (-1, 1):
                raise UserError(f"--seed repeats a run only on one thread; drop --threads {self.threads} or make it 1")

    @property
    def num_threads(self) -> int:
        """Threads COLMAP is given: one when seeded, else ``threads`` (-1: all cores)."""
        return 1 if self.seed is not None else self.threads


@dataclass(frozen=True)
class PosesReport:
    """What mapping found. Lengths are in the model's arbitrary units (COLMAP's scale)."""

    capture: str
    given: int
    registered: int
    unregistered: tuple[str, ...]
    models: int  # models COLMAP built; the largest is kept
    matcher: str
    camera_model: str
    shared_camera: bool
    points: int
    mean_reprojection_error_px: float
    mean_track_length: float
    camera_spread: float  # diagonal of the camera centres' bounding box
    points_extent: float  # diagonal of the 5-95 percentile box of the points
    seconds: dict[str, float]
    matchers_tried: tuple[str, ...] = ()  # the kept model's matcher is the last unless a retry did worse
    breaks: tuple[str, ...] = ()  # consecutive photos the kept model puts apart (pose_check): a fold
    seed: int | None = None  # the run's COLMAP seed (it ran on one thread); None: not seeded, not repeatable

    def lines(self) -> list[str]:
        """Human-readable summary, one fact per line."""
        out = [
            f"registered {self.registered} of {self.given} images ({self.models} model(s) built, kept the largest)",
            f"mean reprojection error {self.mean_reprojection_error_px:.2f} px, mean track length "
            f"{self.mean_track_length:.1f}, {self.points} points",
            f"camera centres span {self.camera_spread:.3g}, points' 5-95% extent {self.points_extent:.3g} "
            f"(model units)",
            "phases: " + ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds.items()),
        ]
        if self.unregistered:
            shown = ", ".join(self.unregistered[:8]) + (
                f" and {len(self.unregistered) - 8} more" if len(self.unregistered) > 8 else ""
            )
            out.insert(1, f"not registered: {shown}")
        if len(self.matchers_tried) > 1:
            out.append(
                f"matching: {' then '.join(self.matchers_tried)} (the first model was folded); kept {self.matcher}"
            )
        if self.breaks:
            out.append(
                f"warning: the model looks folded at {len(self.breaks)} place(s): {'; '.join(self.breaks[:3])}"
                + (f" and {len(self.breaks) - 3} more" if len(self.breaks) > 3 else "")
                + ". Photos from different sides of a symmetric or repetitive object were matched; with photos "
                "named in capture order try --matcher sequential, or add photos of the object's distinctive sides"
            )
        return out


def list_images(folder: str) -> list[str]:
    """Image file names in ``folder`` (not recursive), sorted; one-line error if none."""
    if not os.path.isdir(folder):
        raise MissingInputError(f"--images: folder not found: {folder}")
    names = sorted(n for n in os.listdir(folder) if n.lower().endswith(IMAGE_EXTENSIONS))
    if not names:
        raise UserError(f"--images {folder}: no images ({', '.join(IMAGE_EXTENSIONS)})")
    return names


def extract_frames(video: str, out_dir: str, fps: float, progress: Callable[[str], None] = print) -> list[str]:
    """Write ``fps`` frames a second of ``video`` to ``out_dir/frame_00000.jpg``...; return
    their names. Decoding by the ffmpeg binary that ``imageio-ffmpeg`` ships."""
    import imageio_ffmpeg

    if not os.path.isfile(video):
        raise MissingInputError(f"--video: file not found: {video}")
    check_video(video)  # a photo or a text file named .mp4: one line, before ffmpeg runs
    if not fps > 0:
        raise UserError(f"--fps must be > 0, got {fps}")
    try:
        reader = imageio_ffmpeg.read_frames(video, output_params=["-vf", f"fps={fps}"])
        meta = next(reader)
    except (OSError, RuntimeError, StopIteration) as e:
        raise UserError(
            f"--video {video}: not a video ffmpeg can read ({str(e).splitlines()[0] if str(e) else e})"
        ) from e
    os.makedirs(out_dir, exist_ok=True)  # only once ffmpeg reads it: a refused video leaves nothing
    w, h = meta["size"]
    expected = int(meta.get("duration", 0) * fps) or None
    progress(
        f"extracting frames from {video} ({w}x{h}, {fps:g} a second" + (f", ~{expected} frames)" if expected else ")")
    )
    names = []
    for raw in reader:
        frame = np.frombuffer(raw, np.uint8).reshape(h, w, 3)
        name = f"frame_{len(names):05d}.jpg"
        write_image(os.path.join(out_dir, name), frame.astype(np.float32) / 255.0)
        names.append(name)
    if not names:
        raise UserError(f"--video {video}: no frames decoded")
    return names


def _copy_images(src: str, names: list[str], dst: str) -> None:
    """The photos into the capture: hard links where the filesystem allows, else copies."""
    os.makedirs(dst, exist_ok=True)
    for n in names:
        target = os.path.join(dst, n)
        if os.path.exists(target):
            os.remove(target)
        try:
            os.link(os.path.join(src, n), target)
        except OSError:
            shutil.copy2(os.path.join(src, n), target)


def _diagonal(points: np.ndarray, lo: float = 0.0, hi: float = 100.0) -> float:
    if len(points) == 0:
        return 0.0
    a, b = np.percentile(points, [lo, hi], axis=0)
    return float(np.linalg.norm(b - a))


def _match(pycolmap, database: str, matcher: str, n: int, cfg: PosesConfig, progress: Callable[[str], None]) -> None:
    """COLMAP's matching and geometric verification of the pairs ``matcher`` chooses.

    Sequential pairing matches each image with its next ``cfg.overlap`` images only: not
    COLMAP's "quadratic overlap" (also i + 2^k), whose far pairs are the look-alike views that
    fold a model (:mod:`llrmpp_jax.capture.pose_check`), nor its vocabulary-tree loop detection.
    """
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = cfg.num_threads
    if matcher == "exhaustive":
        progress(f"matching: exhaustive, {n * (n - 1) // 2} pairs")
        pycolmap.match_exhaustive(database, matching_options=matching)
    else:
        progress(f"matching: sequential, each image with its next {cfg.overlap}")
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = cfg.overlap
        pairing.quadratic_overlap = False
        pairing.loop_detection = False
        pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing)


def _map(pycolmap, database: str, image_dir: str, scratch: str, cfg: PosesConfig, progress: Callable[[str], None]):
    """Incremental mapping into ``scratch``; ``(largest model or None, all models)``."""
    progress("mapping: incremental")
    os.makedirs(scratch, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = cfg.num_threads
    models = pycolmap.incremental_mapping(database, image_dir, scratch, options=options)
    return max(models.values(), key=lambda r: r.num_reg_images(), default=None), models


def estimate_poses(
    images: str | None,
    out: str,
    cfg: PosesConfig = PosesConfig(),
    *,
    video: str | None = None,
    fps: float = 2.0,
    progress: Callable[[str], None] = print,
) -> PosesReport:
    """Poses for the photos in ``images`` (or the frames of ``video``) as a COLMAP capture
    in ``out`` (module docstring); returns the report, also written as
    ``out/poses_report.json``. A one-line ``UserError`` when fewer than
    ``cfg.min_registered`` images register, saying what to try."""
    pycolmap = import_pycolmap()

    if (images is None) == (video is None):
        raise UserError("give exactly one of --images DIR and --video FILE")
    if os.path.exists(os.path.join(out, "sparse")):
        raise UserError(f"{out} already holds a COLMAP model (sparse/); choose another --out or remove it")
    seconds: dict[str, float] = {}
    image_dir = os.path.join(out, "images")
    t = time.perf_counter()
    if video is not None:
        names = extract_frames(video, image_dir, fps, progress)
        seconds["frames"] = time.perf_counter() - t
    else:
        names = list_images(images)  # pyright: ignore[reportArgumentType] -- exactly one of images and video is given (checked above)
        if len(names) < cfg.min_registered:
            raise UserError(f"{len(names)} images; poses need at least {cfg.min_registered}")
        for n in names:  # each photo opens (text named .jpg is one line naming it) before anything is written
            image_size(os.path.join(images, n))  # pyright: ignore[reportCallIssue, reportArgumentType] -- as above
        _copy_images(images, names, image_dir)  # pyright: ignore[reportArgumentType] -- as above
    if len(names) < cfg.min_registered:
        raise UserError(f"{len(names)} images; poses need at least {cfg.min_registered}")
    sizes = {image_size(os.path.join(image_dir, n)) for n in names}
    shared = len(sizes) == 1
    matcher = cfg.matcher
    if matcher == "auto":
        matcher = "sequential" if video is not None or len(names) > EXHAUSTIVE_UP_TO else "exhaustive"

    pycolmap.logging.minloglevel = 2  # COLMAP's own per-image log lines: errors only
    if cfg.seed is not None:
        pycolmap.set_random_seed(cfg.seed)
        progress(f"repeatable run: seed {cfg.seed}, one thread")
    database = os.path.join(out, "database.db")
    if os.path.exists(database):
        os.remove(database)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cfg.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.use_gpu = False
    extraction.num_threads = cfg.num_threads
    progress(
        f"features: {len(names)} images at up to {cfg.max_image_size} px, camera {cfg.camera_model} "
        + ("shared" if shared else "per image")
    )
    t = time.perf_counter()
    pycolmap.extract_features(
        database,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader,
        extraction_options=extraction,
    )
    seconds["features"] = time.perf_counter() - t

    n = len(names)
    t = time.perf_counter()
    _match(pycolmap, database, matcher, n, cfg, progress)
    seconds["matching"] = time.perf_counter() - t
    tried = [matcher]
    sparse = os.path.join(out, "sparse", "0")
    with tempfile.TemporaryDirectory(dir=out) as scratch:
        t = time.perf_counter()
        best, models = _map(pycolmap, database, image_dir, os.path.join(scratch, matcher), cfg, progress)
        seconds["mapping"] = time.perf_counter() - t
        breaks = continuity_breaks(best, database) if best is not None else []
        if breaks and cfg.matcher == "auto" and matcher == "exhaustive":
            # A fold (pose_check): exhaustive pairs include the look-alike views from other
            # sides; matching each photo only with its successors in capture order leaves them out.
            progress(f"the model looks folded at {len(breaks)} place(s) ({breaks[0]}): matching again sequentially")
            t = time.perf_counter()
            retry_db = os.path.join(scratch, "sequential.db")
            shutil.copy2(database, retry_db)
            with contextlib.closing(pycolmap.Database.open(retry_db)) as db:
                db.clear_matches()
                db.clear_two_view_geometries()
            _match(pycolmap, retry_db, "sequential", n, cfg, progress)
            seconds["matching (sequential)"] = time.perf_counter() - t
            t = time.perf_counter()
            retry, retry_models = _map(
                pycolmap, retry_db, image_dir, os.path.join(scratch, "sequential"), cfg, progress
            )
            seconds["mapping (sequential)"] = time.perf_counter() - t
            tried.append("sequential")
            retry_breaks = continuity_breaks(retry, retry_db) if retry is not None else []
            if retry is not None and retry.num_reg_images() >= cfg.min_registered and len(retry_breaks) < len(breaks):
                best, models, breaks, matcher = retry, retry_models, retry_breaks, "sequential"
                os.replace(retry_db, database)  # the kept model's matches
        registered = best.num_reg_images() if best is not None else 0
        if registered < cfg.min_registered:
            raise UserError(
                f"only {registered} of {n} images registered (need {cfg.min_registered}): give the photos more "
                f"overlap (each spot seen from 3+ nearby viewpoints), try --matcher "
                f"{'exhaustive' if matcher == 'sequential' else 'sequential'}"
                + (", or a higher --fps" if video is not None else " (for ordered photos or frames)")
            )
        os.makedirs(sparse)
        best.write_binary(sparse)  # pyright: ignore[reportOptionalMemberAccess] -- registered >= min_registered >= 1 above, so best is set

    reg_names = {best.image(i).name for i in best.reg_image_ids()}  # pyright: ignore[reportOptionalMemberAccess] -- as above
    centres = np.array([best.image(i).projection_center() for i in best.reg_image_ids()])  # pyright: ignore[reportOptionalMemberAccess] -- as above
    points = np.array([p.xyz for p in best.points3D.values()]).reshape(-1, 3)  # pyright: ignore[reportOptionalMemberAccess] -- as above
    report = PosesReport(
        capture=out,
        given=n,
        registered=registered,
        unregistered=tuple(x for x in names if x not in reg_names),
        models=len(models),
        matcher=matcher,
        camera_model=cfg.camera_model,
        shared_camera=shared,
        points=int(best.num_points3D()),  # pyright: ignore[reportOptionalMemberAccess] -- as above
        mean_reprojection_error_px=float(best.compute_mean_reprojection_error()),  # pyright: ignore[reportOptionalMemberAccess] -- as above
        mean_track_length=float(best.compute_mean_track_length()),  # pyright: ignore[reportOptionalMemberAccess] -- as above
        camera_spread=_diagonal(centres),
        points_extent=_diagonal(points, 5.0, 95.0),
        seconds=seconds,
        matchers_tried=tuple(tried),
        breaks=tuple(str(b) for b in breaks),
        seed=cfg.seed,
    )
    with open(os.path.join(out, "poses_report.json"), "w") as f:
        json.dump(dataclasses.asdict(report), f, indent=1)
    return report
