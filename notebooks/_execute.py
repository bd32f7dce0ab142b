"""Execute ablation notebooks and save them with their outputs: the ``make notebooks`` job.

Run:  python notebooks/_execute.py [--scale cpu] [table6_partitions ...]
      (no names: every table*.py; ``cpu``: under an hour per table on a 2-core CPU)

Each ``notebooks/NAME.py`` (jupytext percent format, the source of truth) is read with
jupytext, run top to bottom by nbclient in a fresh ``python3`` kernel whose working folder is
``notebooks/`` and whose environment carries ``LLRMPP_NOTEBOOK_SCALE`` and the checkout's
``LLRMPP_NOTEBOOK_REVISION`` (``experiments/git_worktree.py``: the short commit, ``+dirty``
with uncommitted changes; the notebooks record it), then written to
``notebooks/NAME.ipynb`` with its outputs (tables, figures). The notebooks themselves write
their JSON and PNG results (``llrmpp_jax.ablation.save``). A cell that raises stops that notebook,
reports the cell and leaves its .ipynb untouched.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jupytext
import nbclient
import nbformat

HERE = os.path.dirname(os.path.abspath(__file__))
SCALES = ("smoke", "cpu", "paper")


def execute(name: str, scale: str, timeout_s: int = 3 * 3600) -> float:
    """Run ``notebooks/{name}.py`` at ``scale`` and write ``{name}.ipynb`` with outputs;
    returns the wall seconds."""
    source = os.path.join(HERE, name + ".py")
    if not os.path.isfile(source):
        raise FileNotFoundError(f"{source}: no such notebook")
    nb = jupytext.read(source, fmt="py:percent")
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    os.environ["LLRMPP_NOTEBOOK_SCALE"] = scale  # the kernel inherits this process's environment
    os.environ["LLRMPP_NOTEBOOK_REVISION"] = checkout_revision()
    os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    # The notebooks' tables and figures go to the repository's results (cited by notebooks/README.md).
    os.environ.setdefault(
        "LLRMPP_NOTEBOOK_OUT",
        os.path.join(
            os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments", "results", "ablations"
        ),
    )
    os.environ["LLRMPP_NOTEBOOK_ECHO"] = "1"  # progress lines also to this terminal (llrmpp_jax.ablation.progress)
    t0 = time.perf_counter()
    # Without fd capture the kernel's own stderr stays this terminal's, and the progress
    # echo does not land in the notebook a second time.
    nbclient.NotebookClient(
        nb,
        timeout=timeout_s,
        kernel_name="python3",
        extra_arguments=["--IPKernelApp.capture_fd_output=False"],
        resources={"metadata": {"path": HERE}},
    ).execute()
    nbformat.write(nb, os.path.join(HERE, name + ".ipynb"))
    return time.perf_counter() - t0


def checkout_revision() -> str:
    """``experiments/git_worktree.revision`` of this checkout (the scripts there may run git;
    the package does not)."""
    experiments = os.path.join(os.path.dirname(HERE), "experiments")
    if experiments not in sys.path:
        sys.path.append(experiments)
    from git_worktree import revision

    return revision()


def notebook_names() -> list[str]:
    """The ablation notebooks: every ``notebooks/table*.py``, by name, sorted."""
    return sorted(f[:-3] for f in os.listdir(HERE) if f.startswith("table") and f.endswith(".py"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="notebooks to run (default: every table*.py)")
    parser.add_argument("--scale", default="cpu", choices=SCALES, help="LLRMPP_NOTEBOOK_SCALE for the run")
    args = parser.parse_args()
    names = args.names or notebook_names()
    for name in names:
        print(f"{name}: running at the {args.scale} scale ...", flush=True)
        try:
            seconds = execute(name, args.scale)
        except nbclient.exceptions.CellExecutionError as err:
            sys.exit(f"{name}: a cell failed; {name}.ipynb left as it was\n{err}")
        print(f"{name}: done in {seconds / 60:.1f} min, wrote notebooks/{name}.ipynb", flush=True)


if __name__ == "__main__":
    main()
