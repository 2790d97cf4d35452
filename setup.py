"""The compiled kernels are accelerators: without a working C compiler or Python's headers gravcal installs
without them (one line says why) and runs the numpy references beside them (core/accelerator.py); only
gravcald's per-sample engine needs them. The extensions themselves are listed in pyproject.toml."""
import os
import sys
import tempfile

from setuptools import setup
from setuptools.command.build_ext import build_ext


def _compiles(compiler, source: str, include_dirs: list[str]) -> bool:
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "probe.c")
        with open(path, "w") as f:
            f.write(source)
        try:
            compiler.compile([path], output_dir=tmp, include_dirs=include_dirs)
        except Exception:  # noqa: BLE001 - any failure of the toolchain means: no extensions
            return False
    return True


class OptionalBuildExt(build_ext):
    """build_ext that first checks the toolchain once and, without one, builds nothing and says so in one line."""

    def build_extensions(self):
        include = list(self.include_dirs or [])
        cc = " ".join(self.compiler.compiler_so[:1]) if getattr(self.compiler, "compiler_so", None) else "cc"
        problem = None
        if not _compiles(self.compiler, "int main(void) { return 0; }\n", include):
            problem = f"no working C compiler ({cc})"
        elif not _compiles(self.compiler, "#include <Python.h>\n", include):
            problem = "no Python headers (Python.h: e.g. apt install python3-dev)"
        if problem:
            sys.stderr.write(f"gravcal: {problem}: installing without the compiled accelerators (the numpy forms "
                             f"calibrate; gravcald needs them)\n")
            self.extensions = []
            return
        super().build_extensions()


setup(cmdclass={"build_ext": OptionalBuildExt})
