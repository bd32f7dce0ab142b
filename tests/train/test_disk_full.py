"""A disk that fills during a checkpoint save (simulated with a file-size limit,
``RLIMIT_FSIZE``): ``llrmpp train`` stops with one line and exit status 3, no traceback from
orbax's threads; the previous checkpoint survives and the next run resumes exactly."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import textwrap

import jax
import numpy as np

from llrmpp_jax.params_io import load_params

# A micro run (tiny model, 32x32 procedural scenes) that checkpoints every step.
_CONFIG = textwrap.dedent(
    """
    from dataclasses import replace

    from llrmpp_jax import config as C
    from llrmpp_jax.data.synthetic import ProceduralConfig
    from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig

    def get_config():
        model = replace(C.tiny(), head=C.GaussianHeadConfig(gaussians_per_token=2, feature_dim=8,
                                                               max_dist=8.0, scale_bias=-2.5))
        return ExperimentConfig(
            name="micro", model=model,
            stages=(StageConfig("s1", steps={steps}, global_batch=2, num_inputs=2, num_targets=1,
                                resize_h=32, square_crop=True, lr=1e-3, warmup_steps=1),),
            data=DataConfig(procedural=ProceduralConfig(height=32, width=32, num_frames=6),
                            num_eval_scenes=1, workers=1),
            perceptual_weight=0.0, log_every=1, eval_every=100, checkpoint_every=1,
        )
    """
)


def _train(tmp_path, workdir, steps: int, file_size_limit: int | None = None) -> subprocess.CompletedProcess:
    config = tmp_path / f"micro_{steps}.py"
    config.write_text(_CONFIG.format(steps=steps))

    def limit():
        if file_size_limit is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (file_size_limit, file_size_limit))

    # The runs share XLA's persistent cache: the three runs of 4 steps compile once.
    env = dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        JAX_COMPILATION_CACHE_DIR=str(tmp_path / "xla_cache"),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
    )
    # Output through pipes: a file-size limit does not apply to them.
    return subprocess.run(
        [sys.executable, "-m", "llrmpp_jax.cli", "train", "--config", str(config), "--workdir", str(workdir)],
        capture_output=True,
        text=True,
        env=env,
        preexec_fn=limit,
        timeout=600,
    )


def _file_size_limit(workdir) -> int:
    """A file-size limit the log, TensorBoard and checkpoint metadata files stay under, and
    the checkpoint's array data does not. Orbax splits the arrays into a number of files
    that varies with thread timing (1-4 here, 1.3-2.1 MB the largest); a sixteenth of their
    total is below the largest file of any split into at most 16."""
    files = [p for p in workdir.rglob("*") if p.is_file()]
    data = [p for p in files if "ocdbt.process_0" in p.parts and p.parent.name == "d"]
    newest = max(int(p.parts[p.parts.index("s1") + 1]) for p in data)
    limit = sum(p.stat().st_size for p in data if f"/s1/{newest}/" in str(p)) // 16
    others = max(p.stat().st_size for p in files if p not in data)
    assert limit > 2 * others, (limit, others)  # the other files (and the log growing) still fit
    return limit


def test_a_full_disk_during_a_save_is_one_line_and_the_run_resumes_exactly(tmp_path):
    ref, run = tmp_path / "uninterrupted", tmp_path / "run"
    assert _train(tmp_path, ref, 4).returncode == 0
    assert _train(tmp_path, run, 2).returncode == 0

    res = _train(tmp_path, run, 4, file_size_limit=_file_size_limit(run))
    assert res.returncode == 3, res.stderr  # out of space, not a bad config (2)
    assert "Traceback" not in res.stderr and "ERROR:absl" not in res.stderr, res.stderr
    errors = [line for line in res.stderr.splitlines() if line.startswith("llrmpp: error:")]
    assert len(errors) == 1, res.stderr
    assert "checkpoint step 3 not saved" in errors[0] and "File too large" in errors[0], errors[0]
    assert "the newest complete checkpoint (step 2) is intact" in errors[0], errors[0]
    stage_dir = next((run / "checkpoints").iterdir())
    assert sorted(p.name for p in stage_dir.iterdir()) == ["1", "2"]  # nothing half-written

    assert _train(tmp_path, run, 4).returncode == 0
    resumed, _ = load_params(str(run))
    expected, _ = load_params(str(ref))
    jax.tree.map(np.testing.assert_array_equal, resumed, expected)
