"""The paper's global attention at stage-4 size through the Pallas splash kernel, compiled for
TPU chips from this CPU: does it fit, how long it compiles, what it costs.

One row per (target, forward or gradient): q, k, v ``[1, 261122, 12, 64]`` bf16 (32 inputs +
8 targets at 544x960, ``experiments/cost_table.py``'s global-attention piece) through
``multi_head_attention(..., implementation="splash")`` (512 x 512 blocks: L padded to
261,632, the padded keys removed by segment ids); the gradient is of the output's sum, w.r.t.
q, k, v. Each compile runs in its own process under ``--limit`` seconds.

Per row: ``compiled``; ``hbm_bytes`` (arguments + temp + outputs - aliases) against the chip's
``hbm_available_bytes`` and ``fits``; ``compile_s``; ``estimate`` (``llrmpp_jax.plan.hlo_cost``:
per-op rooflines, the splash kernels given their matrix products over the padded length, as
they carry no ``pl.CostEstimate``); ``xla_flops`` / ``xla_optimal_seconds`` (libtpu's
``cost_analysis()``, which counts a Pallas kernel only by its ``pl.CostEstimate``: splash's
FLOPs are missing there); ``model_flops`` (the products on the unpadded L: 4 x nh x L^2 x hd
forward, 3.5x that more for the backward kernels' 14) and ``matmul_limit_s`` = model FLOPs /
the chip's bf16 peak.

Run (libtpu installed: ``pip install -e '.[tpu]'``):
    JAX_PLATFORMS=cpu python experiments/plan_splash_attention.py --targets v5p,v6e --limit 900 \\
        --out experiments/results/plan_splash_attention.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

L, NH, HD = 261_122, 12, 64  # stage-4 backbone tokens, heads, head dim (config.paper_dl3dv())


def _one(target: str, grad: bool) -> dict:
    """Compile one row's program in this process; its row."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from llrmpp_jax.nn.attention import multi_head_attention
    from llrmpp_jax.plan import targets
    from llrmpp_jax.plan.hlo_cost import estimate_hlo
    from llrmpp_jax.plan.planner import chip_model

    t = targets.target(target)
    mesh = Mesh(np.asarray(targets.compile_devices(t)[:1]), ("batch",))
    sds = jax.ShapeDtypeStruct((1, L, NH, HD), jnp.bfloat16, sharding=NamedSharding(mesh, PartitionSpec()))
    fn = lambda q, k, v: multi_head_attention(q, k, v, implementation="splash")  # noqa: E731
    if grad:
        forward = fn
        fn = jax.grad(lambda q, k, v: jnp.sum(forward(q, k, v).astype(jnp.float32)), argnums=(0, 1, 2))
    t0 = time.perf_counter()
    with jax.numpy_dtype_promotion("standard"):
        compiled = jax.jit(fn).lower(sds, sds, sds).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    need = (
        mem.argument_size_in_bytes + mem.temp_size_in_bytes + mem.output_size_in_bytes - mem.alias_size_in_bytes  # pyright: ignore[reportOptionalMemberAccess] -- the TPU compiler reports memory
    )
    ca = compiled.cost_analysis() or {}
    ca = ca[0] if isinstance(ca, list) else ca
    model_flops = 4.0 * NH * L * L * HD * (1 + (3.5 if grad else 0))
    return {
        "target": target,
        "program": "global_attention_grad" if grad else "global_attention",
        "shape": [1, L, NH, HD],
        "dtype": "bfloat16",
        "compiled": True,
        "hbm_bytes": need,
        "hbm_available_bytes": t.hbm_bytes,
        "fits": need <= t.hbm_bytes,
        "temp_bytes": mem.temp_size_in_bytes,  # pyright: ignore[reportOptionalMemberAccess] -- as above
        "compile_s": compile_s,
        "tpu_custom_calls": compiled.as_text().count('custom_call_target="tpu_custom_call"'),  # pyright: ignore[reportOptionalMemberAccess] -- a compiled program has HLO text
        "estimate": estimate_hlo(compiled.as_text(), chip_model(target)).to_json(),  # pyright: ignore[reportArgumentType] -- as above
        "xla_flops": ca.get("flops"),
        "xla_optimal_seconds": ca.get("optimal_seconds"),
        "model_flops": model_flops,
        "matmul_limit_s": model_flops / t.peak_flops,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--targets", default="v5p,v6e", help="comma-separated llrmpp_jax.plan targets (one chip)")
    parser.add_argument("--modes", default="fwd,grad", help="fwd, grad or both")
    parser.add_argument("--limit", type=float, default=900.0, help="seconds one compile may take")
    parser.add_argument("--out", default=None, help="JSON file of the rows (rewritten after each)")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: TARGET:MODE compiled here
    args = parser.parse_args()
    if args.one:
        target, mode = args.one.split(":")
        print(json.dumps(_one(target, mode == "grad")))
        return
    rows = []
    for target in args.targets.split(","):
        for mode in args.modes.split(","):
            cmd = [sys.executable, __file__, "--one", f"{target}:{mode}"]
            t0 = time.perf_counter()
            try:
                done = subprocess.run(
                    cmd, capture_output=True, text=True, timeout=args.limit, env={**os.environ, "JAX_PLATFORMS": "cpu"}
                )
                lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
                row = json.loads(lines[-1]) if lines else {"compiled": False, "error": done.stderr.strip()[-2000:]}
            except subprocess.TimeoutExpired:
                row = {"compiled": False, "not_compiled_within_s": args.limit}
            row = {"target": target, "mode": mode, **row, "wall_s": time.perf_counter() - t0}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.out:
                with open(args.out, "w") as f:
                    json.dump(
                        {"command": " ".join(sys.argv), "load_average": list(os.getloadavg()), "rows": rows},
                        f,
                        indent=1,
                    )


if __name__ == "__main__":
    main()
