"""PyTorch state_dict -> JAX parameter pytrees, driven by tables of rules.

``table.py`` holds the machinery (rules, transforms, strict matching and error
reporting); each model family has its own table module (``long_lrm.py``, ``vgg.py``).
"""

from llrmpp_jax.convert.table import Rule, convert_state_dict, load_torch_state_dict

__all__ = ["Rule", "convert_state_dict", "load_torch_state_dict"]
