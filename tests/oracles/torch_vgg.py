"""torchvision's VGG ``features`` module, run layer by layer in torch (float64), and random
state dicts in its layout: the oracle of the VGG feature extractor (``perceptual.py``) and
of the perceptual loss (``losses.py``)."""

import numpy as np
import torch
import torch.nn.functional as F

# torchvision's ``features`` configurations ("M" = pooling module).
TORCHVISION_CFG = {
    "vgg16": [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"],
    "vgg19": [64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M", 512, 512, 512, 512, "M", 512, 512, 512, 512, "M"],
}


def random_torchvision_state_dict(rng: np.random.Generator, arch: str) -> dict[str, torch.Tensor]:
    """He-initialised ``features.{idx}.weight/bias`` in torchvision's layout, built from the cfg."""
    sd, idx, cin = {}, 0, 3
    for v in TORCHVISION_CFG[arch]:
        if v == "M":
            idx += 1
            continue
        w = rng.standard_normal((v, cin, 3, 3)) * np.sqrt(2.0 / (9 * cin))
        sd[f"features.{idx}.weight"] = torch.tensor(w, dtype=torch.float32)
        sd[f"features.{idx}.bias"] = torch.tensor(0.05 * rng.standard_normal(v), dtype=torch.float32)
        idx, cin = idx + 2, v
    return sd


def torch_vgg_taps(sd, x, arch, tap_module_indices, pool):
    """Run torchvision's ``features`` module by module (conv, ReLU, pool) and collect outputs."""
    outs, idx = {}, 0
    for v in TORCHVISION_CFG[arch]:
        if v == "M":
            x = F.max_pool2d(x, 2, 2) if pool == "max" else F.avg_pool2d(x, 2, 2)
            idx += 1
            continue
        x = F.conv2d(x, sd[f"features.{idx}.weight"].double(), sd[f"features.{idx}.bias"].double(), padding=1)
        x = F.relu(x)
        outs[idx + 1] = x
        idx += 2
        if idx > max(tap_module_indices):
            break
    return [outs[i] for i in tap_module_indices]
