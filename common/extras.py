"""Optional dependencies: the pyproject extras a feature needs, imported where it is used.

A robot, a cloud host or the image installs the runtime lock only, without plotting or sample data;
the features that need one (a plot, the real photographs, the stereo pair) import it through
`require`, which says in one line which extra to install when it is missing.
"""

from __future__ import annotations

import importlib
from enum import Enum
from types import ModuleType

from common.errors import UserError


class Extra(str, Enum):
    """The optional-dependency groups of pyproject.toml that a runtime path can need."""

    PLOTS = "plots"  # matplotlib
    DATA = "data"  # scikit-image: the photographs and the stereo pair it ships


# The distribution each extra brings (pip's name; the message avoids `elasticfog[...]` because
# the CLI prints errors through rich, which reads square brackets as markup).
DISTRIBUTION = {Extra.PLOTS: "matplotlib", Extra.DATA: "scikit-image"}


class MissingExtraError(UserError):
    """A feature needs a package of an extra that is not installed."""


def require(module: str, extra: Extra, feature: str) -> ModuleType:
    """Import `module`; if its distribution is missing, a one-line error naming `extra`."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".", 1)[0]
        if exc.name is None or exc.name.split(".", 1)[0] != top:
            raise  # the package is there but something it imports is not: not ours to reword
        raise MissingExtraError(
            f"{feature}: {top} is not installed; it comes with elasticfog's {extra.value!r} "
            f"extra (requirements/dev.lock has it, or pip install {DISTRIBUTION[extra]})"
        ) from None
