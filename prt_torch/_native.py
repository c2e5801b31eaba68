"""Small C libraries compiled on first use with the system C compiler and called through ctypes.

Used where torch has no fused op for a hot loop: the relight kernels
(:mod:`prt_torch.codecs.relight_kernels`) and the ray generation of the diffuse precompute
(:mod:`prt_torch.transfer.ray_kernels`). A library is compiled once per source, flags, compiler,
CPU and platform (a hash of them names the file), kept on disk in
``$PRT_TORCH_CACHE`` or ``$XDG_CACHE_HOME/prt_torch`` (default ``~/.cache/prt_torch``), else in a
per-user directory of the system temp dir, and written atomically (concurrent processes see the
whole file or none). A library is never loaded from a directory another user can write.

Without a compiler, or when the compile fails, :func:`compile_library` returns ``(None, why)``
and the caller takes its torch or numpy path.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["compile_library", "cache_dirs"]


def _cpu_id() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            lines = [ln for ln in f if ln.startswith(("model name", "flags"))][:2]
        return "".join(lines)
    except OSError:
        return platform.processor() or platform.machine()


def cache_dirs() -> list[Path]:
    """Where compiled libraries are kept: ``$PRT_TORCH_CACHE`` or ``$XDG_CACHE_HOME/prt_torch`` (default
    ``~/.cache/prt_torch``), then a per-user directory in the system temp dir (read-only homes)."""
    root = os.environ.get("PRT_TORCH_CACHE") or os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "prt_torch")
    user = getattr(os, "getuid", lambda: "user")()
    return [Path(root) / "kernels", Path(tempfile.gettempdir()) / f"prt_torch-kernels-{user}"]


def _private(d: Path) -> bool:
    """``d`` (created 0700 if missing) belongs to this user and no one else can write to it."""
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        st = d.stat()
    except OSError:
        return False
    return not hasattr(os, "getuid") or (st.st_uid == os.getuid() and not st.st_mode & 0o022)


def _build(cc: str, flags: list[str], src_text: str, name: str, so: Path) -> str | None:
    """Compile ``src_text`` into ``so`` (atomically); the compiler's complaint, or None."""
    so.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=so.parent) as tmp:
        src = Path(tmp) / f"{name}.c"
        src.write_text(src_text)
        out = Path(tmp) / f"{name}.so"
        r = subprocess.run([cc, *flags, str(src), "-o", str(out), "-lm"], capture_output=True, text=True, timeout=120)
        if r.returncode != 0:
            return r.stderr.strip()[-400:]
        os.replace(out, so)  # atomic: concurrent processes see the whole file or none
    return None


def compile_library(name: str, src: str, flags: list[str], signatures: dict[str, list]) -> tuple[ctypes.CDLL | None, str]:
    """``(library, how)`` or ``(None, why not)``: ``src`` compiled with ``flags`` (then without
    ``-march=native``, for a compiler that refuses it: the baseline ISA), cached on disk as
    ``<name>-<hash>.so``. ``signatures``: function name → ctypes argument types; each returns
    a C ``int``."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        return None, "no C compiler (cc/gcc) on PATH"
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as e:
        return None, f"C compiler {cc!r} did not run: {e}"
    errors = []
    so = used = None
    for used in (flags, [f for f in flags if f != "-march=native"]):
        key = hashlib.sha256("\0".join([src, " ".join(used), version, _cpu_id(), platform.platform()]).encode()).hexdigest()[:16]
        for d in cache_dirs():
            so = d / f"{name}-{key}.so"
            if not _private(d):  # never load a library from a directory another user can write
                errors.append(f"{d}: not a directory of this user only")
                so = None
                continue
            if so.exists():
                break
            try:
                err = _build(cc, used, src, name, so)
            except (OSError, subprocess.SubprocessError) as e:  # unwritable directory: try the next
                errors.append(f"{d}: {e}")
                continue
            if err is None:
                break
            errors.append(f"{cc} {' '.join(used)}: {err}")
            so = None
            break  # the compiler refused: the next flags, not the next directory
        if so is not None and so.exists():
            break
    if so is None or not so.exists():
        return None, f"compiling the {name} kernels failed: " + " | ".join(errors)
    try:
        lib = ctypes.CDLL(str(so))
    except OSError as e:
        return None, f"loading {so} failed: {e}"
    for fn, argtypes in signatures.items():
        f = getattr(lib, fn)
        f.argtypes = argtypes
        f.restype = ctypes.c_int
    return lib, f"compiled with {cc} ({' '.join(used)}), {so}"
