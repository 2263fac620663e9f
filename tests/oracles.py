"""Independent references for the TFI tests: a plain numpy Soni TFI.

Not part of the package: the compiled kernels of :mod:`tfi_quat.tfi` are
tested against these.  :func:`tfi_block_fields` forms the full-size (Δ, Q)
fields of a block by the recursive Boolean sum of docs/method.md §3.4 (slerp
in the leading direction, hemisphere-aligned corrections, normalised, with
the rotation-vector fallback where the blended norm is below
``tfi.QNORM_MIN``); :func:`tfi_patch` does the same on a 2-D patch, in place.
Inputs are validated with the package's own checks, so the references see
exactly the arrays the kernels see.
"""

from __future__ import annotations

import numpy as np

from tfi_quat import quaternion as qa
from tfi_quat import tfi


def coherent(q):
    """Flip signs in place so that neighbouring quaternions of a face (na, nb, 4) share a
    hemisphere (each point against the previous one along a, or along b on a = 0)."""
    na, nb = q.shape[0], q.shape[1]
    for b in range(nb):
        for a in range(na):
            if a == 0 and b == 0:
                continue
            pa, pb = (a - 1, 0) if b == 0 else (a, b - 1)
            if float(np.dot(q[a, b], q[pa, pb])) < 0.0:
                q[a, b] = -q[a, b]


