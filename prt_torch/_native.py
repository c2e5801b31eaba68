"""Small C libraries compiled on first use with the system C compiler and called through ctypes.

Used where torch has no fused op for a hot loop: the relight kernels
(:mod:`prt_torch.codecs.relight_kernels`) and the ray generation of the diffuse precompute
(:mod:`prt_torch.transfer.ray_kernels`); and by the cold-cache timing, to flush what a timed call
touches from the caches (:func:`prt_torch.harness.timing.flush_caches`). Their C sources are files of their own, shipped as package
data in ``prt_torch/kernels/`` (:data:`LIBRARIES` lists which files and flags make each library);
a compile error names the file and line there. A library is compiled once per source, flags,
compiler, CPU and platform (a hash of them names the file), kept on disk in
``$PRT_TORCH_CACHE`` or ``$XDG_CACHE_HOME/prt_torch`` (default ``~/.cache/prt_torch``), else in a
per-user directory of the system temp dir, and written atomically (concurrent processes see the
whole file or none). A library is never loaded from a directory another user can write.

Without a compiler, or when the compile fails, :func:`compile_library` returns ``(None, why)``
and the caller takes its torch or numpy path.

Ahead of time: ``pip install .`` (a non-editable install) builds each library when the build
machine has a compiler (``setup.py``'s build step calls :func:`prebuild`) into
``prt_torch/kernels/prebuilt/`` with a manifest of what it was built from. At run time a prebuilt
library is used only when its sources and flags are the ones asked for and this CPU has every
instruction-set flag of the CPU that built it (so a wheel carried to an older CPU compiles at run
time instead of faulting); otherwise, and with ``PRT_TORCH_PREBUILT=0``, the run-time compile
above runs as before.
"""
from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["compile_library", "cache_dirs", "kernel_sources", "prebuild", "kernel_isa", "cpu_isa", "LIBRARIES", "KERNELS_DIR",
           "PREBUILT_DIR", "KERNEL_ISAS"]

#: where the C sources live (package data)
KERNELS_DIR = Path(__file__).resolve().parent / "kernels"
#: where ``pip install`` leaves the libraries it built ahead of time (:func:`prebuild`)
PREBUILT_DIR = KERNELS_DIR / "prebuilt"

#: each library: (its sources in :data:`KERNELS_DIR`, headers first, then the files compiled together, in
#: this order; the compiler flags). ``relight_kernels`` and ``ray_kernels`` read theirs from here, and so does
#: ``setup.py``'s ahead-of-time build (this module imports nothing outside the standard library).
LIBRARIES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "relight": (("prt_kernels.h", "vec.h", "affine.h", "sg_texels.h", "affine_constants.c", "affine_rows.c", "affine_dense.c",
                 "affine_taps.c", "relight_plan.c", "sg_lookup.c"),
                ("-O3", "-march=native", "-ffp-contract=fast", "-fopenmp", "-shared", "-fPIC", "-std=c99")),
    "raygen": (("raygen.c", "guided.c", "glossy.c"), ("-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-fopenmp", "-shared", "-fPIC",
                                "-std=c99")),
    "wavelet": (("wavelet.c",), ("-O3", "-march=native", "-ffp-contract=fast", "-fopenmp", "-shared", "-fPIC", "-std=c99")),
    # libmvec (glibc's vector math: the AVX2 path's 4-lane pow), linked even where --as-needed is the default;
    # -fno-trapping-math lets GCC if-convert (vectorise) the BRDF's guarded divisions
    "transport": (("transport.c",), ("-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math",
                                     "-fopenmp", "-shared",
                                     "-fPIC", "-std=c99", "-Wl,--no-as-needed", "-lmvec")),
    # -fno-trapping-math: lets GCC if-convert (and so vectorise) the polynomial exp's range clamps
    "gauss_lm": (("gauss_lm.c",), ("-O3", "-march=native", "-ffp-contract=fast", "-fno-trapping-math", "-fopenmp", "-shared",
                                   "-fPIC", "-std=c99")),
    # cold-cache timing's eviction (harness.timing.flush_caches): CLFLUSHOPT where -march=native has it, else CLFLUSH
    # (the build without -march=native), dc civac on aarch64
    "cacheflush": (("cacheflush.c",), ("-O2", "-march=native", "-shared", "-fPIC", "-std=c99")),
}


