"""JAX's persistent compilation cache for every command: where it lives, turning it on, what
it holds, and saying whether a compile came from it.

A compiled XLA program is written to disk (``jax_compilation_cache_dir``) and a later
process that compiles the same program on the same machine with the same JAX loads it
instead. :func:`enable` points JAX at ``ROOT/MACHINE`` where ``ROOT`` is, first found:

1. the ``--compile-cache DIR`` flag (``path=``),
2. ``JAX_COMPILATION_CACHE_DIR``,
3. :func:`default_root`: the user's cache folder (``platformdirs``; ``$XDG_CACHE_HOME`` or
   ``~/.cache`` on Linux) ``/llrmpp_jax/xla``,

and ``MACHINE`` (:func:`machine_tag`) names the JAX and jaxlib versions, the CPU
architecture and a hash of the CPU's feature flags, so an entry written by another JAX or
on another machine (a shared home folder, a copied cache) is never looked up, let alone
loaded. Within a folder JAX's own key (program, devices, XLA flags, compile options)
decides a hit; an unreadable entry is a warning and a fresh compile
(``jax_raise_persistent_cache_errors`` is off), which :func:`enable` turns into one line.

Every compiled program is written (:data:`MIN_COMPILE_S`): even the smallest loads several
times faster than it compiles, for a few kB. :func:`enable` holds the folder under
:data:`MAX_BYTES` by deleting the least recently used entries (:func:`trim`, once per
command; JAX's own size cap rescans the whole folder under a lock on every write, which
grows quadratically with the entries). Processes may share the folder (the suite's
workers, two commands at once): an entry read while another process is writing it, or left
truncated by a killed process, fails JAX's decompression; JAX then warns and compiles
afresh, and :func:`enable`'s warning hook deletes the unreadable entry, so the fresh
compile replaces it. :func:`clear` empties the folder.

Turning it off: ``--no-compile-cache`` or ``JAX_ENABLE_COMPILATION_CACHE=0``. A folder that
cannot be created or written is one warning line and the command runs uncached.

:class:`CompileWatch` counts, over a block, the programs compiled and those loaded from the
cache (JAX's monitoring events), so a command can say "compiled in 41 s" or "0.8 s, from
the compile cache".
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import os
import platform
import re
import shutil
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager

MIN_COMPILE_S = 0.0
"""Seconds a program must take to compile before it is written (JAX's default is 1 s)."""

MAX_BYTES = 4 * 1024**3
"""The folder's cap in bytes; beyond it :func:`trim` deletes the least recently used entries."""

_ENTRY = "-cache"  # JAX's suffix of an entry's file

_WARNING_PREFIXES = ("Error reading persistent compilation cache", "Error writing persistent compilation cache")


def default_root() -> str:
    """The user's cache folder for compiled programs (before the machine tag)."""
    import platformdirs

    return os.path.join(platformdirs.user_cache_dir("llrmpp_jax"), "xla")


def _cpu_flags() -> str:
    """The CPU's feature flags (``/proc/cpuinfo``), or the processor name where there are none."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor()


def machine_tag() -> str:
    """``jax-V_jaxlib-V_ARCH_HASH``: the cache's subfolder for this JAX on this kind of CPU."""
    from importlib.metadata import version

    digest = hashlib.sha256(_cpu_flags().encode()).hexdigest()[:10]
    return f"jax-{version('jax')}_jaxlib-{version('jaxlib')}_{platform.machine()}_{digest}"


@dataclasses.dataclass(frozen=True)
class CacheState:
    """Where compiled programs go in this process.

    ``path`` is the folder in use (``None`` when off); ``reason`` says why it is off, or
    where the root came from (``"flag"``, ``"JAX_COMPILATION_CACHE_DIR"``, ``"default"``,
    ``"already set"``)."""

    path: str | None
    reason: str

    @property
    def enabled(self) -> bool:
        return self.path is not None


_state = CacheState(None, "not configured")
_warned = threading.Event()


def state() -> CacheState:
    """What :func:`enable` (or :func:`disable`) last set up in this process."""
    return _state


def _writable(path: str) -> str | None:
    """``None`` when ``path`` (created if missing) takes a file, else why not, in a few words."""
    try:
        os.makedirs(path, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=path, prefix=".probe-")
        try:
            os.write(fd, b"\0" * 4096)
        finally:
            os.close(fd)
            os.remove(probe)
    except OSError as e:
        return f"{type(e).__name__}: {e.strerror or e}"
    return None


def _entry_readable(path: str) -> bool:
    """Whether the cache entry ``path`` decompresses (JAX's own codec)."""
    try:
        from jax._src.compilation_cache import decompress_executable  # JAX's codec: zstd, else zlib
    except ImportError:  # another JAX: assume unreadable, the entry is only a cache
        return False
    try:
        with open(path, "rb") as f:
            decompress_executable(f.read())
    except Exception:  # any codec error means the entry cannot be used
        return False
    return True


def _remove_unreadable(module: str) -> int:
    """Delete the entries of the program ``module`` that do not decompress; returns how many."""
    folder = _state.path
    if folder is None:
        return 0
    removed = 0
    for entry in glob.glob(os.path.join(glob.escape(folder), f"{glob.escape(module)}-*{_ENTRY}")):
        if not _entry_readable(entry):
            with contextlib.suppress(FileNotFoundError):
                os.remove(entry)
            removed += 1
    return removed


def _one_line_warnings() -> None:
    """Show JAX's cache read/write warnings as one line, once per process (a full disk would
    otherwise print one two-line warning per program), deleting an entry that could not be
    read so the compile that follows replaces it."""
    shown = warnings.showwarning
    unreadable = re.compile(r"Error reading persistent compilation cache entry for '([^']+)'")

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if not text.startswith(_WARNING_PREFIXES):
            return shown(message, category, filename, lineno, file, line)
        m = unreadable.match(text)
        if m:
            _remove_unreadable(m.group(1))
        if not _warned.is_set():
            _warned.set()
            where = _state.path or "the compile cache"
            what = f"{text.splitlines()[0][:300]}" + ("; the entry was removed and compiled afresh" if m else "")
            print(f"llrmpp: warning: compile cache {where}: {what}", file=sys.stderr)

    if getattr(warnings.showwarning, "_llrmpp_cache", False):
        return
    show._llrmpp_cache = True  # pyright: ignore[reportFunctionMemberAccess] -- a marker so it is installed once
    warnings.showwarning = show


def _point_jax_at(path: str | None) -> None:
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()  # JAX opens its cache once per process; a new folder needs a reset
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_enable_compilation_cache", path is not None)
    if path is not None:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # every size: the time decides
        jax.config.update("jax_compilation_cache_max_size", -1)  # trim() caps the size instead


def enable(path: str | None = None, *, quiet: bool = False) -> CacheState:
    """Turn the persistent compilation cache on at ``ROOT/`` :func:`machine_tag` (``ROOT``
    as the module docstring says; ``path`` is the ``--compile-cache`` flag). Off instead,
    with ``reason``, when ``JAX_ENABLE_COMPILATION_CACHE`` is false or the folder cannot be
    written (one warning line on stderr unless ``quiet``). Call it before the first compile."""
    global _state
    # The user's switch, read where the user sets it (disable() turns JAX's own option off).
    if os.environ.get("JAX_ENABLE_COMPILATION_CACHE", "1").strip().lower() in ("0", "false", "no", "off", "n", "f"):
        _state = CacheState(None, "off (JAX_ENABLE_COMPILATION_CACHE)")
        return _state
    if path:
        root, source = path, "flag"
    elif os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        root, source = os.environ["JAX_COMPILATION_CACHE_DIR"], "JAX_COMPILATION_CACHE_DIR"
    else:
        root, source = default_root(), "default"
    folder = os.path.join(os.path.abspath(os.path.expanduser(root)), machine_tag())
    if _state.path == folder:
        return _state
    why = _writable(folder)
    if why is not None:
        if not quiet:
            warn = f"llrmpp: warning: compile cache {folder} cannot be written ({why}); running uncached"
            print(warn, file=sys.stderr)
        _point_jax_at(None)
        _state = CacheState(None, f"off ({folder}: {why})")
        return _state
    _one_line_warnings()
    trim(folder)
    _point_jax_at(folder)
    _state = CacheState(folder, source)
    return _state


def disable(reason: str = "off (--no-compile-cache)") -> CacheState:
    """Turn the persistent compilation cache off in this process."""
    global _state
    _point_jax_at(None)
    _state = CacheState(None, reason)
    return _state


def usage(path: str) -> tuple[int, int]:
    """``(entries, bytes)`` of the cache folder ``path`` (0, 0 when it does not exist)."""
    entries, size = 0, 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                size += os.path.getsize(os.path.join(root, name))
            except OSError:  # evicted meanwhile
                continue
            entries += name.endswith(_ENTRY)
    return entries, size


def trim(folder: str, max_bytes: int = MAX_BYTES) -> int:
    """Delete the least recently used entries of ``folder`` (by the files' access or
    modification time, the later) until it holds at most ``max_bytes``; returns the bytes freed."""
    entries = []
    with os.scandir(folder) as it:
        for e in it:
            if e.name.endswith(_ENTRY):
                st = e.stat()
                entries.append((max(st.st_atime, st.st_mtime), e.path, st.st_size))
    total = sum(size for _, _, size in entries)
    freed = 0
    for _, path, size in sorted(entries):
        if total - freed <= max_bytes:
            break
        with contextlib.suppress(FileNotFoundError):
            os.remove(path)
        freed += size
    return freed


def clear(root: str | None = None) -> int:
    """Delete every compiled program under ``root`` (default :func:`default_root`, all
    machine tags); returns the bytes freed."""
    root = root or default_root()
    freed = usage(root)[1]
    shutil.rmtree(root, ignore_errors=True)
    return freed


class CompileWatch:
    """Counts, while it is entered, the XLA programs compiled and those loaded from the
    persistent cache in this process (all threads), and the seconds they took.

    ``programs``: compile requests that reached the backend (hits included); ``hits``: those
    the persistent cache answered; ``seconds``: their summed compile-or-load time."""

    _lock = threading.Lock()
    _active: list[CompileWatch] = []
    _registered = False

    def __init__(self) -> None:
        self.programs = 0
        self.hits = 0
        self.seconds = 0.0

    @classmethod
    def _register(cls) -> None:
        import jax.monitoring

        if cls._registered:
            return
        cls._registered = True

        def on_event(event: str, **_) -> None:
            if event == "/jax/compilation_cache/cache_hits":
                with cls._lock:
                    for w in cls._active:
                        w.hits += 1

        def on_duration(event: str, duration_secs: float, **_) -> None:
            if event == "/jax/core/compile/backend_compile_duration":
                with cls._lock:
                    for w in cls._active:
                        w.programs += 1
                        w.seconds += duration_secs

        jax.monitoring.register_event_listener(on_event)
        jax.monitoring.register_event_duration_secs_listener(on_duration)

    def __enter__(self) -> CompileWatch:
        self._register()
        with self._lock:
            self._active.append(self)
        return self

    def __exit__(self, *exc) -> None:
        with self._lock:
            self._active.remove(self)

    def describe(self, seconds: float) -> str:
        """``seconds`` (the block's wall time) with where the programs came from: ``"41 s"``,
        ``"0.8 s, from the compile cache"``, or ``"12 s, 3 of 5 programs from the compile cache"``."""
        took = f"{seconds:.1f} s" if seconds < 10 else f"{seconds:.0f} s"
        if not self.hits:
            return took
        compiled = self.programs - self.hits
        if not compiled:
            return f"{took}, from the compile cache"
        return f"{took}, {self.hits} of {self.programs} programs from the compile cache"


@contextmanager
def announce(what: str, report: Callable[[str], None] | None = print) -> Iterator[CompileWatch]:
    """Say ``"compiling WHAT ..."`` before the block and ``"compiled WHAT: 41 s"`` (or
    ``"0.8 s, from the compile cache"``) after it, through ``report`` (``None``: silent)."""
    if report:
        report(f"compiling {what} ...")
    t0 = time.perf_counter()
    with CompileWatch() as watch:
        yield watch
    if report:
        report(f"compiled {what}: {watch.describe(time.perf_counter() - t0)}")
