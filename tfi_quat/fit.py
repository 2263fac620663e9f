"""Rigid motions fitted to moved point sets (least squares), with plane constraints.

Used by the two-level Deformer: each wall body's motion is split into the
rigid motion that fits it best (applied to the whole field, Samareh's way) and
the residual deformation (applied near the walls).  docs/method.md §3.6: the fit is
frame-invariant, so the result translates and rotates with the problem.

Conventions: quaternions scalar first ``(w, x, y, z)``; a rigid motion maps
``x -> rot(q, x) + t``.
"""

from __future__ import annotations

import numpy as np

from . import quaternion as qa

__all__ = ["fit_rigid", "rigid_from_moments", "constrain_to_planes"]


def _plane_basis(n: np.ndarray):
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def constrain_to_planes(normals) -> tuple:
    """What rigid motions keep every plane of these normals in place.

    Parameters
    ----------
    normals : sequence of (3,) unit vectors

    Returns
    -------
    axis : ndarray (3,) or None
        The only rotation axis allowed (all normals parallel), None for any
        axis (no planes), or a zero vector for no rotation at all.
    tproj : ndarray (3, 3)
        Projection that removes the forbidden translation components.
    """
    ns = [np.asarray(n, dtype=np.float64) / np.linalg.norm(n) for n in normals]
    if not ns:
        return None, np.eye(3)
    basis = []
    for n in ns:
        v = n - sum((n @ b) * b for b in basis)
        if np.linalg.norm(v) > 1e-8:
            basis.append(v / np.linalg.norm(v))
    proj = np.eye(3) - sum(np.outer(b, b) for b in basis)
    axis = basis[0] if len(basis) == 1 else np.zeros(3)
    return axis, proj


def fit_rigid(pu, pd, axis=None, tproj=None):
    """Least-squares rigid motion taking points ``pu`` to ``pd``.

    Parameters
    ----------
    pu, pd : ndarray, shape (n, 3)
        Points before and after the motion.
    axis : (3,) array, optional
        Allowed rotation axis (unit), or a zero vector for translation only;
        None: any rotation (Kabsch's SVD solution, reflections excluded).
    tproj : (3, 3) array, optional
        Projection applied to the translation (forbidden directions removed).

    Returns
    -------
    q : ndarray (4,)
        Unit quaternion, ``w >= 0``.
    t : ndarray (3,)
        Translation: ``pd ~ rot(q, pu) + t``.
    """
    pu = np.asarray(pu, dtype=np.float64)
    pd = np.asarray(pd, dtype=np.float64)
    cu = pu.mean(axis=0)
    cd = pd.mean(axis=0)
    return rigid_from_moments(cu, cd, (pu - cu).T @ (pd - cd), axis, tproj)


def rigid_from_moments(cu, cd, h, axis=None, tproj=None):
    """The least-squares rigid motion of :func:`fit_rigid` from the point sets' moments:
    centroids ``cu``, ``cd`` (3,) and cross-covariance ``h = sum (pu - cu)(pd - cd)^T``
    (3, 3), so that the sums may be taken over a partition of the points (the two-level
    Deformer sums per wall patch, :func:`tfi_quat.deform.twolevel.fit_bodies`).  Returns
    ``(q, t)`` as :func:`fit_rigid`."""
    cu = np.asarray(cu, dtype=np.float64)
    cd = np.asarray(cd, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    if axis is None:
        u, _, vt = np.linalg.svd(h)
        dd = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
        r = vt.T @ np.diag([1.0, 1.0, dd]) @ u.T
        q = qa.normalize(qa.from_matrix(r))
        if q[0] < 0.0:
            q = -q
    elif not np.any(axis):
        q = np.array([1.0, 0.0, 0.0, 0.0])
    else:
        n = np.asarray(axis, dtype=np.float64)
        e1, e2 = _plane_basis(n)
        # sum a1 b2 - a2 b1 and sum a1 b1 + a2 b2 (a1 = a . e1, ...) from h
        sin_ = float(e1 @ h @ e2 - e2 @ h @ e1)
        cos_ = float(e1 @ h @ e1 + e2 @ h @ e2)
        if sin_ == 0.0 and cos_ == 0.0:
            q = np.array([1.0, 0.0, 0.0, 0.0])
        else:
            half = 0.5 * np.arctan2(sin_, cos_)
            q = np.concatenate([[np.cos(half)], np.sin(half) * n])
    t = cd - qa.rotate(q, cu)
    if tproj is not None:
        t = np.asarray(tproj) @ t
    return q, t
