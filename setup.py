"""Package discovery for threedq's layout (everything else is in ``pyproject.toml``).

The importable packages are found, never listed: ``threedq/`` and each of its sub-packages, plus the folders at
the top of the repository that install inside the ``threedq`` namespace (``stages/`` -> ``threedq.stages``,
``datamodules/`` -> ``threedq.datamodules``, ``configs/`` -> ``threedq.configs``, YAML only). A package added to
any of them ships without a change here; ``tests/test_packaging.py`` checks the built wheel against the tree.
"""

import os

from setuptools import find_namespace_packages, find_packages, setup

# top-level folder -> the package it installs as; each keeps the design card's place in the repository, and no
# top-level ``stages`` or ``datamodules`` package is put into site-packages.
MAPPED = {"threedq.stages": "stages", "threedq.datamodules": "datamodules", "threedq.configs": "configs"}


def discover(root: str = ".") -> tuple[list[str], dict[str, str]]:
    """``(packages, package_dir)`` of the tree at ``root`` (``package_dir`` relative to it)."""
    packages = find_packages(where=root, include=["threedq", "threedq.*"])
    package_dir: dict[str, str] = {}
    for name, folder in MAPPED.items():
        finder = find_namespace_packages if name == "threedq.configs" else find_packages
        for sub in ["", *("." + p for p in finder(where=os.path.join(root, folder)))]:
            packages.append(name + sub)
        package_dir[name] = folder
    return packages, package_dir


if __name__ == "__main__":  # how setuptools runs this file; importing it (tests/test_packaging.py) only defines
    packages, package_dir = discover()
    setup(packages=packages, package_dir=package_dir)
