"""Shared fixtures: small canonical grids and helpers."""

from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import settings

settings.register_profile("ci", max_examples=40, deadline=None, derandomize=True)
settings.register_profile("dev", max_examples=40, deadline=None)
settings.load_profile(os.environ.get("TFI_QUAT_HYPOTHESIS", "ci"))


def sheared_box(ni=5, nj=4, nk=3, seed=0):
    """A sheared, slightly warped 3-D box, float64 Fortran order ``(ni, nj, nk, 3)``."""
    i, j, k = np.meshgrid(np.linspace(0, 1, ni), np.linspace(0, 1, nj), np.linspace(0, 1, nk),
                          indexing="ij")
    x = 2.0 * i + 0.3 * j + 0.05 * np.sin(3 * k)
    y = 1.5 * j + 0.2 * k + 0.02 * i * i
    z = 1.0 * k + 0.1 * i * j
    return np.asfortranarray(np.stack([x, y, z], axis=-1))


def annulus(ni=9, nj=5, r0=1.0, r1=3.0, theta=np.pi / 2):
    """A 2-D annulus sector ``(ni, nj, 1, 3)``: i around, j outwards, z = 0."""
    t = np.linspace(0.0, theta, ni)[:, None]
    r = np.geomspace(r0, r1, nj)[None, :]
    xyz = np.zeros((ni, nj, 1, 3), order="F")
    xyz[:, :, 0, 0] = r * np.cos(t)
    xyz[:, :, 0, 1] = r * np.sin(t)
    return xyz


@pytest.fixture
def box_xyz():
    return sheared_box()


@pytest.fixture
def annulus_xyz():
    return annulus()