def kernel_sources(names, root: Path | None = None) -> dict[str, str]:
    """``{file name: its text}`` of the C sources ``names`` in ``root`` (default :data:`KERNELS_DIR`), in
    the given order."""
    root = KERNELS_DIR if root is None else Path(root)
    out = {}
    for n in names:
        try:
            out[n] = (root / n).read_text()
        except OSError as e:
            raise FileNotFoundError(f"the C kernel source {root / n} is missing ({e.strerror}); accepted: an installation "
                                    f"of prt_torch with its package data (prt_torch/kernels/*.c, *.h)") from e
    return out


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


def _complaint(stderr: str, tmp: Path, origin: Path | None) -> str:
    """The compiler's message with the temporary directory's paths replaced by the sources' own
    (``origin``), its first errors first: ``affine_rows.c:123:5: error: ...`` names a line a C programmer
    can open."""
    if origin is not None:
        stderr = stderr.replace(str(tmp) + os.sep, str(origin) + os.sep)
    lines = stderr.strip().splitlines()
    errors = [ln for ln in lines if ": error:" in ln or ": fatal error:" in ln]
    head = "\n".join(errors[:5])
    rest = "\n".join(lines)
    return (head + ("\n..." if head else "") + "\n" + rest[-600:]) if head else rest[-800:]


#: how :func:`_build` compiles (part of every library's key: a change of method rebuilds)
_BUILD = "one translation unit of the .c files in order"


def _key(name: str, sources: dict[str, str], flags: list[str], extra: list[str]) -> str:
    parts = [name, _BUILD] + [f"{n}\0{t}" for n, t in sources.items()] + [" ".join(flags)] + extra
    return hashlib.sha256("\0".join(parts).encode()).hexdigest()[:16]


def _build(cc: str, flags: list[str], sources: dict[str, str], name: str, so: Path, origin: Path | None) -> str | None:
    """Compile ``sources`` (file name → text; the headers found beside the ``.c`` files) into ``so``
    (atomically); the compiler's complaint, or None.

    Several ``.c`` files are compiled as one translation unit, each ``#include``d in the given order
    by a generated ``<name>.unity.c``: the compiler then sees what it saw when the kernels were one
    source (the relight library's machine code is byte-identical to the former single string's,
    objdump-checked), so it inlines across files and lays the code out as before — these kernels'
    speed moves by a few per cent with code placement alone (docs/codecs_log.md, "Comparing kernels"). Each file still
    compiles on its own (tests/test_kernel_sources.py), and an error names the file and line."""
    so.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=so.parent) as tmp:
        tmp = Path(tmp)
        for n, text in sources.items():
            (tmp / n).write_text(text)
        units = [n for n in sources if n.endswith(".c")]
        if len(units) > 1:
            unity = tmp / f"{name}.unity.c"
            unity.write_text("".join(f'#include "{n}"\n' for n in units))
            units = [unity.name]
        units = [str(tmp / n) for n in units]
        out = tmp / f"{name}.so"
        r = subprocess.run([cc, *flags, f"-I{tmp}", *units, "-o", str(out), "-lm"], capture_output=True, text=True, timeout=300)
        if r.returncode != 0:
            return _complaint(r.stderr, tmp, origin)
        os.replace(out, so)  # atomic: concurrent processes see the whole file or none
    return None


