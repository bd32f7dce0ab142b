"""Readers and writers of on-disk multi-view formats; each reader returns a
:class:`~llrmpp_jax.data.scene.Scene`."""

from llrmpp_jax.data.formats.colmap import read_colmap_model, read_colmap_scene, write_colmap_scene
from llrmpp_jax.data.formats.long_lrm import (
    cached_kmeans_inputs,
    read_kmeans_index,
    read_long_lrm_index,
    read_long_lrm_scene,
    write_long_lrm_index,
    write_long_lrm_scene,
)
from llrmpp_jax.data.formats.nerfstudio import read_nerfstudio_scene, write_nerfstudio_scene
from llrmpp_jax.data.formats.re10k import read_re10k_eval_index, read_re10k_scene, write_re10k_scene
from llrmpp_jax.data.formats.registry import (
    FORMATS,
    READERS,
    Format,
    dataset_scenes,
    detect_format,
    listed_scenes,
    read_scene,
)
from llrmpp_jax.data.formats.scannet import read_scannet_scene, write_scannet_scene

__all__ = [
    "FORMATS",
    "Format",
    "READERS",
    "dataset_scenes",
    "detect_format",
    "listed_scenes",
    "read_scene",
    "cached_kmeans_inputs",
    "read_colmap_model",
    "read_colmap_scene",
    "read_kmeans_index",
    "read_long_lrm_index",
    "read_long_lrm_scene",
    "read_nerfstudio_scene",
    "read_re10k_eval_index",
    "read_re10k_scene",
    "read_scannet_scene",
    "write_colmap_scene",
    "write_long_lrm_index",
    "write_long_lrm_scene",
    "write_nerfstudio_scene",
    "write_re10k_scene",
    "write_scannet_scene",
]
