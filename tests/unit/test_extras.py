"""common.extras: an optional package is imported where it is used, and a missing one is a
one-line error naming the pyproject extra that brings it."""

from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib
from pathlib import Path

import pytest

from common.errors import UserError
from common.extras import Extra, MissingExtraError, require

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def test_installed_module_is_returned() -> None:
    assert require("json", Extra.DATA, "a test") is sys.modules["json"]


def test_missing_module_names_the_extra() -> None:
    with pytest.raises(MissingExtraError) as caught:
        require("elasticfog_no_such_package.data", Extra.DATA, "the photographs")
    message = str(caught.value)
    assert isinstance(caught.value, UserError) and "\n" not in message
    assert message.startswith("the photographs: ") and "'data' extra" in message
    assert "pip install scikit-image" in message and "[" not in message  # rich markup


def test_a_missing_dependency_of_an_installed_package_is_not_reworded(tmp_path: Path) -> None:
    (tmp_path / "efx_present").mkdir()
    (tmp_path / "efx_present" / "__init__.py").write_text("import efx_absent_dependency\n")
    sys.path.insert(0, str(tmp_path))
    try:
        with pytest.raises(ModuleNotFoundError, match="efx_absent_dependency"):
            require("efx_present", Extra.PLOTS, "a plot")
    finally:
        sys.path.remove(str(tmp_path))


def test_every_extra_is_in_pyproject_with_its_package() -> None:
    extras = tomllib.loads(PYPROJECT.read_text())["project"]["optional-dependencies"]
    assert any(r.startswith("matplotlib") for r in extras[Extra.PLOTS.value])
    assert any(r.startswith("scikit-image") for r in extras[Extra.DATA.value])
    runtime = tomllib.loads(PYPROJECT.read_text())["project"]["dependencies"]
    for heavy in ("matplotlib", "scikit-image", "torch"):
        assert not any(r.startswith(heavy) for r in runtime), f"{heavy} is not a runtime dependency"
