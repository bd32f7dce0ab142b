"""Data: the ``Scene`` record, readers/writers of real formats, procedural scenes, view
selection, preprocessing and the training batch iterator (batch layout documented in
:mod:`llrmpp_jax.data.batching`)."""

from llrmpp_jax.data.batching import BatchConfig, BatchIterator, FileSource, ProceduralSource
from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.scene import Scene, in_memory_scene
from llrmpp_jax.data.selection import eval_views, kmeans_inputs, training_views, uniform_inputs
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene

__all__ = [
    "BatchConfig",
    "BatchIterator",
    "FileSource",
    "ProceduralConfig",
    "ProceduralSource",
    "Scene",
    "ViewGeometry",
    "eval_views",
    "in_memory_scene",
    "kmeans_inputs",
    "make_sample",
    "procedural_scene",
    "training_views",
    "uniform_inputs",
]
