"""``llrmpp doctor``: does this install compute the right numbers on this device?

Prints the versions, backend, devices and default matmul precision, then runs small
checks of the fast kernels against their independent references on the default device
(with the device's default matmul precision, which is the point: a GPU's TF32 default
or a new backend shows up here as a failed check):

* ``scan``      -- chunked SSD (:func:`ssd_scan`, the batched and the fused forms) vs the
  sequential recurrence, float32.
* ``splat``     -- tiled splatter (:func:`~llrmpp_jax.splat.rasterize`) vs the brute-force renderer.
* ``attention`` -- blockwise attention vs plain ``jax.nn.dot_product_attention``,
  forward and gradients of q, k, v, with uneven blocks and a mask.
* ``model``     -- a tiny model's forward (reconstruct + render) is finite.

Each check returns its error (max abs difference over max abs reference; for ``model``
the count of non-finite outputs) and passes at ``error <= tolerance``. A check that fails
at the default precision is run once more at matmul precision ``"highest"`` and the line
under it says which it is: a kernel that is wrong, or a device whose default matmul
precision costs float32 accuracy (an NVIDIA GPU's default TF32 matmuls;
``JAX_DEFAULT_MATMUL_PRECISION=highest`` restores float32; docs/accelerators.md).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax import compile_cache
from llrmpp_jax.compile_cache import CompileWatch


@dataclasses.dataclass(frozen=True)
class CheckResult:
    name: str
    error: float
    tolerance: float
    seconds: float

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.error)) and self.error <= self.tolerance

    def line(self) -> str:
        verdict = "ok  " if self.ok else "FAIL"
        return (
            f"{verdict} {self.name:<10} error {self.error:.2e} (tolerance {self.tolerance:.0e}) {self.seconds:5.1f} s"
        )


def _rel(got, want) -> float:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return float(np.max(np.abs(got - want)) / max(float(np.max(np.abs(want))), 1e-30))


def check_scan() -> float:
    """Chunked SSD scan vs the sequential recurrence (L=300, chunk 64: a ragged last chunk);
    the larger error of the batched (``"associative"``) and the ``"fused"`` forms."""
    from llrmpp_jax.nn.ssd import ssd_scan, ssd_sequential

    r = np.random.default_rng(0)
    L, nh, p, n = 300, 4, 8, 16
    x = jnp.asarray(r.normal(size=(1, L, nh, p)), jnp.float32)
    dt = jnp.asarray(r.uniform(0.01, 0.2, size=(1, L, nh)), jnp.float32)
    a = jnp.asarray(-r.uniform(0.5, 2.0, size=nh), jnp.float32)
    b, c = (jnp.asarray(r.normal(size=(1, L, 1, n)), jnp.float32) for _ in range(2))
    d = jnp.asarray(r.normal(size=nh), jnp.float32)
    want = jax.jit(lambda *a_: ssd_sequential(*a_, D=d))(x, dt, a, b, c)
    return max(
        _rel(jax.jit(lambda *a_, m=m: ssd_scan(*a_, chunk_size=64, D=d, inter_chunk=m))(x, dt, a, b, c), want)
        for m in ("associative", "fused")
    )


def check_splat() -> float:
    """Tiled splatter vs the brute-force O(N x pixels) renderer: 300 Gaussians, 48x40 canvas."""
    from llrmpp_jax.splat import rasterize
    from llrmpp_jax.splat.reference import render_features_reference

    r = np.random.default_rng(1)
    n, h, w = 300, 40, 48
    z = r.uniform(1.5, 5.0, n)
    means = np.stack([r.uniform(-0.5, 0.5, n) * z, r.uniform(-0.4, 0.4, n) * z, z], -1)
    args = [
        jnp.asarray(a, jnp.float32)
        for a in (
            means,
            r.normal(size=(n, 4)),
            np.exp(r.uniform(-4.5, -2.5, (n, 3))) * z[:, None],
            r.uniform(0.1, 0.9, n),
            r.normal(size=(n, 3)),
            np.eye(4),
            [w, w, w / 2, h / 2],
        )
    ]
    got = rasterize(*args, h, w)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    want = jax.jit(render_features_reference, static_argnums=(7, 8))(*args, h, w)
    return max(_rel(got.features, want[0]), _rel(got.transmittance, want[1]))


def check_attention() -> float:
    """Blockwise vs plain attention, forward and q/k/v gradients (L=300, blocks 64 x 48)."""
    from llrmpp_jax.nn.blockwise_attention import blockwise_attention

    r = np.random.default_rng(2)
    q, k, v, cot = (jnp.asarray(r.normal(size=(1, 300, 2, 32)), jnp.float32) for _ in range(4))
    mask = jnp.asarray(r.random((1, 1, 300, 300)) > 0.2)

    def vjp(fn, q, k, v, cot, mask):
        out, back = jax.vjp(lambda q, k, v: fn(q, k, v, mask), q, k, v)
        return (out, *back(cot))

    def blocked(q, k, v, mask):
        return blockwise_attention(q, k, v, mask=mask, block_q=64, block_k=48)

    def plain(q, k, v, mask):
        return jax.nn.dot_product_attention(q, k, v, mask=mask)

    run = jax.jit(vjp, static_argnums=0)
    got, want = run(blocked, q, k, v, cot, mask), run(plain, q, k, v, cot, mask)
    return max(_rel(g, w) for g, w in zip(got, want))


def check_model() -> float:
    """Number of non-finite values in a tiny model's rendered views (2 inputs, 32x32)."""
    from llrmpp_jax import config as C
    from llrmpp_jax.model import init_params, reconstruct, render

    cfg = C.tiny()
    h = w = 32
    r = np.random.default_rng(3)
    images = jnp.asarray(r.uniform(size=(1, 2, h, w, 3)), jnp.float32)
    c2w = np.broadcast_to(np.eye(4), (1, 2, 4, 4)).copy()
    c2w[0, 1, 0, 3] = 0.1  # a small baseline between the two views
    c2w = jnp.asarray(c2w, jnp.float32)
    intr = jnp.asarray(np.broadcast_to([w, w, w / 2, h / 2], (1, 2, 4)), jnp.float32)

    def forward(key, images, c2w, intr):
        p = init_params(key, cfg, 2, h, w)
        return render(p, cfg, reconstruct(p, cfg, images, c2w, intr), c2w, intr, h, w).images["rgb"]

    rgb = jax.jit(forward)(jax.random.key(0), images, c2w, intr)
    return float(np.sum(~np.isfinite(np.asarray(rgb))))


