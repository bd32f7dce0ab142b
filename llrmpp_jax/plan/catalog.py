"""The names of the programs a plan compiles and of their groups, importable without JAX
(the command line lists them in its help); :mod:`llrmpp_jax.plan.programs` builds each."""

PAPER_PROGRAMS = (
    "reconstruct_16",
    "reconstruct_32",
    "reconstruct_64",
    "render",
    "train_dl3dv_1",
    "train_dl3dv_2",
    "train_dl3dv_3",
    "train_dl3dv_4",
    "train_scannet_1",
    "train_scannet_2",
    "train_scannet_3",
)
TINY_PROGRAMS = ("tiny_reconstruct", "tiny_render", "tiny_train")
PROGRAM_NAMES = PAPER_PROGRAMS + TINY_PROGRAMS
GROUPS: dict[str, tuple[str, ...]] = {"paper": PAPER_PROGRAMS, "tiny": TINY_PROGRAMS}
