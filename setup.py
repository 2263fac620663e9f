"""Packages for setuptools; the metadata is in pyproject.toml.

Every package under ``tfi_quat/`` is found, and the checkout's ``grids/`` folder
(sample grids and case files) is installed as ``tfi_quat/grids`` so that the
demo and the tutorials find it after a regular ``pip install .``
(``tfi_quat.demo.sample_path``).  ``tests/test_install.py`` builds the wheel and
checks both.
"""

from setuptools import find_packages, setup

setup(packages=find_packages(include=["tfi_quat", "tfi_quat.*"]) + ["tfi_quat.grids"],
      package_dir={"tfi_quat.grids": "grids"})
