"""benchmarks/ab_kernels.py, the paired A/B of two revisions' relight kernels: at a small point
count it builds the kernels, measures every view mode of the chosen settings and reports equal
results (maxdiff 0) and finite ratios for equal sources; bad options are refused, naming them."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "benchmarks" / "ab_kernels.py"


def _run(*args, tmp):
    return subprocess.run([sys.executable, str(TOOL), "--base", ".", "--test", ".", "--points", "1000", "--repeats", "3",
                           "--cache", str(tmp), *args], capture_output=True, text=True, cwd=ROOT, timeout=600)


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
@pytest.mark.parametrize("shape, only, rows", [("relight", "mrt_pca,gaussian 1", 5), ("diffuse", "pca 8", 1)])
def test_each_shape_measures_its_settings(shape, only, rows, tmp_path):
    r = _run("--shape", shape, "--only", only, tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    table = [line for line in r.stdout.splitlines() if line.startswith("| ") and "**" in line]
    assert len(table) == rows, r.stdout
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[-1] == "0.0e+00", line  # the same source: the same bits
        assert 0.2 < float(cells[-2].split("**")[1]) < 5, line  # a measured ratio, not a placeholder


def test_bad_options_are_refused_naming_them(tmp_path):
    r = subprocess.run([sys.executable, str(TOOL), "--points", "10"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and "--points 10; accepted: an integer >= 64" in r.stderr
    r = subprocess.run([sys.executable, str(TOOL), "--threads", "0"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and "--threads '0'; accepted: positive integers" in r.stderr
    r = subprocess.run([sys.executable, str(TOOL), "--clock", "cpu", "--threads", "1,2"], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode != 0 and "--clock cpu with --threads '1,2'; accepted: --threads 1" in r.stderr


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
def test_cpu_clock_pairs_by_thread_time(tmp_path):
    """--clock cpu times both sides by the thread's CPU time (one thread): the table says so, and equal
    sources give equal bits and a finite ratio."""
    r = _run("--shape", "diffuse", "--only", "vq", "--clock", "cpu", tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "CPU time (time.thread_time)" in r.stdout
    table = [line for line in r.stdout.splitlines() if line.startswith("| ") and "**" in line]
    assert len(table) == 1 and table[0].strip("|").split("|")[-1].strip() == "0.0e+00", r.stdout
    assert 0.2 < float(table[0].split("**")[1]) < 5, table


def _cpu_has(flag: str) -> bool:
    try:
        return any(line.startswith("flags") and f" {flag} " in line + " " for line in Path("/proc/cpuinfo").read_text().splitlines())
    except OSError:
        return False


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not _cpu_has("avx"), reason="needs an x86-64 CPU with AVX (-march=native then differs from the baseline ISA)")
def test_a_source_built_only_by_the_fallback_flags_is_refused(monkeypatch, tmp_path):
    """A kernel source that fails under its own flags but compiles without ``-march=native`` (the library's
    fallback for users) must not be A/B'd: it would time another instruction set (this once hid a
    typo in a macro behind a 6x "slow-down")."""
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path))  # a fresh kernel cache: build, don't load
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import ab_kernels
        from prt_torch._native import kernel_sources
        from prt_torch.codecs import relight_kernels as rk
        src = kernel_sources(rk._SOURCES)
        src["relight_plan.c"] += "\n#ifdef __AVX__\n#error built with -march=native\n#endif\n"
        with pytest.raises(SystemExit, match="compiled only with other flags"):
            ab_kernels.compile_source((src, list(rk._FLAGS)), "broken")
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def _has_revision(rev: str) -> bool:
    return subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{rev}^{{commit}}"], capture_output=True).returncode == 0


def test_stubs_only_for_the_entry_points_a_source_lacks():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import ab_kernels
        old = ({"relight.c": "int prt_affine_rows(void) { return 0; }\n"}, ["-O3"])
        (src, flags), added = ab_kernels.with_stubs(old)
        assert added == ["prt_plan_path", "prt_isa"] and flags == ["-O3"]
        assert src["relight.c"] == old[0]["relight.c"] and "int prt_isa(void)" in src["ab_stubs.c"]
        has = ({"a.c": "int prt_plan_path(const i64 *a) { return 1; }\nint prt_isa(void) { return 2; }\n"}, [])
        assert ab_kernels.with_stubs(has) == (has, [])
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not (ROOT / ".git").exists() or not _has_revision("332b8d2"), reason="needs the history back to 332b8d2")
def test_a_revision_with_other_python_runs_only_when_accepted(tmp_path):
    """332b8d2 (the kernels as one string, before the path reporting) is refused by default; with
    --accept-python-diff its Python difference is printed, the entry points it lacks are stubbed and its
    kernels give the working tree's bits on the diffuse PCA row."""
    r = _run("--base", "332b8d2", "--shape", "diffuse", "--only", "pca 8", tmp=tmp_path)
    assert r.returncode != 0 and "differs between '332b8d2' and the working tree" in r.stderr
    r = _run("--base", "332b8d2", "--shape", "diffuse", "--only", "pca 8", "--accept-python-diff", tmp=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "+def kernel_path(" in r.stderr and "lacks prt_plan_path, prt_isa: stubs" in r.stderr
    table = [line for line in r.stdout.splitlines() if line.startswith("| ") and "**" in line]
    assert len(table) == 1 and table[0].strip("|").split("|")[-1].strip() == "0.0e+00", r.stdout


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
@pytest.mark.skipif(not _cpu_has("avx512f") or not _cpu_has("avx512vl"), reason="needs AVX-512 (the avx2 build is then another ISA)")
def test_the_kernel_isa_choice_is_the_builds_own_flags(tmp_path):
    """PRT_TORCH_KERNEL_ISA=avx2 adds -mno-avx512f to both sides' flags (_compile): that build is accepted (it
    was refused as 'compiled only with other flags'), and the table names the choice."""
    env = {**os.environ, "PRT_TORCH_KERNEL_ISA": "avx2"}
    r = subprocess.run([sys.executable, str(TOOL), "--base", ".", "--test", ".", "--points", "1000", "--repeats", "3", "--cache",
                        str(tmp_path), "--shape", "diffuse", "--only", "pca 8"], capture_output=True, text=True, cwd=ROOT,
                       timeout=600, env=env)
    assert r.returncode == 0, r.stderr
    assert "PRT_TORCH_KERNEL_ISA=avx2" in r.stdout
