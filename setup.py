"""Packaging hook: ``pip install .`` compiles the C kernels ahead of time when the build machine has
a C compiler (everything else is in pyproject.toml).

Chosen over a setuptools ``Extension``: the kernels are plain C libraries called through ctypes
(no Python C API), built with ``-march=native`` and OpenMP, and keyed on the CPU that built them;
an Extension would make them part of the wheel's ABI tag and fail the install where no compiler
exists. Here the library is an optional extra: :func:`prt_torch._native.prebuild` writes
``prt_torch/kernels/prebuilt/<name>.so`` and a manifest (the sources' and flags' hash, the
building CPU's instruction-set flags); at run time it is loaded only when both match (a wheel
carried to another CPU compiles at run time instead). Without a compiler, or when the compile fails,
the install still succeeds and the kernels compile on first use (or the torch path runs).
Editable installs (``pip install -e``, as scripts/setup does) skip it: there the sources are meant
to change. ``PRT_TORCH_PREBUILD=0`` skips it too.
"""
import importlib.util
import os
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


class BuildPyWithKernels(build_py):
    def run(self):
        super().run()
        if getattr(self, "editable_mode", False) or os.environ.get("PRT_TORCH_PREBUILD", "1") == "0":
            return
        # _native imports only the standard library, so it loads without torch in the build environment
        spec = importlib.util.spec_from_file_location("_prt_torch_native", HERE / "prt_torch" / "_native.py")
        native = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(native)
        out = Path(self.build_lib) / "prt_torch" / "kernels" / "prebuilt"
        for name in native.LIBRARIES:
            try:
                print(f"prt_torch: {native.prebuild(name, out, HERE / 'prt_torch' / 'kernels')}")
            except (RuntimeError, OSError) as e:
                print(f"prt_torch: the {name} kernels were not built ahead of time ({e}); they compile on first use",
                      file=sys.stderr)


setup(cmdclass={"build_py": BuildPyWithKernels})
