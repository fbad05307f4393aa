"""Builds the C++ rasterizer (mipslam/render/cpu/raster_ext.cpp) when mipslam is installed; everything else
is in pyproject.toml. The recipe is mipslam/render/cpu/build.py (standard library only, so the build needs
neither torch nor pybind11: the libraries have a C interface that mipslam loads with ctypes). The libraries
are optional: without a C++ compiler the install succeeds with a warning and mipslam renders with torch."""
import importlib.util
import os
import shutil
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CompileError

_spec = importlib.util.spec_from_file_location(
    "_mipslam_cpu_build", Path(__file__).resolve().parent / "mipslam" / "render" / "cpu" / "build.py")
cpu_build = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(cpu_build)


class BuildRasterizer(build_ext):
    """Compile each ISA's library with build.py's recipe (both at once) instead of setuptools' Python-module
    recipe; the libraries are plain shared objects named like extension modules of this interpreter."""

    def finalize_options(self):
        super().finalize_options()
        if not self.parallel:
            self.parallel = len(self.extensions)  # one compiler per ISA

    def build_extension(self, ext):
        isa = ext.name.rsplit(cpu_build.LIBRARY_STEM, 1)[1]
        try:
            cpu_build.compile_library(isa, Path(self.get_ext_fullpath(ext.name)))
        except cpu_build.BuildError as exc:
            raise CompileError(str(exc)) from None

    def copy_extensions_to_source(self):
        """Editable installs: install each library next to its sources by an atomic rename (a running mipslam
        keeps the file it mapped; setuptools' copy would rewrite that file under it)."""
        build_py = self.get_finalized_command("build_py")
        for ext in self.extensions:
            inplace_file, regular_file = self._get_inplace_equivalent(build_py, ext)
            if os.path.exists(regular_file):  # an optional library that failed to build is skipped
                partial = f"{inplace_file}.partial"
                shutil.copyfile(regular_file, partial)
                os.replace(partial, inplace_file)


setup(
    ext_modules=[Extension(f"mipslam.render.cpu.{cpu_build.LIBRARY_STEM}{isa}",
                           sources=[f"mipslam/render/cpu/{name}" for name in cpu_build.SOURCES],
                           depends=[f"mipslam/render/cpu/{name}" for name in cpu_build.HEADERS],
                           optional=True)
                 for isa in cpu_build.isas()],
    cmdclass={"build_ext": BuildRasterizer},
)
