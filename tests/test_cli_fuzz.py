"""Property-based fuzzing of the command line (hypothesis): for each verb, generated flag
values (negative, zero, huge, NaN, empty, not numbers, odd text) and generated broken files
(cut short, wrong leading bytes, random bytes, NaN or infinity in arrays of the right shapes,
wrong shapes, a photo or text where an archive belongs, broken captures) must end in exit
status 0 or 2 with one ``error:`` line last on stderr and a few lines at most (a parser error
is one line too; a warning may precede the error), never a traceback (``main`` raising anything but
``SystemExit``), and nothing written under the example's output paths.

Every example has at least one broken input, so every command is refused before it compiles
or trains (a run that got further would take minutes: the property is about the error
paths). Derandomized (the same examples every run); hypothesis prints the failing example.
Settings and what the first runs found: ``docs/lab-notes.md`` (2026-12-02).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.bad_inputs import run_cli, tiny_capture, write_gs, write_photo

EXAMPLES = 75  # per verb
MAX_STDERR_LINES = 3  # the error line, and a warning or two before it (a compile cache, missing thumbnails)
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    print_blob=True,
)

# ------------------------------------------------------------------ flag values

ODD_TEXT = [
    "",
    " ",
    "nan",
    "-nan",
    "inf",
    "-inf",
    "1e3",
    "0x10",
    "abc",
    "1,2",
    "256x0",
    "0x0",
    "x",
    "9" * 5000,
    "-0",
    "1_0",
    "\u00bd",
    "\x00",
    "a\nb",
]
NUMBER = st.one_of(
    st.integers(-3, 3).map(str),
    st.integers(-(2**70), 2**70).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(ODD_TEXT),
    st.text(max_size=6),
)
TEXT = st.one_of(st.sampled_from(ODD_TEXT), st.text(max_size=10))
SIZE = st.one_of(NUMBER, st.tuples(NUMBER, NUMBER).map("x".join))
LIST = st.one_of(NUMBER, st.lists(NUMBER, max_size=4).map(",".join))


def _flags(options: dict[str, st.SearchStrategy[str]]) -> st.SearchStrategy[list[str]]:
    """Up to 4 of ``options``, each as ``--flag=value`` (so that a value starting with ``-``
    is not read as another flag)."""
    names = sorted(options)
    if not names:
        return st.just([])
    return st.lists(st.sampled_from(names), unique=True, max_size=4).flatmap(
        lambda chosen: st.tuples(*(options[n] for n in chosen)).map(
            lambda values: [f"{n}={v}" for n, v in zip(chosen, values)]
        )
    )


CAPTURE_FLAGS = {
    "--num-inputs": NUMBER,
    "--inputs": LIST,
    "--size": SIZE,
    "--repeats": NUMBER,
    "--format": TEXT,
}
POSES_FLAGS = {
    "--fps": NUMBER,
    "--max-image-size": NUMBER,
    "--threads": NUMBER,
    "--seed": NUMBER,
    "--matcher": TEXT,
    "--camera-model": TEXT,
}

# ------------------------------------------------------------------ broken files, as recipes
# A recipe is a tuple drawn by hypothesis (so the failing example prints it) and written into
# the example's folder by _materialise.

GS_FIELDS = ("means", "quats", "scales", "opacities", "features", "c2w", "intrinsics", "world_from_scene")
BAD_FLOATS = st.sampled_from([float("nan"), float("inf"), float("-inf")])
BROKEN_GS = st.one_of(
    st.tuples(st.just("cut"), st.floats(0.0, 0.999)),
    st.tuples(st.just("bytes"), st.binary(max_size=512)),
    st.tuples(st.just("magic"), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("non_finite"), st.sampled_from(GS_FIELDS), BAD_FLOATS, st.floats(0.01, 1.0)),
    st.tuples(st.just("shape"), st.sampled_from((*GS_FIELDS, "inputs", "targets"))),
    st.tuples(st.just("header"), st.sampled_from([b"", b"{}", b"[]", b"null", b'{"format": 1}', b"\xff\xfe"])),
    st.tuples(st.just("photo")),
    st.tuples(st.just("text"), st.text(max_size=40)),
    st.tuples(st.just("folder")),
    st.tuples(st.just("missing")),
)
BROKEN_FILE = st.one_of(  # where a .pt/.npz/.json/.py or a video belongs
    st.tuples(st.just("bytes"), st.binary(max_size=512)),
    st.tuples(st.just("photo")),
    st.tuples(st.just("text"), st.text(max_size=40)),
    st.tuples(st.just("cut_gs"), st.floats(0.0, 0.999)),
    st.tuples(st.just("zip")),
    st.tuples(st.just("npz_objects")),
    st.tuples(st.just("folder")),
    st.tuples(st.just("missing")),
)
JSON = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=8,
)
BROKEN_CAPTURE = st.one_of(
    st.tuples(st.just("transforms_bytes"), st.binary(max_size=256)),
    st.tuples(st.just("transforms_json"), JSON),
    st.tuples(st.just("transforms_top"), st.sampled_from(["frames", "camera_model"]), JSON),
    st.tuples(st.just("pose"), st.integers(0, 5), st.integers(0, 11), BAD_FLOATS),
    st.tuples(st.just("focal"), st.sampled_from([0.0, -1.0, float("nan"), float("inf")])),
    st.tuples(st.just("image"), st.integers(0, 5), st.sampled_from(["text", "empty", "cut", "random", "nan_exr"])),
    st.tuples(st.just("no_frames")),
    st.tuples(st.just("empty_folder")),
    st.tuples(st.just("photo")),
)
BROKEN_FOLDER = st.one_of(  # where a checkpoint folder belongs
    st.tuples(st.just("params_meta"), st.binary(max_size=64)),
    st.tuples(st.just("params_json"), JSON),
    st.tuples(st.just("empty_folder")),
    BROKEN_FILE,
)
BROKEN_PHOTOS = st.lists(st.sampled_from(["text", "empty", "random", "header_only"]), max_size=5)


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    """The valid files the broken ones are made from: a .gs, a photo and a nerfstudio capture
    of 6 frames of 32x48 (PNG)."""
    d = tmp_path_factory.mktemp("valid")
    rng = np.random.default_rng(0)
    return {
        "gs": write_gs(str(d / "ok.gs"), rng),
        "photo": write_photo(str(d / "photo.jpg"), rng),
        "capture": tiny_capture(str(d / "capture"), rng),
    }


def _write_file(recipe: tuple, path: str, valid: dict) -> str:
    kind = recipe[0]
    if kind == "bytes":
        open(path, "wb").write(recipe[1])
    elif kind == "photo":
        shutil.copy(valid["photo"], path)
    elif kind == "text":
        open(path, "w", encoding="utf-8", errors="surrogatepass").write(recipe[1])
    elif kind == "cut_gs":
        data = open(valid["gs"], "rb").read()
        open(path, "wb").write(data[: int(len(data) * recipe[1])])
    elif kind == "zip":
        import zipfile

        with zipfile.ZipFile(path, "w") as z:
            z.writestr("data.txt", "hello")
    elif kind == "npz_objects":
        with open(path, "wb") as f:
            np.savez(f, a=np.array([{"x": 1}], dtype=object))
    elif kind == "folder":
        os.makedirs(path)
    elif kind == "empty_folder":
        os.makedirs(path)
    elif kind != "missing":
        raise AssertionError(recipe)
    return path


def _write_gs(recipe: tuple, path: str, valid: dict) -> str:
    kind = recipe[0]
    if kind in ("bytes", "photo", "text", "folder", "missing"):
        return _write_file(recipe, path, valid)
    data = open(valid["gs"], "rb").read()
    if kind == "cut":
        open(path, "wb").write(data[: int(len(data) * recipe[1])])
        return path
    if kind == "magic":
        open(path, "wb").write(recipe[1] + data[len(recipe[1]) :])
        return path
    with np.load(valid["gs"]) as z:
        arrays = {k: z[k] for k in z.files}
    if kind == "non_finite":
        _, field, value, frac = recipe
        a = arrays[field].astype(np.float64).copy()
        a.reshape(-1)[: max(1, int(a.size * frac))] = value
        arrays[field] = a
    elif kind == "shape":
        a = arrays[recipe[1]]
        arrays[recipe[1]] = a.reshape(-1)[:-1] if a.ndim <= 1 else a[:-1]
    elif kind == "header":
        arrays["header"] = np.frombuffer(recipe[1], np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **arrays)  # pyright: ignore[reportArgumentType] -- arrays by keyword
    return path


def _write_capture(recipe: tuple, path: str, valid: dict) -> str:
    kind = recipe[0]
    if kind == "empty_folder":
        os.makedirs(path)
        return path
    if kind == "photo":
        return _write_file(recipe, path, valid)
    shutil.copytree(valid["capture"], path)
    tj = os.path.join(path, "transforms.json")
    meta = json.load(open(tj))
    if kind == "transforms_bytes":
        open(tj, "wb").write(recipe[1])
        return path
    if kind == "transforms_json":
        meta = recipe[1]
    elif kind == "transforms_top":
        meta[recipe[1]] = recipe[2]
    elif kind == "pose":
        _, frame, entry, value = recipe
        meta["frames"][frame]["transform_matrix"][entry // 4][entry % 4] = value
    elif kind == "focal":
        for fr in [meta, *meta["frames"]]:
            if "fl_x" in fr:
                fr["fl_x"] = recipe[1]
    elif kind == "no_frames":
        meta["frames"] = []
    elif kind == "image":
        _, frame, how = recipe
        image = os.path.join(path, meta["frames"][frame]["file_path"])
        data = open(image, "rb").read()
        if how == "nan_exr":
            from llrmpp_jax.data.image_io import write_image

            exr = os.path.splitext(image)[0] + ".exr"
            write_image(exr, np.full((32, 48, 3), np.nan, np.float32), bits=32)
            meta["frames"][frame]["file_path"] = os.path.relpath(exr, path)
        else:
            content = {"text": b"not a photo\n", "empty": b"", "cut": data[:60], "random": bytes(range(256))}
            open(image, "wb").write(content[how])
    json.dump(meta, open(tj, "w"), allow_nan=True)
    return path


def _write_folder(recipe: tuple, path: str, valid: dict) -> str:
    kind = recipe[0]
    if kind == "params_meta":
        os.makedirs(path)
        open(os.path.join(path, "llrmpp_params.json"), "wb").write(recipe[1])
        return path
    if kind == "params_json":
        os.makedirs(path)
        json.dump(recipe[1], open(os.path.join(path, "llrmpp_params.json"), "w"))
        return path
    return _write_file(recipe, path, valid)


def _write_photos(kinds: list[str], path: str) -> str:
    os.makedirs(path)
    content = {"text": b"not a photo\n", "empty": b"", "random": bytes(range(256)) * 4, "header_only": b"\xff\xd8\xff"}
    for i, k in enumerate(kinds):
        open(os.path.join(path, f"{i}.jpg"), "wb").write(content[k])
    return path


# ------------------------------------------------------------------ one strategy per verb
# Each gives (argv with {in}/{out} placeholders, {name: (writer, recipe)} of the files to make).

IN, OUT = "{in}", "{out}"


def _verb(fixed: st.SearchStrategy, files: dict[str, tuple], flags: dict) -> st.SearchStrategy:
    recipes = st.fixed_dictionaries({name: strategy for name, (_, strategy) in files.items()})
    writers = {name: writer for name, (writer, _) in files.items()}
    return st.tuples(fixed, recipes, _flags(flags)).map(
        lambda t: (t[0] + t[2], {n: (writers[n], r) for n, r in t[1].items()})
    )


GS = {"gs": (_write_gs, BROKEN_GS)}
# a capture reconstructed by the shipped model (2 inputs: the capture has 6 frames)
FROM_CAPTURE = ["--scene", IN + "capture", "--checkpoint", "pretrained:small", "--num-inputs=2", "--out", OUT]
STRATEGIES = {
    "render": st.one_of(
        _verb(
            st.just(["render", "--gaussians", IN + "gs", "--out", OUT]),
            GS,
            {"--path": TEXT, "--frames": NUMBER, "--fps": NUMBER, "--video": st.just(OUT + ".mp4"), **CAPTURE_FLAGS},
        ),
        _verb(
            st.just(["render", *FROM_CAPTURE]),
            {"capture": (_write_capture, BROKEN_CAPTURE)},
            {"--frames": NUMBER, **CAPTURE_FLAGS},
        ),
    ),
    "export": _verb(
        st.just(["export", "--gaussians", IN + "gs", "--ply", OUT + ".ply"]),
        GS,
        {
            "--sh-degree": NUMBER,
            "--bake-steps": NUMBER,
            "--bake-views-per-step": NUMBER,
            "--bake-views-between": NUMBER,
            "--checkpoint": TEXT,
        },
    ),
    "refine": _verb(
        st.just(["refine", "--checkpoint", "pretrained:small", "--gaussians", IN + "gs", "--out", OUT + ".gs"]),
        GS,
        {"--steps": NUMBER, "--views-per-step": NUMBER, "--perceptual-weight": NUMBER},
    ),
    "view": st.one_of(
        _verb(
            st.just(["view", "--gaussians", IN + "gs", "--port=0"]),
            GS,
            {"--height": NUMBER, "--moving-height": NUMBER, "--host": TEXT, "--port": NUMBER},
        ),
        _verb(
            st.just(["view", "--procedural", "0", "--port=0", "--checkpoint", IN + "ckpt"]),
            {"ckpt": (_write_folder, BROKEN_FOLDER)},
            {"--procedural": NUMBER, "--port": NUMBER},
        ),
    ),
    "reconstruct": st.one_of(
        _verb(
            st.just(["reconstruct", *FROM_CAPTURE]),
            {"capture": (_write_capture, BROKEN_CAPTURE)},
            {**CAPTURE_FLAGS, "--timing": st.just(OUT + ".json")},
        ),
        _verb(
            st.just(["reconstruct", "--images", IN + "photos", "--checkpoint", "pretrained:small", "--out", OUT]),
            {"photos": (lambda r, p, v: _write_photos(r, p), BROKEN_PHOTOS)},
            POSES_FLAGS,
        ),
    ),
    "poses": st.one_of(
        _verb(
            st.just(["poses", "--images", IN + "photos", "--out", OUT]),
            {"photos": (lambda r, p, v: _write_photos(r, p), BROKEN_PHOTOS)},
            POSES_FLAGS,
        ),
        _verb(
            st.just(["poses", "--video", IN + "video", "--out", OUT]),
            {"video": (_write_file, BROKEN_FILE)},
            POSES_FLAGS,
        ),
    ),
    "convert": st.one_of(
        _verb(
            st.just(["convert", "--checkpoint", IN + "pt", "--out", OUT]),
            {"pt": (_write_file, BROKEN_FILE)},
            {"--config": TEXT},
        ),
        _verb(st.just(["convert", "--vgg19", IN + "pt", "--out", OUT]), {"pt": (_write_file, BROKEN_FILE)}, {}),
    ),
    "eval": _verb(
        st.just(["eval", "--config", "demo", "--checkpoint", IN + "ckpt", "--data", IN + "capture", "--out", OUT]),
        {"ckpt": (_write_folder, BROKEN_FOLDER), "capture": (_write_capture, BROKEN_CAPTURE)},
        {
            "--num-inputs": NUMBER,
            "--max-scenes": NUMBER,
            "--size": SIZE,
            "--refine-steps": NUMBER,
            "--refine-perceptual-weight": NUMBER,
            "--refine-views-per-step": NUMBER,
            "--split": TEXT,
        },
    ),
    "train": st.one_of(
        _verb(
            st.just(["train", "--config", IN + "config.py", "--workdir", OUT]),
            {"config.py": (_write_file, BROKEN_FILE)},
            {"--max-minutes": NUMBER, "--heartbeat-timeout": NUMBER},
        ),
        _verb(
            st.just(["train", "--config", "demo", "--workdir", OUT, "--init", IN + "init"]),
            {"init": (_write_file, BROKEN_FILE.filter(lambda r: r[0] != "folder"))},
            {"--max-minutes": NUMBER, "--heartbeat-timeout": NUMBER},
        ),
    ),
    # no file: a number that is never valid, or a name that is never known
    "demo": st.tuples(st.sampled_from(["0", "-1", "nan", "", "1.5", "9" * 30]), NUMBER).map(
        lambda t: (["demo", "--out", OUT, f"--steps={t[0]}", f"--minutes={t[1]}"], {})
    ),
    "bench": st.tuples(TEXT.filter(lambda s: s not in ("cpu", "paper")), _flags({"--views": LIST, "--size": SIZE})).map(
        lambda t: (["bench", f"--scale={t[0]}", "--out", OUT, *t[1]], {})
    ),
    "plan": st.tuples(st.text(alphabet="!@# xyz09,_-", max_size=12), st.text(max_size=8)).map(
        lambda t: (["plan", f"--programs={t[0]}", f"--targets={t[1]}", "--out", OUT + ".json"], {})
    ),
}


def test_every_verb_but_doctor_is_fuzzed():
    """``doctor`` takes no flags and reads no file (it checks the machine)."""
    from llrmpp_jax.cli import VERBS

    assert sorted(STRATEGIES) == sorted(v.name for v in VERBS if v.name != "doctor")


def _check(case, valid) -> None:
    argv, files = case
    with tempfile.TemporaryDirectory() as d:
        for name, (writer, recipe) in files.items():
            writer(recipe, os.path.join(d, "in_" + name), valid)
        argv = [a.replace(IN, os.path.join(d, "in_")).replace(OUT, os.path.join(d, "out")) for a in argv]
        status, lines = run_cli(argv)
        assert status in (0, 2), (status, lines)
        assert not any("Traceback" in x for x in lines), lines
        if status == 2:
            errors = [x for x in lines if "error:" in x]
            assert len(errors) == 1 and lines[-1] == errors[0], lines
            assert len(lines) <= MAX_STDERR_LINES, lines
            assert not [f for f in os.listdir(d) if f.startswith("out")], os.listdir(d)  # nothing half-written


@pytest.mark.parametrize("verb", sorted(STRATEGIES))
def test_fuzzed_command_lines_end_in_one_line_or_success(verb, valid):
    @FUZZ
    @given(case=STRATEGIES[verb])
    def run(case):
        _check(case, valid)

    run()
