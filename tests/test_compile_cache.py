"""The persistent compilation cache (``llrmpp_jax.compile_cache``): a cached executable computes
what a fresh compile computes; a broken, foreign or unwritable cache costs time, never a result
or a crash; two processes share a folder; the size cap keeps the most recently used entries."""

import os
import subprocess
import sys
import textwrap
from dataclasses import replace

import jax
import numpy as np
import optax
import pytest

from llrmpp_jax import compile_cache
from llrmpp_jax import config as C
from llrmpp_jax.cli import main
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.objective import objective
from tests.helpers.scenes import orbit_batch


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """A fresh cache folder for this test; the suite's folder is back afterwards."""
    monkeypatch.setattr(compile_cache, "_warned", type(compile_cache._warned)())
    yield tmp_path / "xla"
    compile_cache.enable()
    jax.clear_caches()


def _programs(key):
    """The tiny model's reconstruct, render and one SGD-with-momentum train step, jitted, with their inputs."""
    cfg = replace(C.tiny(), outputs=("rgb", "depth"))
    batch = orbit_batch(key, 2, 1, 32, depth=True)
    params = init_params(jax.random.fold_in(key, 1), cfg, 2, 32, 32)
    tx = optax.sgd(1e-3, momentum=0.9)  # (adam's bias correction mixes int32 and float under strict promotion)

    def rec(p):
        return reconstruct(p, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])

    def ren(p):
        return render(p, cfg, rec(p), batch["target_c2w"], batch["target_intrinsics"], 32, 32, ("rgb", "depth")).images

    def step(p, opt):
        loss, grads = jax.value_and_grad(lambda q: objective(q, cfg, batch, key)[0])(p)
        updates, opt = tx.update(grads, opt, p)
        return optax.apply_updates(p, updates), opt, loss

    return {
        "reconstruct": lambda: jax.jit(rec)(params),
        "render": lambda: jax.jit(ren)(params),
        "train step": lambda: jax.jit(step)(params, tx.init(params)),
    }


def _run_all(programs) -> tuple[dict, compile_cache.CompileWatch]:
    jax.clear_caches()  # the in-memory caches: the next call compiles, or loads from disk
    with compile_cache.CompileWatch() as watch:
        out = {name: jax.tree.map(np.asarray, fn()) for name, fn in programs.items()}
    return out, watch


def _assert_same(a, b) -> None:
    for name in a:
        for x, y in zip(jax.tree.leaves(a[name]), jax.tree.leaves(b[name]), strict=True):
            np.testing.assert_array_equal(x, y, err_msg=name)  # the same executable: bit for bit


def test_a_cached_executable_gives_what_a_fresh_compile_gives(own_cache, key):
    programs = _programs(key)
    assert compile_cache.enable(str(own_cache)).enabled
    fresh, watch = _run_all(programs)  # compiled, and written
    assert watch.programs > 0 and watch.hits == 0
    assert compile_cache.usage(compile_cache.state().path)[0] >= watch.programs  # pyright: ignore[reportArgumentType]
    loaded, watch = _run_all(programs)
    assert watch.hits == watch.programs > 0, "every program of the second run comes from the cache"
    assert "from the compile cache" in watch.describe(1.0)
    _assert_same(fresh, loaded)


