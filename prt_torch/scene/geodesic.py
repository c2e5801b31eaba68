"""The geodesic sphere the built-in scenes and the scan-like meshes are made from."""
from __future__ import annotations

import numpy as np

__all__ = ["geodesic_sphere"]


def geodesic_sphere(freq: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit geodesic sphere: each icosahedron face split into freq² triangles, projected.

    Returns ``(vertices [10 f² + 2, 3] float64, faces [20 f², 3] int64)``, outward CCW winding.
    """
    freq = int(freq)
    t = (1 + 5 ** 0.5) / 2
    ico_v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                      [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    ico_f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    # barycentric lattice of one face: points (i, j) with i + j <= f
    ii, jj = np.meshgrid(np.arange(freq + 1), np.arange(freq + 1), indexing="ij")
    keep = ii + jj <= freq
    i, j = ii[keep], jj[keep]
    idx = -np.ones((freq + 1, freq + 1), np.int64)
    idx[i, j] = np.arange(i.shape[0])
    # small triangles of the lattice (upward and downward)
    a_i, a_j = np.meshgrid(np.arange(freq), np.arange(freq), indexing="ij")
    up = a_i + a_j <= freq - 1
    tri_up = np.stack([idx[a_i[up], a_j[up]], idx[a_i[up] + 1, a_j[up]], idx[a_i[up], a_j[up] + 1]], 1)
    dn = a_i + a_j <= freq - 2
    tri_dn = np.stack([idx[a_i[dn] + 1, a_j[dn]], idx[a_i[dn] + 1, a_j[dn] + 1], idx[a_i[dn], a_j[dn] + 1]], 1)
    local_f = np.concatenate([tri_up, tri_dn])
    A, B, C = ico_v[ico_f[:, 0]], ico_v[ico_f[:, 1]], ico_v[ico_f[:, 2]]  # [20,3]
    w_b = i / freq
    w_c = j / freq
    w_a = 1 - w_b - w_c
    pts = w_a[None, :, None] * A[:, None] + w_b[None, :, None] * B[:, None] + w_c[None, :, None] * C[:, None]
    pts = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
    P = pts.shape[1]
    faces = (local_f[None] + (np.arange(20) * P)[:, None, None]).reshape(-1, 3)
    flat = pts.reshape(-1, 3)
    # merge the lattice points shared by neighbouring icosahedron faces
    # (a stable lexicographic sort of the rounded coordinates, then each run's first index: what
    # np.unique(axis=0, return_index, return_inverse) gives, at ~1/5 of its time on 1M points)
    key = np.round(flat * 1e9).astype(np.int64)
    srt = np.lexsort(key.T[::-1])  # stable: within a run of equal keys, indices ascend
    ks = key[srt]
    new = np.ones(srt.shape[0], bool)
    new[1:] = (ks[1:] != ks[:-1]).any(axis=1)
    group = np.cumsum(new) - 1  # run id of each sorted point
    first = srt[new]  # the lowest index of every run
    inv = np.empty_like(srt)
    inv[srt] = group
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    verts = flat[first[order]]
    faces = rank[inv][faces]
    # orient outward
    tri = verts[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", nrm, tri.mean(1)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces
