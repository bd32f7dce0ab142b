"""What a file is, read from its content before any loader runs: a user's file that is not
what its flag or name claims is one line naming the file, what it looks like and what was
expected, instead of the loader's own error from deep inside it.

Kept libraries recognise what they can -- :func:`zipfile.is_zipfile` (``.npz``, ``.gs``,
torch's zip checkpoints), :func:`numpy.lib.format.read_magic` (``.npy``), OpenImageIO's
readers (images, by content when the extension is not theirs) -- and a short table of
leading bytes the rest (PLY, pickles, videos, gzip, SQLite); text and JSON are whatever
decodes as UTF-8 without NUL bytes.

:func:`looks_like` describes any path; the ``check_*`` functions raise
:class:`~llrmpp_jax.errors.UserError` (:class:`~llrmpp_jax.errors.MissingInputError` when
the path does not exist) unless the file is of the kind a loader expects.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Iterable

from llrmpp_jax.errors import MissingInputError, UserError

_HEAD = 64  # bytes read to recognise a kind: enough for every signature below
# (leading bytes, kind); the first match wins.
_SIGNATURES: tuple[tuple[bytes, str], ...] = (
    (b"PK\x03\x04", "a truncated or damaged zip archive"),  # is_zipfile found no central directory
    (b"ply\n", "a PLY file"),
    (b"ply\r\n", "a PLY file"),
    (b"\x93NUMPY", "a NumPy .npy array"),
    (b"\x1f\x8b", "a gzip file"),
    (b"SQLite format 3\x00", "an SQLite database"),
    (b"\x1a\x45\xdf\xa3", "a Matroska/WebM video"),
    (b"\x89HDF\r\n\x1a\n", "an HDF5 file"),
)
# Images OpenImageIO could not open (cut short, damaged) still say what they were meant to be.
_DAMAGED_IMAGES: tuple[tuple[bytes, str], ...] = (
    (b"\xff\xd8\xff", "a damaged or truncated JPEG image"),
    (b"\x89PNG\r\n\x1a\n", "a damaged or truncated PNG image"),
    (b"v/1\x01", "a damaged or truncated EXR image"),
)
_PICKLE_PROTOCOLS = (2, 3, 4, 5)  # b"\x80" then the protocol number: torch's legacy .pt too
_VIDEO_KINDS = ("an MP4/MOV video", "a Matroska/WebM video", "an AVI video")
# Kinds that are certainly not a video (anything else is left to ffmpeg to decode).
_NOT_VIDEO = ("empty", "folder", "zip", "NumPy", "PLY", "pickle", "text", "JSON", "image", "gzip", "SQLite", "HDF5")


def _head(path: str) -> bytes:
    with open(path, "rb") as f:
        return f.read(_HEAD)


def _image_format(path: str) -> str | None:
    """OpenImageIO's name for the format of ``path`` (``"jpeg"``, ``"png"``, ...), or None."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        oiio.geterror()  # clear it: the next caller's error must be its own
        return None
    try:
        return str(inp.format_name())
    finally:
        inp.close()


def _zip_kind(path: str) -> str:
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except (zipfile.BadZipFile, OSError, ValueError):
        return "a damaged zip archive"
    if any(n.endswith("data.pkl") for n in names):
        return "a torch checkpoint (zip)"
    if names and all(n.endswith(".npy") for n in names):
        return "a NumPy .npz archive"
    return "a zip archive"


def _text_kind(head: bytes, path: str) -> str | None:
    if b"\x00" in head:
        return None
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as e:
        if len(head) < _HEAD or e.start < len(head) - 4:  # not merely a character cut by the read
            return None
    if head.lstrip()[:1] in (b"{", b"["):
        try:
            with open(path, encoding="utf-8") as f:
                json.load(f)
            return "JSON"
        except (ValueError, UnicodeDecodeError):
            return "text (not valid JSON)"
    return "text"


def looks_like(path: str) -> str:
    """What ``path`` appears to be, in words: ``"a folder"``, ``"a missing path"``,
    ``"an empty file"``, ``"a zip archive"``, ``"a jpeg image"``, ``"text"``, ... (an
    unrecognised file is ``"binary data (starts 00 11 22 33)"``)."""
    if os.path.isdir(path):
        return "a folder"
    if not os.path.exists(path):
        return "a missing path"
    if os.path.getsize(path) == 0:
        return "an empty file"
    head = _head(path)
    if zipfile.is_zipfile(path):
        return _zip_kind(path)
    for magic, kind in _SIGNATURES:
        if head.startswith(magic):
            return kind
    if head[:1] == b"\x80" and len(head) > 1 and head[1] in _PICKLE_PROTOCOLS:
        return "a Python pickle"
    if head[4:8] == b"ftyp":
        return "an MP4/MOV video"
    if head[:4] == b"RIFF" and head[8:12] == b"AVI ":
        return "an AVI video"
    fmt = _image_format(path)
    if fmt is not None:
        return f"a {fmt} image"
    for magic, kind in _DAMAGED_IMAGES:
        if head.startswith(magic):
            return kind
    text = _text_kind(head, path)
    if text is not None:
        return text
    return f"binary data (starts {head[:4].hex(' ')})"


def _missing(path: str, expected: str) -> MissingInputError:
    noun = expected.split(" (")[0]  # "a checkpoint folder (a workdir ...)" -> "checkpoint folder not found"
    noun = noun.split(" ", 1)[1] if noun.startswith(("a ", "an ")) else noun
    return MissingInputError(f"{noun} not found: {path}")


def _refuse(path: str, expected: str) -> UserError:
    return UserError(f"{path}: looks like {looks_like(path)}, expected {expected}")


def check_file(path: str, expected: str) -> None:
    """``path`` is a non-empty file (``expected`` names what it should be, for the message)."""
    if not os.path.exists(path):
        raise _missing(path, expected)
    if os.path.isdir(path) or os.path.getsize(path) == 0:
        raise _refuse(path, expected)


def check_npz(path: str, expected: str, members: Iterable[str] = ()) -> None:
    """``path`` is a NumPy ``.npz`` archive holding (at least) the arrays ``members``."""
    check_file(path, expected)
    if not zipfile.is_zipfile(path):
        raise _refuse(path, expected)
    try:
        with zipfile.ZipFile(path) as z:
            names = set(z.namelist())
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as e:
        raise UserError(f"{path}: a damaged zip archive ({e}), expected {expected}") from None
    absent = [m for m in members if f"{m}.npy" not in names]
    if absent:
        raise UserError(
            f"{path}: looks like {_zip_kind(path)} without {', '.join(absent[:4])}"
            + (f" (+{len(absent) - 4} more)" if len(absent) > 4 else "")
            + f", expected {expected}"
        )


def check_ply(path: str) -> None:
    """``path`` starts with a PLY header (``ply`` on the first line)."""
    check_file(path, "a PLY file")
    if not _head(path).startswith((b"ply\n", b"ply\r\n")):
        raise _refuse(path, "a PLY file")


def check_torch_file(path: str) -> None:
    """``path`` starts as a torch checkpoint does (a zip, possibly truncated: torch then says
    what is wrong, or a legacy pickle) or is a ``.npz`` archive."""
    expected = "a torch checkpoint (.pt/.pth) or a .npz archive"
    check_file(path, expected)
    head = _head(path)
    if not (head.startswith(b"PK\x03\x04") or (head[:1] == b"\x80" and len(head) > 1 and head[1] in _PICKLE_PROTOCOLS)):
        raise _refuse(path, expected)


def check_video(path: str) -> None:
    """``path`` is not certainly something other than a video (a container ffmpeg might
    read is left to ffmpeg, which names the file when it cannot)."""
    check_file(path, "a video file")
    kind = looks_like(path)
    if kind not in _VIDEO_KINDS and any(k in kind for k in _NOT_VIDEO):
        raise UserError(f"{path}: looks like {kind}, expected a video file (MP4, MOV, MKV, AVI, ...)")


def read_json(path: str, expected: str):
    """The JSON value in ``path`` (a file that is not UTF-8 JSON: a one-line ``UserError``)."""
    check_file(path, expected)
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (ValueError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: looks like {looks_like(path)}, expected {expected} ({e})") from None


def check_folder(path: str, expected: str) -> None:
    """``path`` is a folder (a file there is named with what it looks like)."""
    if not os.path.exists(path):
        raise _missing(path, expected)
    if not os.path.isdir(path):
        raise _refuse(path, expected)
