"""The stored views of a Gaussian encoding (Green 2005 §2.2.1, §2.3): the view set a J-view table
uses, each view's nearest other views (r(v) of the view terms M and V, eq. 2.4–2.5), whether a
view set covers the sphere, the three nearest views of a direction with barycentric weights
(§2.3: "interpolate the parameters from the three closest views"), and the interpolation of
corresponding lobes across views or triangle vertices (§2.3).
"""
from __future__ import annotations

import math

import torch

__all__ = ["fibonacci_directions", "default_views", "view_neighbours", "views_cover_sphere", "view_taps", "blend_lobes", "order_lobes",
           "fill_empty_lobes"]


def fibonacci_directions(n: int) -> torch.Tensor:
    """``[n, 3]`` float64 near-uniform unit directions (Fibonacci lattice); n = 1: +z."""
    if n == 1:
        return torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    rho = (1 - z * z).clamp_min(0).sqrt()
    return torch.stack([rho * torch.cos(phi), rho * torch.sin(phi), z], -1)


def default_views(J: int) -> torch.Tensor:
    """The view set a J-view table is assumed to use: the icosphere of frequency f when
    J = 10 f² + 2 (f = 3: Green's 92 views; :func:`transfer.transport.icosphere_directions`),
    else a Fibonacci lattice. ``[J, 3]`` float64."""
    f = math.isqrt(max(0, (J - 2) // 10))
    if J >= 12 and 10 * f * f + 2 == J:
        from ...transfer.transport import icosphere_directions

        return icosphere_directions(f)
    return fibonacci_directions(J)


def view_neighbours(views: torch.Tensor, k: int = 6) -> torch.Tensor:
    """Indices ``[J, min(k, J−1)]`` int64 of each view's nearest other views (r(v) of eq. 2.4)."""
    J = views.shape[0]
    k = min(k, J - 1)
    if k <= 0:
        return torch.zeros(J, 0, dtype=torch.long)
    c = views @ views.T
    c.fill_diagonal_(-2.0)
    return c.topk(k, dim=1).indices


def views_cover_sphere(views: torch.Tensor, max_angle_deg: float = 75.0) -> tuple[bool, float]:
    """Whether every direction has a stored view within ``max_angle_deg`` (so each vertex's
    hemisphere of views is covered and three nearest views bracket any view). Returns
    (ok, the largest angle to the nearest view in degrees, over 4096 test directions)."""
    test = fibonacci_directions(4096)
    v = views.to(torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    worst = math.degrees(math.acos(float((test @ v.T).amax(1).min().clamp(-1, 1))))
    return worst <= max_angle_deg, worst


def view_taps(views: torch.Tensor, dirs: torch.Tensor, k: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """The three nearest stored views of each direction and barycentric weights (Green §2.3:
    "interpolate the parameters from the three closest views"). ``views [J, 3]``, ``dirs
    [M, 3]`` unit → ``(idx int64 [M, k], w float32 [M, k])``, weights ≥ 0 summing to 1 (the
    barycentric coordinates of the direction in the triangle of the three views, clamped)."""
    J = views.shape[0]
    k = min(k, J)
    d = dirs.to(torch.float64)
    vv = views.to(torch.float64)
    c = d @ vv.T
    idx = c.topk(k, dim=1).indices
    if k < 3:
        w = c.gather(1, idx).clamp_min(0) + 1e-12
        return idx, (w / w.sum(1, keepdim=True)).to(torch.float32)
    B = vv[idx].transpose(1, 2)  # [M, 3, 3] columns = the three views
    det = torch.linalg.det(B)
    ok = det.abs() > 1e-9
    Bs = torch.where(ok[:, None, None], B, torch.eye(3, dtype=B.dtype).expand_as(B))
    b = torch.linalg.solve(Bs, d[..., None])[..., 0].clamp_min(0)
    fallback = c.gather(1, idx).clamp_min(0) + 1e-12
    b = torch.where(ok[:, None] & (b.sum(1, keepdim=True) > 0), b, fallback)
    return idx, (b / b.sum(1, keepdim=True)).to(torch.float32)


def blend_lobes(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, a: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interpolate corresponding lobes (Green §2.3; barycentric across views or triangle
    vertices): ``w [M, T, N]``, ``mu [M, T, N, 3]``, ``sigma [M, T, N]``, weights ``a [M, T]``
    → ``(w [M, N], mu [M, N, 3] unit, sigma [M, N])``. Weights and widths blend linearly, means
    as the normalised weighted sum (the non-linear interpolation that moves a highlight instead
    of cross-fading it)."""
    a = a.to(w.dtype)
    wb = torch.einsum("mt,mtn->mn", a, w)
    sb = torch.einsum("mt,mtn->mn", a, sigma)
    mb = torch.einsum("mt,mtnc->mnc", a, mu)
    mb = mb / mb.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return wb, mb, sb.clamp_min(1e-6)


def order_lobes(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, views: torch.Tensor, k: int = 6
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Number each view's lobes so that lobe n of neighbouring views is the same lobe (Green §2.3
    blends *corresponding* lobes; a fit numbers them per function). Breadth-first over the views'
    neighbour graph (:func:`view_neighbours`) from view 0; each view's N lobes take the permutation
    (of the N! ≤ 24 for N ≤ 4; more lobes are left as fitted) whose means best agree, Σ_n μ_n · m_n, with
    m_n the weight-weighted sum of lobe n's means over the already-numbered neighbour views — per vertex,
    batched over the vertices (a loop over the J views only). The sum over the lobes, hence the tables
    and relighting at a stored view, is unchanged. ``w [V, J, N]``, ``mu [V, J, N, 3]``, ``sigma [V, J, N]``,
    ``views [J, 3]`` → the same tensors renumbered (new tensors; measured on ``prt bench gaussian``'s
    tables: reports/benchmarks/gaussian_taps.md)."""
    import itertools

    V, J, N = w.shape
    if N < 2 or N > 4 or J < 2:
        return w, mu, sigma
    perms = torch.tensor(list(itertools.permutations(range(N))))  # [Q, N]
    nb = view_neighbours(views.to(torch.float64), k)
    seq, seen = [0], {0}
    for j in seq:  # breadth-first order of the views
        for m in nb[j].tolist():
            if m not in seen:
                seen.add(m)
                seq.append(m)
    seq += [j for j in range(J) if j not in seen]
    w, mu, sigma = w.clone(), mu.clone(), sigma.clone()
    done = torch.zeros(J, dtype=torch.bool)
    done[seq[0]] = True
    for j in seq[1:]:
        ks = [m for m in nb[j].tolist() if done[m]]
        done[j] = True
        if not ks:
            continue
        tgt = (w[:, ks, :, None] * mu[:, ks]).sum(1)  # [V, N, 3]
        best = perms[torch.einsum("vnc,vqnc->vq", tgt, mu[:, j][:, perms]).argmax(1)]  # [V, N]
        w[:, j] = w[:, j].gather(1, best)
        sigma[:, j] = sigma[:, j].gather(1, best)
        mu[:, j] = mu[:, j].gather(1, best[..., None].expand(-1, -1, 3))
    return w, mu, sigma


#: :func:`fill_empty_lobes`: the locality κ of the weights exp(κ (v_j·v_m − 1)) over the views m a zero-weight
#: lobe's mean is extrapolated from (κ = 10: half weight at 22°, a tenth at 40°; measured best of 4, 8 (scratch) and 10)
FILL_LOCALITY = 10.0


def fill_empty_lobes(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, views: torch.Tensor, k: int = 6,
                     locality: float = FILL_LOCALITY, block: int = 1024) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Place every lobe of weight 0 — all N lobes of a zero function (a view below the vertex's horizon) and a
    lobe a fit dropped — where the same-numbered lobe's track over the views leads (run after :func:`order_lobes`).

    The mean: an affine function of the view direction, μ(v) ≈ A v + b (A 3×3, b 3; a highlight's mirror
    direction 2(n·v)n − v is one, exactly), fitted per (vertex, lobe, zero view j) by weighted least squares
    over the views m where the lobe has weight, weights w_m exp(κ (v_j·v_m − 1)) (κ = ``locality``), then
    evaluated at v_j and normalised — batched: per vertex block one GEMM of the locality kernel [J, J] with the
    per-view moments, and 4×4 solves. A lobe with weight in fewer than 4 of its vertex's views (an ill-posed
    fit) takes instead the normalised sum of its neighbouring views' means (:func:`view_neighbours`), sweep
    after sweep outward over the view graph. The width: that neighbour average for every zero-weight lobe.

    Weights stay 0, so the tables, the fit's error and every stored-view relight are unchanged. What changes
    is the blend at view taps (Green §2.3, :func:`blend_lobes`): means and widths are blended with the tap
    weights whatever the lobes' weights, so a tapped view with nothing there (near each vertex's horizon: about
    20% of the vertices a camera sees at 162 views) pulled the blended lobe toward its placeholder (the fit's
    zero functions start at the view direction, width 0.5) instead of only fading it out. Measured on ``prt
    bench gaussian``'s tables against the exact radiance: reports/benchmarks/gaussian_taps.md (issue 42 §2).
    ``w [V, J, N]``, ``mu [V, J, N, 3]``, ``sigma [V, J, N]``, ``views [J, 3]`` → (w, new mu, new sigma);
    a lobe with weight in no view of its vertex is left as it was."""
    from ..._checks import check_float, check_int

    if w.ndim != 3 or tuple(mu.shape) != (*w.shape, 3) or tuple(sigma.shape) != tuple(w.shape) \
            or tuple(views.shape) != (w.shape[1], 3):
        raise ValueError(f"fill_empty_lobes: w {list(w.shape)}, mu {list(mu.shape)}, sigma {list(sigma.shape)}, views "
                         f"{list(views.shape)}; accepted: w [V, J, N], mu [V, J, N, 3], sigma [V, J, N], views [J, 3]")
    k, block = check_int("k", k, 1), check_int("block", block, 1)
    locality = check_float("locality", locality, 0.0)
    V, J, N = w.shape
    if J < 2:
        return w, mu, sigma
    vw = views.to(torch.float64)
    nb = view_neighbours(vw, k)  # [J, K]
    X = torch.cat([vw, torch.ones(J, 1, dtype=torch.float64)], 1)  # [J, 4]: (v, 1)
    XX = (X[:, :, None] * X[:, None, :]).reshape(J, 16)
    Kj = torch.exp(float(locality) * (vw @ vw.T - 1))  # [J, J] locality of view m to view j
    mu, sigma = mu.clone(), sigma.clone()
    for v0 in range(0, V, block):  # blocks of vertices: [b, N, J, 16] moments, no [V, J, J] temporaries
        sl = slice(v0, v0 + block)
        wb, m_, s_ = w[sl].to(torch.float64), mu[sl].to(torch.float64), sigma[sl].to(torch.float64)
        b = wb.shape[0]
        valid = wb > 0
        todo = ~valid
        # ring fill (widths; the means of lobes with too few weighted views), sweep by sweep over the view graph
        mr, sr, got, left = m_.clone(), s_.clone(), valid.clone(), todo.clone()
        for _ in range(J):
            src = got[:, nb]  # [b, J, K, N]
            can = left & src.any(2)
            if not bool(can.any()):
                break
            m = (mr[:, nb] * src[..., None]).sum(2)
            s = (sr[:, nb] * src).sum(2) / src.sum(2).clamp_min(1)
            mr = torch.where(can[..., None], m / m.norm(dim=-1, keepdim=True).clamp_min(1e-12), mr)
            sr = torch.where(can, s, sr)
            got, left = got | can, left & ~can
        # the affine track of each lobe's mean, fitted around each zero view
        wt = (wb * valid).permute(0, 2, 1)  # [b, N, J]
        G = (Kj @ (wt[..., None] * XX).reshape(b * N, J, 16)).reshape(b, N, J, 4, 4)  # Σ_m K_jm w_m x_m x_mᵀ
        R = (Kj @ (wt[..., None, None] * X[:, :, None] * m_.permute(0, 2, 1, 3)[..., None, :]).reshape(b * N, J, 12)
             ).reshape(b, N, J, 4, 3)  # Σ_m K_jm w_m x_m μ_mᵀ
        rows = (todo.permute(0, 2, 1) & (valid.sum(1)[..., None] >= 4)).nonzero(as_tuple=True)  # (vertex, lobe, view)
        lin = torch.zeros(b, N, J, dtype=torch.bool)
        if rows[0].numel():
            Gs = G[rows]
            Gs = Gs + 1e-9 * Gs.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(4, dtype=Gs.dtype)
            C = torch.linalg.solve(Gs, R[rows])  # [n, 4, 3]
            pred = torch.einsum("na,nac->nc", X[rows[2]], C)
            ok = pred.norm(dim=-1) > 1e-6
            lin[rows[0][ok], rows[1][ok], rows[2][ok]] = True
            full = torch.zeros(b, N, J, 3, dtype=torch.float64)
            full[rows[0][ok], rows[1][ok], rows[2][ok]] = pred[ok] / pred[ok].norm(dim=-1, keepdim=True)
            mr = torch.where(lin.permute(0, 2, 1)[..., None], full.permute(0, 2, 1, 3), mr)
        mu[sl] = torch.where(todo[..., None], mr, m_).to(mu.dtype)
        sigma[sl] = torch.where(todo, sr, s_).to(sigma.dtype)
    return w, mu, sigma