def np_rel_log(base, q):
    """log(conj(base) ⊗ q), q in base's hemisphere; (..., 4) -> (..., 3)."""
    p = qa.multiply(base * np.array([1.0, -1.0, -1.0, -1.0]), q)
    p = np.where(p[..., :1] < 0.0, -p, p)
    n = np.linalg.norm(p[..., 1:], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(n > 1e-30, np.arctan2(n, p[..., 0]) / np.where(n > 1e-30, n, 1.0),
                     np.where(p[..., 0] > 0.0, 1.0 / np.where(p[..., 0] > 0.0, p[..., 0], 1.0), 0.0))
    return p[..., 1:] * f[..., None]


def np_exp_times(base, r):
    th = np.linalg.norm(r, axis=-1)
    e = np.empty(r.shape[:-1] + (4,))
    e[..., 0] = np.cos(th)
    e[..., 1:] = r * np.sinc(th / np.pi)[..., None]
    out = qa.multiply(base, e)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def np_normalize_or_fallback(W, base, terms):
    """Normalise W (..., 4); where |W| < tfi.QNORM_MIN use the rotation-vector Boolean sum."""
    n = np.linalg.norm(W, axis=-1)
    out = W / np.maximum(n, tfi.QNORM_MIN)[..., None]
    bad = n < tfi.QNORM_MIN
    if np.any(bad):
        b = base[bad]
        b = b / np.linalg.norm(b, axis=-1, keepdims=True)
        r = np.zeros(b.shape[:-1] + (3,))
        for w, F, U in terms:
            wb = np.broadcast_to(w, bad.shape)[bad]
            Fb = np.broadcast_to(F, bad.shape + (4,))[bad]
            Ub = np.broadcast_to(U, bad.shape + (4,))[bad]
            r += wb[:, None] * (np_rel_log(b, Fb) - np_rel_log(b, Ub))
        out[bad] = np_exp_times(b, r)
    return out


def fields_ref(fd, fq, s, order):
    """Plain numpy Boolean-sum TFI on a block; fd/fq face arrays (normal d removed), s (..., 3)."""
    dims = s.shape[:3]
    nd = len(order)

    def bcf(face, d):
        if nd == 2:            # 2-D faces are (n, 1, c): insert the missing direction
            face = face[:, 0, :]
            return np.expand_dims(np.expand_dims(face, d), 2)
        return np.expand_dims(face, d)

    sl = [np.asarray(s[..., d], dtype=np.float64)[..., None] for d in range(3)]
    L = order[0]
    D = (1.0 - sl[L]) * bcf(fd[2 * L], L) + sl[L] * bcf(fd[2 * L + 1], L)
    Q = None
    if fq is not None:
        q0 = np.array(fq[2 * L], order="F", copy=True)
        coherent(q0)
        a = np.broadcast_to(bcf(q0, L), dims + (4,))
        b = np.broadcast_to(bcf(fq[2 * L + 1], L), dims + (4,))
        Q = qa.slerp(a, b, np.broadcast_to(sl[L][..., 0], dims))
        base = Q.copy()
        terms = []
    for step, d in enumerate(order[1:]):
        w = sl[d]
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[d] = slice(0, 1)
        hi[d] = slice(dims[d] - 1, dims[d])
        D0, D1 = D[tuple(lo)], D[tuple(hi)]
        D = D + (1.0 - w) * (bcf(fd[2 * d], d) - D0) + w * (bcf(fd[2 * d + 1], d) - D1)
        if Q is not None:
            Q0, Q1 = Q[tuple(lo)], Q[tuple(hi)]
            F0, F1 = bcf(fq[2 * d], d), bcf(fq[2 * d + 1], d)
            F0 = F0 * np.where(np.sum(F0 * Q0, axis=-1) < 0.0, -1.0, 1.0)[..., None]
            F1 = F1 * np.where(np.sum(F1 * Q1, axis=-1) < 0.0, -1.0, 1.0)[..., None]
            if step == 0:
                U0 = Q0 / np.linalg.norm(Q0, axis=-1, keepdims=True)
                U1 = Q1 / np.linalg.norm(Q1, axis=-1, keepdims=True)
            else:
                U0, U1 = Vhat[tuple(lo)], Vhat[tuple(hi)]
            Q = Q + (1.0 - w) * (F0 - Q0) + w * (F1 - Q1)
            terms += [(1.0 - w[..., 0], F0, U0), (w[..., 0], F1, U1)]
            if step == 0 and nd == 3:
                Vhat = np_normalize_or_fallback(Q, base, terms)
    if Q is not None:
        Q = np_normalize_or_fallback(Q, base, terms)
    return D, Q


def tfi_block_fields(face_delta, face_q, s, order):
    """Unfused Soni TFI of (Δ, Q) over a block (reference implementation; allocates full size).

    Parameters
    ----------
    face_delta : sequence of 6 arrays
        Δ on faces imin, imax, jmin, jmax, kmin, kmax, each of shape
        ``Block.face(f).shape[:2] + (3,)``; consistent on shared edges.  For a
        2-D block (``len(order) == 2``): 4 sides imin, imax ``(nj, 3)``, jmin,
        jmax ``(ni, 3)``.
    face_q : sequence of 6 (or 4) arrays (..., 4) of unit quaternions, or None
        Q on the same faces; None for the baseline (Q ≡ 1).
    s : ndarray, shape (ni, nj, nk, 3), float64
        The block's arclength parameters (:func:`arclength`).
    order : sequence of int
        ``(L, M, N)`` (``(L, M)`` in 2-D), e.g. from :func:`lead_order`.

    Returns
    -------
    delta : ndarray, shape (ni, nj, nk, 3), float64
    q : ndarray, shape (ni, nj, nk, 4), float64, or None
        Unit quaternions (to 1e-12).
    """
    if not isinstance(s, np.ndarray) or s.ndim != 4:
        tfi._fail(f"s: expected an array of shape (ni, nj, nk, 3), got {getattr(s, 'shape', type(s))}")
    dims = s.shape[:3]
    tfi._check_s(s, dims)
    nd = len(order) if hasattr(order, "__len__") else 0
    if nd not in (2, 3):
        tfi._fail(f"order: expected (L, M, N) or (L, M), got {order!r}")
    o = tfi._check_order(order, nd)
    if nd == 2:
        if dims[2] != 1:
            tfi._fail(f"s: a 2-D order needs nk == 1, got shape {s.shape}")
        fd = tfi._sides_as_faces(face_delta, dims, 3, "face_delta")
        fq = None if face_q is None else tfi._sides_as_faces(face_q, dims, 4, "face_q")
    else:
        fd = tfi._faces(face_delta, dims, 3, "face_delta")
        fq = None if face_q is None else tfi._faces(face_q, dims, 4, "face_q")
    D, Q = fields_ref(fd, fq, s, o)
    D = np.asfortranarray(np.broadcast_to(D, dims + (3,)))
    if Q is not None:
        Q = np.asfortranarray(np.broadcast_to(Q, dims + (4,)))
    return D, Q


def tfi_patch(delta, q, s, lead: int = 0) -> None:
    """2-D Soni TFI on a patch, in place: fill the interior from the four sides.

    Parameters
    ----------
    delta : ndarray, shape (na, nb, 3), float64, writeable
        Δ; the sides ``a = 0``, ``a = na - 1``, ``b = 0``, ``b = nb - 1`` hold
        the known values (consistent at the corners); the interior is
        overwritten.
    q : ndarray, shape (na, nb, 4), float64, writeable, or None
        Unit quaternions, same layout (None: baseline, Q ≡ 1).  The interior
        is overwritten with unit quaternions.
    s : array_like, shape (na, nb, 2)
        The patch's arclength parameters from the **undeformed** surface
        (:func:`arclength_surface`).
    lead : {0, 1}
        Leading direction (0: along ``a``, slerp between the sides a = 0 and
        a = na - 1).
    """
    for arr, nm, nc in ((delta, "delta", 3), (q, "q", 4)):
        if arr is None and nm == "q":
            continue
        if not isinstance(arr, np.ndarray) or arr.ndim != 3 or arr.shape[-1] != nc or \
                arr.dtype != np.float64 or not arr.flags.writeable:
            tfi._fail(f"{nm}: expected a writeable float64 array of shape (na, nb, {nc}), got "
                  f"{getattr(arr, 'shape', type(arr).__name__)} {getattr(arr, 'dtype', '')}")
    na, nb = delta.shape[:2]
    if q is not None and q.shape[:2] != (na, nb):
        tfi._fail(f"q: expected shape {(na, nb, 4)} like delta, got {q.shape}")
    sa = np.asarray(s)
    if sa.shape != (na, nb, 2) or sa.dtype.kind != "f":
        tfi._fail(f"s: expected a float array of shape {(na, nb, 2)}, got {sa.shape} {sa.dtype}")
    if lead not in (0, 1):
        tfi._fail(f"lead: expected 0 or 1, got {lead!r}")
    if na <= 2 or nb <= 2:
        return
    sb = np.zeros((na, nb, 1, 3), order="F")
    sb[:, :, 0, :2] = sa
    sides_d = [delta[0], delta[-1], delta[:, 0], delta[:, -1]]
    fd = tfi._sides_as_faces(sides_d, (na, nb, 1), 3, "delta")
    fq = None
    if q is not None:
        fq = tfi._sides_as_faces([q[0], q[-1], q[:, 0], q[:, -1]], (na, nb, 1), 4, "q")
    D, Q = fields_ref(fd, fq, sb, (lead, 1 - lead))
    delta[1:-1, 1:-1] = D[1:-1, 1:-1, 0]
    if q is not None:
        q[1:-1, 1:-1] = Q[1:-1, 1:-1, 0]