def _compiler() -> tuple[str | None, str]:
    """``(cc, its --version text)`` or ``(None, why not)``."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not cc:
        return None, "no C compiler (cc/gcc) on PATH"
    try:
        return cc, subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as e:
        return None, f"C compiler {cc!r} did not run: {e}"


def _isa_flags() -> set[str]:
    """This CPU's instruction-set flags (``/proc/cpuinfo``'s flags line; empty where there is none)."""
    cpu = _cpu_id()
    for ln in cpu.splitlines():
        if ln.startswith("flags"):
            return set(ln.split(":", 1)[1].split())
    return set()


#: the values of ``PRT_TORCH_KERNEL_ISA`` and the flags each adds after ``-march=native`` (issue 42 §4): ``native``
#: (the default: every instruction set of this CPU, so AVX-512's 16-lane and k-mask paths where it has them),
#: ``avx2`` (``-mno-avx512f``: the 8-lane AVX2 paths, also on an AVX-512 CPU: on AMD Zen 4, whose 512-bit
#: operations are two 256-bit halves, the alternative to measure), ``avx512`` (the AVX-512 paths; refused on a
#: CPU without avx512f and avx512vl, where native builds the AVX2 ones), ``avx512-256`` (AVX-512VL's 32
#: registers and k-masks on 8-float vectors, without the 16-lane kernels (``PRT_NO_W16``: vec.h's HAVE_W16 and
#: sg_texels.h's SG16 off) and with the compiler's own vectorisation at 256 bits: between the two, it tells
#: the 512-bit kernels' share from the rest of AVX-512's)
KERNEL_ISAS: dict[str, tuple[str, ...]] = {"native": (), "avx2": ("-mno-avx512f",), "avx512": (),
                                            "avx512-256": ("-mprefer-vector-width=256", "-DPRT_NO_W16")}


def cpu_isa() -> str:
    """This CPU's widest vector instruction set the kernels have paths for: ``avx512`` (avx512f and avx512vl),
    ``avx2``, ``avx``, else ``baseline`` (from ``/proc/cpuinfo``'s flags; ``unknown`` where there are none)."""
    f = _isa_flags()
    if not f:
        return "unknown"
    return ("avx512" if {"avx512f", "avx512vl"} <= f else "avx2" if {"avx2", "fma"} <= f else "avx" if "avx" in f
            else "baseline")


def kernel_isa() -> tuple[str, tuple[str, ...]]:
    """``(choice, extra compiler flags)`` of ``PRT_TORCH_KERNEL_ISA`` (unset or empty: ``native``): which of the
    kernels' instruction-set branches the relight library is built with (:data:`KERNEL_ISAS`). Raises
    ``ValueError`` (one line naming the variable, its value and what is accepted) for another value, or for one
    this CPU cannot run."""
    raw = os.environ.get("PRT_TORCH_KERNEL_ISA", "")
    v = raw.strip().lower() or "native"
    if v not in KERNEL_ISAS:
        raise ValueError(f"PRT_TORCH_KERNEL_ISA={raw!r}; accepted: native (the default: -march=native), avx2 (-march=native "
                         f"-mno-avx512f: the 8-lane AVX2 kernels), avx512 (the 16-lane AVX-512 kernels, on a CPU with avx512f "
                         f"and avx512vl), avx512-256 (AVX-512VL on 8-float vectors, no 16-lane kernels)")
    have = cpu_isa()
    need = {"avx512": ("avx512",), "avx512-256": ("avx512",), "avx2": ("avx512", "avx2")}.get(v)
    if need and have != "unknown" and have not in need:
        cpu = _cpu_id().splitlines()[0].split(":", 1)[-1].strip() if _cpu_id() else platform.machine()
        raise ValueError(f"PRT_TORCH_KERNEL_ISA={raw!r}, but this CPU ({cpu}) has {have} at most; accepted here: native"
                         + (", avx2" if v.startswith("avx512") and have == "avx2" else ""))
    return v, KERNEL_ISAS[v]


def check_isa_list(spec: str) -> list[str]:
    """A comma list of ``PRT_TORCH_KERNEL_ISA`` values (the benchmarks' ``--isa``), each checked by :func:`kernel_isa`
    as this CPU would take it; the variable is left as it was. Raises ``ValueError`` (one line) for a value that is
    not accepted here."""
    out = [v.strip() for v in spec.split(",") if v.strip()]
    prev = os.environ.get("PRT_TORCH_KERNEL_ISA")
    try:
        for v in out:
            os.environ["PRT_TORCH_KERNEL_ISA"] = v
            kernel_isa()
    finally:
        if prev is None:
            os.environ.pop("PRT_TORCH_KERNEL_ISA", None)
        else:
            os.environ["PRT_TORCH_KERNEL_ISA"] = prev
    return out


def _sources_of(name: str, src) -> dict[str, str]:
    return {f"{name}.c": src} if isinstance(src, str) else dict(src)


def _load(so: Path, signatures: dict[str, list]) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(so))
    for fn, argtypes in signatures.items():
        f = getattr(lib, fn)
        f.argtypes = argtypes
        f.restype = ctypes.c_int
    return lib


