"""Every example in the package's docstrings runs and prints what it shows (as scikit-image's
do): an example that drifts from the code is a wrong manual page."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import evseg


# The stage folders sit at the repository's top and install as subpackages of evseg
# (pyproject.toml, package-dir), so walking evseg's own folder does not reach them.
_PACKAGES = ("evseg", "evseg.veckm_flow", "evseg.segmentation", "evseg.train", "evseg.export")


def _modules() -> list[str]:
    names = set()
    for pkg in _PACKAGES:
        mod = importlib.import_module(pkg)
        names.add(pkg)
        names.update(m.name for m in pkgutil.walk_packages(mod.__path__, pkg + "."))
    return sorted(names)


def test_the_package_has_examples():
    finder = doctest.DocTestFinder()
    n = sum(len(t.examples) for name in _modules() for t in finder.find(importlib.import_module(name)))
    assert n >= 55  # 59 examples on 2026-11-24; fewer means examples were lost


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples(name):
    module = importlib.import_module(name)
    failures, _ = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS,
                                  report=True, verbose=False)
    assert failures == 0, f"{name}: {failures} docstring example(s) failed (see the output above)"
