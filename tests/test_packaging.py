"""What a wheel carries: the package data that pyproject.toml lists holds every built-in config, so an installed
mipslam runs ``mipslam run tum`` and ``--preset fast`` without this checkout. Reads setuptools' own file list
(build_py, nothing built); scripts/check_wheel builds and installs a real wheel (CI)."""
from __future__ import annotations

from pathlib import Path

import pytest

from mipslam.config import CONFIG_DIR, builtin_config_names

REPO = Path(__file__).resolve().parent.parent


def _package_data_files(monkeypatch) -> set[Path]:
    """The data files setuptools puts in the wheel beside the modules (pyproject.toml's package-data), absolute."""
    pytest.importorskip("setuptools")
    from setuptools.config.pyprojecttoml import apply_configuration
    from setuptools.dist import Distribution

    monkeypatch.chdir(REPO)  # setuptools reads package folders relative to the working directory
    dist = apply_configuration(Distribution(), REPO / "pyproject.toml")
    dist.include_package_data = False  # only the declared package-data (no MANIFEST.in; nothing written)
    build_py = dist.get_command_obj("build_py")
    build_py.ensure_finalized()
    return {(REPO / src / name).resolve() for _, src, _, names in build_py.data_files for name in names}


def test_the_package_data_holds_every_built_in_config(monkeypatch):
    files = _package_data_files(monkeypatch)
    configs = sorted(CONFIG_DIR.glob("*.yaml"))
    assert {p.stem for p in configs} == set(builtin_config_names()) and len(configs) >= 7
    missing = [p.name for p in configs if p.resolve() not in files]
    assert not missing, f"not in pyproject.toml's package-data, so not in a wheel: {missing}"
    # the C++ sources the install compiles travel too (an sdist, a rebuild: python -m mipslam.render.cpu.build)
    assert (REPO / "mipslam" / "render" / "cpu" / "raster_ext.cpp").resolve() in files


def test_the_built_in_configs_live_inside_the_package():
    assert CONFIG_DIR.parent == REPO / "mipslam"
    assert not (REPO / "configs").exists(), "configs/ beside the package would not be in a wheel"
    for path in CONFIG_DIR.glob("*.yaml"):
        values = [line.split("#", 1)[0] for line in path.read_text(encoding="utf-8").splitlines()]
        # nothing outside the package folder: an installed package has no checkout around it
        assert not [v for v in values if "../" in v or "shared/data" in v], path
