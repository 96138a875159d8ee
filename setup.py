"""Packaging hook (the metadata is in pyproject.toml): ships the repository's top-level assets/ (MJCF models, detector
presets, fitted dynamics) inside the package as specguard_jax/_assets, read through specguard_jax.assets.

pyproject.toml cannot list a package found by `packages.find` next to one mapped from another directory, so both are
given here; the package-data patterns of pyproject.toml apply to them all (envs/data's mission files included)."""

from setuptools import find_namespace_packages, setup

setup(packages=find_namespace_packages(include=["specguard_jax*", "envs*"], exclude=["*__pycache__"])
      + ["specguard_jax._assets"],
      package_dir={"specguard_jax._assets": "assets"})
