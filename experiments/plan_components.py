"""Each component of the paper model at the stage-4 shapes compiled for a TPU chip from this CPU:
compile time, temp memory and the HLO estimate (``llrmpp_jax.plan``), one process per piece under
a time limit, so that a piece that compiles for too long is named rather than waited for.

Run (libtpu installed: ``pip install -e '.[tpu]'``):
    python experiments/plan_components.py --target v5p --limit 400 --out experiments/results/plan_components_v5p.json
    python experiments/plan_components.py --head-views 1,2,4    # the Gaussian head's compile time against its views

The pieces are ``experiments/cost_table.py``'s (the same shapes), with the TPU path's kernels:
the blockwise global attention and the sequential SSD recurrence. ``--grad`` compiles each
piece's gradient (of the sum of its floating outputs) instead of its forward.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def _one(piece: str, target: str, grad: bool) -> dict:
    """Compile one piece in this process; its row."""
    sys.path.insert(0, HERE)
    import cost_table as CT  # noqa: E402  (experiments/ is not a package)
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from llrmpp_jax.nn.attention import multi_head_attention
    from llrmpp_jax.nn.ssd import ssd_scan
    from llrmpp_jax.plan import targets
    from llrmpp_jax.plan.hlo_cost import estimate_hlo
    from llrmpp_jax.plan.planner import chip_model

    t = targets.target(target)
    mesh = Mesh(np.asarray(targets.compile_devices(t)[:1]), ("batch",))
    rep = NamedSharding(mesh, PartitionSpec())
    fn, args = {p.name: p for p in CT.PIECES}[piece].build()
    if piece == "global_attention":  # the TPU path's kernel, not the plain one the CPU table counts
        fn = lambda q, k, v: multi_head_attention(q, k, v, implementation="blockwise")  # noqa: E731
    elif piece == "ssd_scan":
        m = CT.MAMBA
        fn = lambda x, dt, a, b, c, d: ssd_scan(  # noqa: E731
            x,
            dt,
            a,
            b,
            c,
            chunk_size=m.chunk_size,
            D=d,
            inter_chunk="sequential",
        )
    if grad:
        forward = fn

        def total(*a):
            return sum(
                jnp.sum(x.astype(jnp.float32))
                for x in jax.tree.leaves(forward(*a))
                if jnp.issubdtype(x.dtype, jnp.floating)
            )

        floating = tuple(
            i for i, a in enumerate(args) if all(jnp.issubdtype(x.dtype, jnp.floating) for x in jax.tree.leaves(a))
        )
        fn = jax.grad(total, argnums=floating)
    args = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=rep), args)
    t0 = time.perf_counter()
    with jax.numpy_dtype_promotion("standard"):
        compiled = jax.jit(fn).lower(*args).compile()
    row = {
        "piece": piece,
        "grad": grad,
        "target": target,
        "compile_s": time.perf_counter() - t0,
        "temp_bytes": compiled.memory_analysis().temp_size_in_bytes,  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
    }
    row["estimate"] = estimate_hlo(compiled.as_text(), chip_model(target)).to_json()  # pyright: ignore[reportArgumentType] -- as_text() is None only without an HLO module; a compiled program has one
    return row


def head_compile_s(views: int, target: str) -> float:
    """Seconds to compile the paper model's Gaussian head for ``views`` views of 544x960."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from llrmpp_jax import config as C
    from llrmpp_jax.gaussians import GaussianHead
    from llrmpp_jax.plan import targets

    mesh = Mesh(np.asarray(targets.compile_devices(targets.target(target))[:1]), ("batch",))
    rep = NamedSharding(mesh, PartitionSpec())
    cfg = C.paper_dl3dv()
    grid = (544 // cfg.token_stride, 960 // cfg.token_stride)
    head = GaussianHead(cfg.head, cfg.token_stride)
    sds = lambda shape, dtype=jnp.float32: jax.ShapeDtypeStruct(shape, dtype, sharding=rep)  # noqa: E731
    args = (
        sds((1, views * grid[0] * grid[1], cfg.backbone.dims[0]), jnp.bfloat16),
        sds((1, views, 4, 4)),
        sds((1, views, 4)),
    )
    params = jax.eval_shape(lambda t, c, k: head.init(jax.random.key(0), t, grid, c, k), *args)["params"]
    params = jax.tree.map(lambda x: sds(x.shape, jnp.bfloat16), params)
    t0 = time.perf_counter()
    jax.jit(lambda p, t, c, k: head.apply({"params": p}, t, grid, c, k)).lower(params, *args).compile()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", default="v5p", help="a llrmpp_jax.plan target (one chip)")
    parser.add_argument("--pieces", default=None, help="comma-separated subset of cost_table.PIECES' names")
    parser.add_argument("--grad", action="store_true", help="compile each piece's gradient instead of its forward")
    parser.add_argument("--limit", type=float, default=400.0, help="seconds one piece may compile")
    parser.add_argument("--out", default=None, help="JSON file of the rows (rewritten after each)")
    parser.add_argument(
        "--head-views",
        default=None,
        help="comma-separated view counts: time the Gaussian head's compile at each instead",
    )
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: compile this piece here
    args = parser.parse_args()
    if args.head_views:
        for v in (int(x) for x in args.head_views.split(",")):
            print(
                json.dumps(
                    {
                        "piece": "gaussian_head",
                        "views": v,
                        "target": args.target,
                        "compile_s": head_compile_s(v, args.target),
                    }
                ),
                flush=True,
            )
        return
    if args.one:
        print(json.dumps(_one(args.one, args.target, args.grad)))
        return
    sys.path.insert(0, HERE)
    import cost_table as CT  # noqa: E402

    names = args.pieces.split(",") if args.pieces else [p.name for p in CT.PIECES]
    rows = []
    for name in names:
        cmd = [sys.executable, __file__, "--one", name, "--target", args.target] + (["--grad"] if args.grad else [])
        env = {**os.environ, "JAX_PLATFORMS": "cpu"}
        t0 = time.perf_counter()
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=args.limit, env=env)
            lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
            row = json.loads(lines[-1]) if lines else {"piece": name, "error": done.stderr.strip().splitlines()[-1:]}
        except subprocess.TimeoutExpired:
            row = {
                "piece": name,
                "grad": args.grad,
                "target": args.target,
                "compile_s": None,
                "not_compiled_within_s": args.limit,
            }
        row["wall_s"] = time.perf_counter() - t0
        rows.append(row)
        print(json.dumps(row), flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump({"load_average": list(os.getloadavg()), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
