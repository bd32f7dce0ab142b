"""A capture of your own, end to end: poses for photos or a video that have none
(:func:`estimate_poses`, COLMAP), reconstruct once (:func:`reconstruct_scene`), save the
Gaussians (:mod:`.scene_file`), render targets, input views, smooth paths and orbits
(:func:`render_views`), refine against the input photos (:func:`refine_scene`). Every
``llrmpp`` capture command is a thin shell over these."""

from llrmpp_jax.capture.poses import PosesConfig, PosesReport, estimate_poses, extract_frames
from llrmpp_jax.capture.reconstruct import CameraReport, Reconstruction, camera_report, reconstruct_scene, select_views
from llrmpp_jax.capture.refine import RefinedScene, refine_scene
from llrmpp_jax.capture.render import RenderedViews, path_cameras, render_views
from llrmpp_jax.capture.scene_file import GS_VERSION, SavedScene, load_gs, save_gs

__all__ = [
    "GS_VERSION",
    "CameraReport",
    "PosesConfig",
    "PosesReport",
    "Reconstruction",
    "RefinedScene",
    "RenderedViews",
    "SavedScene",
    "camera_report",
    "estimate_poses",
    "extract_frames",
    "load_gs",
    "path_cameras",
    "reconstruct_scene",
    "refine_scene",
    "render_views",
    "save_gs",
    "select_views",
]
