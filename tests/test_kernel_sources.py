"""The C kernels as source files (prt_torch/kernels/): each file compiles on its own without a
warning (-Wall -Wextra -Werror, at the library's flags and at the baseline ISA), every file is part
of a library, a compile error names the file and line a C programmer opens, and a library built
ahead of time (``pip install .``, :func:`prt_torch._native.prebuild`) is used only where it is the
same source, flags and a CPU that runs it."""
import ctypes
import json
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest

from prt_torch import _native
from prt_torch._native import KERNELS_DIR, LIBRARIES, compile_library, kernel_sources, prebuild

CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler")


def test_every_source_file_belongs_to_a_library_and_every_listed_file_exists():
    listed = {n for names, _ in LIBRARIES.values() for n in names}
    on_disk = {p.name for p in KERNELS_DIR.iterdir() if p.suffix in (".c", ".h")}
    assert listed == on_disk
    for names, _ in LIBRARIES.values():
        for n in names:  # the opening comment names the file and says what it computes
            assert (KERNELS_DIR / n).read_text().startswith(f"/* {n}: "), n


@needs_cc
def test_each_file_compiles_alone_without_warnings():
    """``-Wall -Wextra -Werror`` per translation unit, with the library's flags and without
    ``-march=native`` (the fallback users without AVX get); headers through the .c files that include them."""
    jobs = []
    for _, flags in LIBRARIES.values():
        base = [f for f in flags if f not in ("-shared",)]
        for names in (n for n, f in LIBRARIES.values() if f == flags):
            for n in names:
                if n.endswith(".c"):
                    for fl in (base, [f for f in base if f != "-march=native"]):
                        jobs.append([CC, *fl, "-Wall", "-Wextra", "-Werror", f"-I{KERNELS_DIR}", "-c", str(KERNELS_DIR / n), "-o", "/dev/null"])

    def run(cmd):
        return cmd, subprocess.run(cmd, capture_output=True, text=True, timeout=300)

    with ThreadPoolExecutor(2) as ex:
        for cmd, r in ex.map(run, jobs):
            assert r.returncode == 0, f"{' '.join(cmd)}\n{r.stderr}"


@needs_cc
def test_a_compile_error_names_the_source_file_and_line(tmp_path, monkeypatch):
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path / "cache"))
    names, flags = LIBRARIES["raygen"]
    src = kernel_sources(names)
    lines = src["raygen.c"].splitlines()
    bad_line = next(i for i, ln in enumerate(lines) if ln.startswith("int prt_count_up")) + 2  # 1-based: the line after
    lines.insert(bad_line - 1, "    this is not C;")
    src["raygen.c"] = "\n".join(lines) + "\n"
    lib, why = compile_library("raygen", src, list(flags), {})
    assert lib is None
    first = next(ln for ln in why.splitlines() if ": error:" in ln)
    assert f"{KERNELS_DIR / 'raygen.c'}:{bad_line}:" in first, why
    assert str(tmp_path) not in first  # the compiled temporary copy is not what is named


@needs_cc
def test_an_error_in_one_file_of_a_multi_file_library_names_that_file(tmp_path, monkeypatch):
    """The relight library compiles its .c files as one translation unit; an error still names the
    file it is in, not the generated unit that includes it."""
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path / "cache"))
    names, flags = LIBRARIES["relight"]
    src = kernel_sources(names)
    n_lines = src["affine_taps.c"].count("\n")
    src["affine_taps.c"] += "int broken(void) { return undeclared_name; }\n"
    lib, why = compile_library("relight", src, list(flags), {})
    assert lib is None
    first = next(ln for ln in why.splitlines() if ": error:" in ln)
    assert f"{KERNELS_DIR / 'affine_taps.c'}:{n_lines + 1}:" in first and "undeclared_name" in first, why


@needs_cc
def test_a_prebuilt_library_is_used_only_for_its_sources_flags_and_a_cpu_that_runs_it(tmp_path, monkeypatch):
    pre = tmp_path / "prebuilt"
    assert "built" in prebuild("raygen", pre)
    man = json.loads((pre / "raygen.json").read_text())
    assert man["file"] == "raygen.so" and man["flags"] == list(LIBRARIES["raygen"][1])
    monkeypatch.setattr(_native, "PREBUILT_DIR", pre)
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path / "empty-cache"))
    monkeypatch.setenv("CC", str(tmp_path / "no-compiler"))  # only the prebuilt library can answer
    names, flags = LIBRARIES["raygen"]
    sig = {"prt_count_up": [ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]}
    lib, how = compile_library("raygen", kernel_sources(names), list(flags), sig)
    assert lib is not None and "prebuilt at install time" in how, how
    # it runs: counts of cos > 0 per row, against numpy
    import numpy as np
    cos = np.array([[0.5, -1.0, 0.0, 2.0], [1.0, 1.0, 1.0, -0.1]])
    counts = np.zeros(2, np.int64)
    assert lib.prt_count_up(2, 4, cos.ctypes.data, counts.ctypes.data, 1) == 0
    assert counts.tolist() == (cos > 0).sum(1).tolist()
    # another source, other flags, a CPU without one of the builder's ISA flags, or PRT_TORCH_PREBUILT=0: not used
    edited = kernel_sources(names)
    edited["raygen.c"] += "\n/* edited */\n"
    assert compile_library("raygen", edited, list(flags), sig)[0] is None
    assert compile_library("raygen", kernel_sources(names), [*flags, "-O2"], sig)[0] is None
    man["isa"] = [*man["isa"], "a-flag-no-cpu-has"]
    (pre / "raygen.json").write_text(json.dumps(man))
    assert compile_library("raygen", kernel_sources(names), list(flags), sig)[0] is None
    man["isa"] = man["isa"][:-1]
    (pre / "raygen.json").write_text(json.dumps(man))
    monkeypatch.setenv("PRT_TORCH_PREBUILT", "0")
    lib, how = compile_library("raygen", kernel_sources(names), list(flags), sig)
    assert lib is None and "did not run" in how
