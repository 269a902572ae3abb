"""Rigid-body motion of many bodies at once: random axes and vectorised rotations."""

from __future__ import annotations

import numpy as np


def random_unit_vectors(rng: np.random.Generator, count: int) -> np.ndarray:
    """``(count, 3)`` directions uniform on the unit sphere."""
    z = rng.uniform(-1.0, 1.0, count)
    phi = rng.uniform(0.0, 2 * np.pi, count)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def rotate(points: np.ndarray, axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Each row of ``points`` ``(N, 3)`` turned by ``angles`` ``(N,)`` radians about
    the unit ``axes`` ``(N, 3)`` of the same row (Rodrigues' formula)."""
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
    along = np.einsum("ij,ij->i", axes, points)[:, None]
    return points * cos + np.cross(axes, points) * sin + axes * along * (1.0 - cos)


def rotation_matrices(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``(K, 3, 3)`` matrices turning by ``angles`` ``(K,)`` about unit ``axes``
    ``(K, 3)``: the same rotation as :func:`rotate`, for bodies of many vertices."""
    eye = np.broadcast_to(np.eye(3), (len(angles), 3, 3))
    return np.stack([rotate(eye[:, :, k], axes, angles) for k in range(3)], axis=2)


def affines(linear: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(K, 4, 4)`` affine matrices of ``(K, 3, 3)`` linear parts and ``(K, 3)``
    translations."""
    m = np.zeros((len(linear), 4, 4))
    m[:, :3, :3], m[:, :3, 3], m[:, 3, 3] = linear, translation, 1.0
    return m
