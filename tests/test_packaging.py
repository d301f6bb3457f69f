"""What `pip install` puts into site-packages: irdepth_jax with every subpackage, and the folder
experiments/ under a name of its own (irdepth_experiments; a top-level `experiments` would collide
with other projects'), which the library never imports and which refuses to run outside a checkout."""

import ast
import importlib.util
import os
import pathlib
import shutil
import tomllib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent


def package_folders(folder: str) -> list[str]:
    """Dotted names of ROOT/folder and of the folders below it that are packages (an __init__.py,
    in a package)."""
    names = []
    for dirpath, dirnames, filenames in os.walk(ROOT / folder):
        if "__init__.py" not in filenames:
            dirnames.clear()
            continue
        names.append(os.path.relpath(dirpath, ROOT).replace(os.sep, "."))
    return names


def test_pyproject_lists_every_package_and_installs_experiments_as_irdepth_experiments():
    with open(ROOT / "pyproject.toml", "rb") as f:
        setuptools = tomllib.load(f)["tool"]["setuptools"]
    assert setuptools["package-dir"] == {"irdepth_experiments": "experiments"}
    experiments = ["irdepth_" + name for name in package_folders("experiments")]
    assert experiments == ["irdepth_experiments"]  # results/ holds outputs, not code
    assert sorted(setuptools["packages"]) == sorted(package_folders("irdepth_jax") + experiments)


def test_the_library_imports_no_experiment():
    offenders = []
    for path in (ROOT / "irdepth_jax").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([node.module or ""] if isinstance(node, ast.ImportFrom)
                     else [a.name for a in node.names] if isinstance(node, ast.Import) else [])
            offenders += [f"{path.relative_to(ROOT)}: {name}" for name in names
                          if name.split(".")[0] in ("experiments", "irdepth_experiments")]
    assert offenders == []


def test_a_copy_outside_a_checkout_refuses_to_import(tmp_path):
    """`pip install .` copies the package into site-packages, away from the results/ and git
    history the experiments write to: importing it there fails with the remedy."""
    installed = tmp_path / "site-packages" / "irdepth_experiments"
    installed.mkdir(parents=True)
    shutil.copy(ROOT / "experiments" / "__init__.py", installed)
    spec = importlib.util.spec_from_file_location("copied_experiments", installed / "__init__.py")
    with pytest.raises(ImportError, match=r"not in a source checkout.*pip install -e \."):
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