def _prebuilt(name: str, sources: dict[str, str], flags: list[str]) -> Path | None:
    """The library ``setup.py`` built at install time for exactly these sources and flags, if this CPU
    runs it (has every ISA flag of the CPU that built it) and ``PRT_TORCH_PREBUILT`` is not ``0``."""
    if os.environ.get("PRT_TORCH_PREBUILT", "1") == "0":
        return None
    d = PREBUILT_DIR
    try:
        man = json.loads((d / f"{name}.json").read_text())
    except (OSError, ValueError):
        return None
    if man.get("key") != _key(name, sources, flags, []) or man.get("machine") != platform.machine():
        return None
    if not set(man.get("isa", [])) <= _isa_flags():
        return None
    so = d / man.get("file", "")
    return so if so.is_file() else None


def prebuild(name: str, out_dir: Path, root: Path | None = None) -> str:
    """Build library ``name`` of :data:`LIBRARIES` from the sources in ``root`` (default
    :data:`KERNELS_DIR`) into ``out_dir`` as ``<name>.so`` with its manifest ``<name>.json`` (the
    sources' and flags' key, this CPU's ISA flags, the compiler): what ``pip install .`` runs. Returns
    what it did, or raises ``RuntimeError`` naming the compiler's complaint."""
    names, flags = LIBRARIES[name]
    sources = kernel_sources(names, root)
    cc, version = _compiler()
    if cc is None:
        raise RuntimeError(version)
    out_dir = Path(out_dir)
    err = _build(cc, list(flags), sources, name, out_dir / f"{name}.so", KERNELS_DIR if root is None else Path(root))
    if err is not None:
        raise RuntimeError(f"compiling the {name} kernels failed: {err}")
    man = {"key": _key(name, sources, list(flags), []), "file": f"{name}.so", "machine": platform.machine(),
           "isa": sorted(_isa_flags()), "compiler": version.splitlines()[0] if version else cc, "flags": list(flags)}
    tmp = out_dir / f".{name}.json.tmp"
    tmp.write_text(json.dumps(man, indent=1))
    os.replace(tmp, out_dir / f"{name}.json")
    return f"built {out_dir / (name + '.so')} with {man['compiler']}"


def compile_library(name: str, src, flags: list[str], signatures: dict[str, list],
                    origin: Path | None = KERNELS_DIR) -> tuple[ctypes.CDLL | None, str]:
    """``(library, how)`` or ``(None, why not)``: ``src`` (``{file name: text}``: headers and ``.c``
    files, the ``.c`` ones compiled and linked together; or one C source as a string) compiled with
    ``flags`` (then without ``-march=native``, for a compiler that refuses it: the baseline ISA), cached
    on disk as ``<name>-<hash>.so``; or the library ``pip install`` built ahead of time for the same
    sources and flags (:func:`prebuild`). ``origin``: the directory the sources' file names are
    reported in (compiler errors as ``origin/file.c:line``). ``signatures``: function name → ctypes
    argument types; each returns a C ``int``."""
    sources = _sources_of(name, src)
    pre = _prebuilt(name, sources, list(flags))
    skipped = ""
    if pre is not None:
        try:
            return _load(pre, signatures), f"prebuilt at install time ({' '.join(flags)}), {pre}"
        except (OSError, AttributeError) as e:  # not loadable here (or missing a symbol): compile at run time, saying so
            skipped = f" (the prebuilt {pre} did not load: {e})"
    cc, version = _compiler()
    if cc is None:
        return None, version + skipped
    errors = []
    so = used = None
    for used in (flags, [f for f in flags if f != "-march=native"]):
        key = _key(name, sources, used, [version, _cpu_id(), platform.platform()])
        for d in cache_dirs():
            so = d / f"{name}-{key}.so"
            if not _private(d):  # never load a library from a directory another user can write
                errors.append(f"{d}: not a directory of this user only")
                so = None
                continue
            if so.exists():
                break
            try:
                err = _build(cc, used, sources, name, so, origin)
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
        lib = _load(so, signatures)
    except OSError as e:
        return None, f"loading {so} failed: {e}"
    return lib, f"compiled with {cc} ({' '.join(used)}), {so}{skipped}"
