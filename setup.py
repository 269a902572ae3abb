"""The package layout: each top-level folder of the repository is a part of the one
``hlbvh`` import namespace, and every sub-package under it is found, not listed."""

from setuptools import find_packages, setup

ROOTS = {"hlbvh": "plugin", "hlbvh.kernels": "kernels", "hlbvh.scenes": "scenes",
         "hlbvh.comparison": "comparison"}

packages = []
for name, folder in ROOTS.items():
    packages += [name] + [f"{name}.{sub}" for sub in find_packages(folder)]

setup(packages=packages, package_dir=ROOTS)