def test_a_corrupt_entry_is_one_warning_and_is_replaced(own_cache, key, capsys):
    programs = {"reconstruct": _programs(key)["reconstruct"]}
    folder = compile_cache.enable(str(own_cache)).path
    assert folder is not None
    want, _ = _run_all(programs)
    entries = sorted(os.listdir(folder))
    for name in entries:  # truncated, as a killed writer leaves it, or garbage
        path = os.path.join(folder, name)
        data = open(path, "rb").read()
        open(path, "wb").write(data[: len(data) // 2] if len(data) > 100 else b"not an executable")
    capsys.readouterr()
    got, watch = _run_all(programs)
    _assert_same(want, got)
    assert watch.hits == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("llrmpp: warning: compile cache ") and "compiled afresh" in err[0], err
    again, watch = _run_all(programs)  # the broken entries were replaced by the fresh compiles
    _assert_same(want, again)
    assert watch.hits == watch.programs


def test_entries_of_another_jax_or_machine_are_never_looked_up(own_cache, key, monkeypatch):
    programs = {"reconstruct": _programs(key)["reconstruct"]}
    monkeypatch.setattr(compile_cache, "machine_tag", lambda: "jax-0.0.1_jaxlib-0.0.1_riscv64_0123456789")
    foreign = compile_cache.enable(str(own_cache)).path
    want, _ = _run_all(programs)
    monkeypatch.undo()
    folder = compile_cache.enable(str(own_cache)).path
    assert folder is not None and foreign is not None and folder != foreign and os.listdir(foreign)
    for name in os.listdir(foreign):  # and junk beside this machine's entries
        open(os.path.join(folder, "jit_junk-" + name), "wb").write(os.urandom(64))
    got, watch = _run_all(programs)
    assert watch.hits == 0 and watch.programs > 0
    _assert_same(want, got)


def test_an_unwritable_folder_is_one_warning_and_the_command_runs(tmp_path, capsys, own_cache):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    status = main(
        [
            "export",
            "--compile-cache",
            str(blocker / "xla"),
            "--gaussians",
            str(tmp_path / "no.gs"),
            "--ply",
            str(tmp_path / "x.ply"),
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 2, err
    assert err[0].startswith(f"llrmpp: warning: compile cache {blocker / 'xla'}") and "running uncached" in err[0]
    assert err[1].startswith("llrmpp: error: ") and "no.gs" in err[1]  # the command's own check ran
    assert not compile_cache.state().enabled


def test_a_failing_write_is_one_warning_line(own_cache, key, capsys, monkeypatch):
    from jax._src import lru_cache

    def full(self, key, value):
        raise OSError(28, "No space left on device")

    programs = _programs(key)
    monkeypatch.setattr(lru_cache.LRUCache, "put", full)
    compile_cache.enable(str(own_cache))
    capsys.readouterr()
    _run_all(programs)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "No space left on device" in err[0], err


def test_the_cli_turns_it_on_and_off(own_cache, tmp_path, capsys):
    main(
        [
            "export",
            "--compile-cache",
            str(own_cache),
            "--gaussians",
            str(tmp_path / "no.gs"),
            "--ply",
            str(tmp_path / "x.ply"),
        ]
    )
    st = compile_cache.state()
    assert st.enabled and st.reason == "flag" and st.path.startswith(str(own_cache))  # pyright: ignore[reportOptionalMemberAccess]
    main(["export", "--no-compile-cache", "--gaussians", str(tmp_path / "no.gs"), "--ply", str(tmp_path / "x.ply")])
    assert not compile_cache.state().enabled and "--no-compile-cache" in compile_cache.state().reason
    main(
        ["export", "--gaussians", str(tmp_path / "no.gs"), "--ply", str(tmp_path / "x.ply")]
    )  # the default: the environment's folder
    assert compile_cache.state().reason == "JAX_COMPILATION_CACHE_DIR"
    assert main(["plan", "--programs", "no_such_program"]) == 2  # plan measures compile time: off unless asked
    assert not compile_cache.state().enabled and "measures compile time" in compile_cache.state().reason
    capsys.readouterr()


_WRITER = textwrap.dedent(
    """
    import sys, jax, jax.numpy as jnp
    from llrmpp_jax import compile_cache
    assert compile_cache.enable(sys.argv[1]).enabled
    with compile_cache.CompileWatch() as w:
        for n in range(2, 14):  # a dozen programs, the same in both processes
            x = jax.jit(lambda a: jnp.tanh(a @ a.T).sum(axis=0))(jnp.ones((n, 24), jnp.float32))
            assert float(x[0]) > 0
    print(w.programs, w.hits)
    """
)


def test_two_processes_writing_one_folder_at_once(own_cache):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(own_cache)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err.decode()
        assert b"Traceback" not in err
    third = subprocess.run(
        [sys.executable, "-c", _WRITER, str(own_cache)], env=env, capture_output=True, text=True, timeout=300
    )
    programs, hits = map(int, third.stdout.split())
    assert third.returncode == 0 and hits == programs >= 12, third.stderr


def test_trim_keeps_the_most_recently_used(tmp_path):
    rng = np.random.default_rng(3)
    sizes = rng.integers(100, 1000, size=12)
    used = rng.permutation(12) * 100.0 + 1e6
    for i, (size, t) in enumerate(zip(sizes, used)):
        path = tmp_path / f"jit_f{i}-{i:04x}-cache"
        path.write_bytes(b"x" * int(size))
        os.utime(path, (t, t))
    cap = int(sizes.sum() // 2)
    freed = compile_cache.trim(str(tmp_path), cap)
    # oracle: walk from the newest, keeping entries while the total fits
    order = np.argsort(-used)
    keep, total = set(), 0
    for i in order:
        if total + sizes[i] > cap:
            break
        keep.add(int(i))
        total += int(sizes[i])
    left = {int(p.name.split("-")[0][5:]) for p in tmp_path.iterdir()}
    assert left == keep and freed == int(sizes.sum()) - total