# name -> (check, tolerance). float32 checks: a correct float32 kernel is within ~1e-6 of
# its reference here; 1e-4 leaves room for reassociation on other backends while a
# reduced-precision (TF32 / bf16) matmul default, ~1e-3, fails.
CHECKS: dict[str, tuple[Callable[[], float], float]] = {
    "scan": (check_scan, 1e-4),
    "splat": (check_splat, 1e-4),
    "attention": (check_attention, 1e-4),
    "model": (check_model, 0.0),
}


def environment_lines() -> list[str]:
    """Versions, backend, devices and the default matmul precision, one per line."""
    from llrmpp_jax.benchmarks.measure import environment

    env = environment()
    return [
        "versions: " + ", ".join(f"{k} {v or '(not installed)'}" for k, v in env["versions"].items()),
        f"backend: {env['backend']}",
        "devices: " + ", ".join(f"{d} ({d.device_kind})" for d in jax.devices()),
        f"default matmul precision: {env['default_matmul_precision']}",
    ]


def cache_line(watch: CompileWatch | None = None) -> str:
    """Where the persistent compilation cache is, how much it holds, and (with ``watch``, a
    :class:`~llrmpp_jax.compile_cache.CompileWatch` over this run) how many programs came from it."""
    st = compile_cache.state()
    if st.path is None:
        return f"compile cache: {st.reason}"
    entries, size = compile_cache.usage(st.path)
    line = f"compile cache: {st.path} ({st.reason}): {entries} programs, {size / 2**20:.1f} MiB"
    if watch is not None:
        line += f"; this run loaded {watch.hits} of {watch.programs} programs from it"
    return line


def precision_diagnosis(name: str, fn: Callable[[], float], tol: float) -> str:
    """Rerun a failed check at matmul precision ``"highest"``; one line saying whether the
    kernel or the device's default precision is to blame."""
    with jax.default_matmul_precision("highest"):
        err = float(fn())
    if np.isfinite(err) and err <= tol:
        return (
            f"{name}: error {err:.2e} at matmul precision 'highest': the kernel is right; this device's "
            "default matmul precision loses float32 accuracy (set JAX_DEFAULT_MATMUL_PRECISION=highest "
            "for float32 work)"
        )
    return f"{name}: error {err:.2e} at matmul precision 'highest' too: the kernel is wrong on this device"


def run_checks(emit: Callable[[str], None] = print) -> list[CheckResult]:
    """Print the environment, then run every check in :data:`CHECKS`, printing one line
    each as it finishes. A check that raises counts as failed (error ``nan``)."""
    for line in environment_lines():
        emit(line)
    with CompileWatch() as watch:
        results = _run_each(emit)
    emit(cache_line(watch))
    failed = [r.name for r in results if not r.ok]
    emit(f"doctor: {'all checks passed' if not failed else 'FAILED: ' + ', '.join(failed)}")
    return results


def _run_each(emit: Callable[[str], None]) -> list[CheckResult]:
    results = []
    for name, (fn, tol) in CHECKS.items():
        t0 = time.perf_counter()
        try:
            err = float(fn())
        except Exception as e:  # a crashing kernel is a failed check, reported, not a traceback
            emit(f"     {name}: raised {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
            err = float("nan")
        res = CheckResult(name, err, tol, time.perf_counter() - t0)
        emit(res.line())
        if not res.ok and np.isfinite(err) and tol > 0 and jax.config.jax_default_matmul_precision != "highest":  # pyright: ignore[reportAttributeAccessIssue] -- jax.config's options are made at run time; its stub lists none
            emit("     " + precision_diagnosis(name, fn, tol))
        results.append(res)
    return results
