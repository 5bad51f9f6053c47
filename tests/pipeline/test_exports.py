"""Package exports: every name in ``__all__`` resolves to its module's object, and importing a package
loads none of its modules (no dask, matplotlib or GDAL vector stack at ``import pipeline.prior``)."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

PACKAGES = ["common", "pipeline.gis", "pipeline.features", "pipeline.prior", "pipeline.config",
            "pipeline.build", "pipeline.show", "pipeline.tiled"]


@pytest.mark.parametrize("name", PACKAGES)
def test_every_export_resolves_to_its_definition(name: str) -> None:
    pkg = importlib.import_module(name)
    assert pkg.__all__, name
    for export in pkg.__all__:
        value = getattr(pkg, export)
        module = importlib.import_module(f"{name}.{pkg._EXPORTS[export]}")
        assert value is getattr(module, export), (name, export)
    assert set(pkg.__all__) <= set(dir(pkg))
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        pkg.nope  # noqa: B018


def test_package_imports_are_light() -> None:
    code = (
        "import sys, common, pipeline.gis, pipeline.features, pipeline.prior, pipeline.config, pipeline.build, "
        "pipeline.show, pipeline.tiled\n"
        "from pipeline.prior import TerrainPrior, sat_rect\n"
        "heavy = [m for m in ('distributed', 'dask', 'matplotlib', 'sklearn', 'pyogrio', 'shapely') if m in sys.modules]\n"
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
