"""Target searches: the cheapest codec setting that reaches a PSNR target.

* :func:`find_smallest` — one codec, one integer size parameter (``target.codec``,
  ``target.param``): bisection on [lo, hi].
* :func:`search_families` — every codec family of the config (``target.codec`` unset): each
  family's size parameters are searched on their own monotone axes — ``vectors`` and ``lobes``
  by bisection on integers in [lo, hi], ``clusters`` on powers of two in [1, hi_clusters]
  (bisection over that list), the learned codec's ``latent`` by bisection on [lo, min(hi, D − 1,
  features)]; CPCA, with two size parameters, walks its Pareto front: for every
  cluster count, the fewest vectors that reach the target, then the cheapest of those points.
  The winner is the setting with the fewest bytes per vertex (``by='bytes'``) or the highest
  relighting rate (``by='fps'``) among the settings found; each family's best is reported as its
  runner-up, with the search cost (settings evaluated, seconds).

Both assume the target metric grows with each size parameter (nested subspaces for vectors;
more clusters or lobes fit at least as well), the premise of CompressAI's ``find_close``. The
searches only call ``run_setting(setting) -> record`` (harness.run evaluates, caches and
saves), so every evaluated setting is also in the results.

Branch and bound (``by='bytes'``): a setting's bytes per vertex have a floor known before any
fit (:func:`bytes_floor`: the weights and basis vectors it must store), so on CPCA's front a
cluster count is searched only over the vector counts whose floor is below the family's cheapest
setting found so far, and the walk stops at the first cluster count whose floor is not. The
result is the same as without the bound (a setting it skips costs at least what was found), and
the fits it saves are the expensive ones (many clusters, many vectors). :func:`search_cost`
gives the most fits a search can make (``--dry-run`` prints it).
"""
from __future__ import annotations

import time
from typing import Any, Callable

__all__ = ["find_smallest", "search_families", "size_axes", "SIZE_AXES", "bytes_floor", "search_cost"]

#: The size parameters of each codec family (registry name -> parameters, in search order).
SIZE_AXES: dict[str, tuple[str, ...]] = {
    "vq": ("clusters",), "pca": ("vectors",), "mrt_pca": ("vectors",), "cpca": ("clusters", "vectors"),
    "cpca_static": ("clusters", "vectors"), "cpca_iterative": ("clusters", "vectors"),
    "cpca_adaptive": ("clusters", "vectors"), "gaussian": ("lobes",), "neural": ("latent",),
}


def size_axes(codec: str) -> tuple[str, ...]:
    """Size parameters of ``codec`` (a codec class may declare ``size_params``)."""
    from .. import codecs

    cls = type(codecs.get(codec))
    return tuple(getattr(cls, "size_params", SIZE_AXES.get(codec, ())))


#: codecs whose stored size has the floor of :func:`bytes_floor` (fixed vectors per point and cluster)
_AFFINE_FIXED = ("pca", "mrt_pca", "cpca", "cpca_static", "cpca_iterative")


def bytes_floor(setting: dict, points: int, dim: int) -> float:
    """A lower bound of the bytes per vertex a setting ``{type, clusters, vectors, ...}`` will store,
    known before its fit: the float32 weights of every point (``P·n``) and basis vectors of every
    cluster (``K·n·D``) of the affine codecs with a fixed vector count, the codebook (``K·D``) of VQ;
    labels, means and per-cluster counts are left out (so it never exceeds the real size); for the
    learned codec (``neural``) the codes (``P·k`` in ``code_dtype``) and the decoder's float32 weights:
    the last layer of every cluster (``K·H·D`` and ``K·D``), φ's layers (``k → width^depth → H − k``,
    one set per cluster with ``cluster_decoder='full'``) and the stored code samples (``min(P, 256)·k``),
    the codec's defaults for what the setting leaves out; 0 for a codec it does not know (adaptive
    CPCA, Gaussians: no bound, nothing pruned)."""
    name = setting["type"]
    K = min(int(setting.get("clusters", 1)), points)
    if name == "vq":
        return 4.0 * K * dim / points
    if name == "neural":
        from ..codecs import neural

        d = neural.NeuralCodec().get_params()
        prm = {**d, **{k: v for k, v in setting.items() if k in d}}
        k, H = int(prm["latent"]), int(prm["features"])
        dims = [k] + [int(prm["width"])] * int(prm["depth"]) + [H - k] if H > k else []
        phi = sum(a * b + b for a, b in zip(dims[:-1], dims[1:])) * (K if prm["cluster_decoder"] == "full" and K > 1 else 1)
        code = 2 if prm["code_dtype"] == "float16" else 4
        return (code * points * k + 4.0 * (K * H * dim + K * dim + phi + min(points, neural.CODE_SAMPLES) * k)) / points
    if name in _AFFINE_FIXED:
        n = int(setting.get("vectors", 0))
        return 4.0 * (points * n + K * n * dim) / points
    return 0.0


def _steps(n: int) -> int:
    """Most evaluations of :func:`_bisect` over ``n`` values (the top first, then halving)."""
    return 0 if n <= 0 else 1 + max(0, (n - 1).bit_length())


def search_cost(cfg: dict, points: int, dim: int) -> dict:
    """``{family: most fits its search can make}`` and ``total``, without any fit (the bound on
    CPCA's front is the walk without pruning: every cluster count, a bisection of the vectors)."""
    t = cfg["target"]
    lo, hi = int(t["lo"]), int(t["hi"])
    if t.get("codec"):
        return {t["codec"]: _steps(hi - lo + 1), "total": _steps(hi - lo + 1)}
    n_clusters = len([c for c in (2 ** i for i in range(0, 31)) if c <= min(int(t["hi_clusters"]), points)])
    out: dict[str, int] = {}
    for codec in dict.fromkeys(e["type"] for e in cfg["codecs"]):
        axes = size_axes(codec)
        base = _base(cfg, codec)
        vec_hi = min(hi, dim - 1 if base.get("center", True) else dim)
        if axes == ("clusters",):
            out[codec] = _steps(n_clusters)
        elif axes in (("vectors",), ("lobes",)):
            out[codec] = _steps((vec_hi if axes[0] == "vectors" else hi) - lo + 1)
        elif axes == ("latent",):
            out[codec] = _steps(_latent_hi(base, hi, dim) - lo + 1)
        elif axes == ("clusters", "vectors"):
            out[codec] = n_clusters * _steps(vec_hi - lo + 1)
        else:
            out[codec] = 0
    out["total"] = sum(out.values())
    return out


def _latent_hi(base: dict, hi: int, dim: int) -> int:
    """The largest latent size k of a ``neural`` search: ≤ ``hi``, < D (the codes start as PCA with k
    vectors) and ≤ its feature size H (h(z) = [z, φ(z)])."""
    from ..codecs import neural

    return min(hi, dim - 1, int(base.get("features", neural.NeuralCodec().features)))


def _bisect(lo: int, hi: int, ok: Callable[[int], bool]) -> int | None:
    """Smallest v in [lo, hi] with ok(v) (ok monotone), or None when ok(hi) fails."""
    if lo > hi or not ok(hi):
        return None
    while lo < hi:
        mid = (lo + hi) // 2
        if ok(mid):
            hi = mid
        else:
            lo = mid + 1
    return lo


def _base(cfg: dict, codec: str) -> dict:
    """The first config entry of ``codec`` with list values reduced to their first element."""
    base = next((dict(e) for e in cfg["codecs"] if e["type"] == codec), {"type": codec})
    return {k: (v[0] if isinstance(v, list) else v) for k, v in base.items()}


def find_smallest(cfg: dict, run_setting: Callable[[dict], dict]) -> dict:
    """Smallest integer value of ``target.param`` of ``target.codec`` whose setting meets
    ``target.psnr`` on ``target.metric`` (bisection on [lo, hi]). Other parameters come from the
    first codec entry of that name (lists → first)."""
    t = cfg["target"]
    base = _base(cfg, t["codec"])
    metric, goal = t["metric"], float(t["psnr"])
    tried: list[dict] = []

    def ok(v: int) -> bool:
        r = run_setting({**base, t["param"]: v})
        tried.append(r)
        return r[metric] >= goal

    v = _bisect(int(t["lo"]), int(t["hi"]), ok)
    if v is None:
        best = max(tried, key=lambda r: r[metric])
        return {"met": False, "codec": t["codec"], "param": t["param"], "value": None, "goal_db": goal, "metric": metric,
                "note": f"{t['param']}={t['hi']} (the upper bound) does not reach {goal} dB; the best was "
                        f"{best[metric]:.2f} dB by {best['setting_id']}", "_records": tried}
    best = next(r for r in tried if r["params"].get(t["param"]) == v)
    return {"met": True, "codec": t["codec"], "param": t["param"], "value": v, "goal_db": goal, "metric": metric,
            "achieved_db": best[metric], "bytes_per_vertex": best["bytes_per_vertex"], "setting_id": best["setting_id"],
            "evaluated": [r["params"].get(t["param"]) for r in tried], "_records": tried}


def _summary(r: dict, metric: str) -> dict:
    """A search result's entry; ``fps`` is None for a probe searched untimed (harness.run.run_target
    times the finalists)."""
    return {"setting_id": r["setting_id"], "codec": r["codec"], "params": r["params"], "achieved_db": r[metric],
            "bytes_per_vertex": r["bytes_per_vertex"], "fps": r.get("fps")}


#: codecs whose single-cluster fit is a PCA fit: their ``clusters=1`` outcomes are PCA's (same ``center``)
_ONE_CLUSTER_IS_PCA = ("cpca", "cpca_static", "cpca_iterative")


def search_families(cfg: dict, run_setting: Callable[[dict], dict], points: int, dim: int,
                    log: Callable[[str], None] | None = None) -> dict:
    """Search every codec family of ``cfg['codecs']`` for its cheapest setting reaching
    ``target.psnr`` (module docstring); ``points``/``dim`` bound clusters (≤ P) and vectors (< D).
    Returns the JSON-able search record (``_records``: every record evaluated)."""
    t = cfg["target"]
    metric, goal, by = t["metric"], float(t["psnr"]), t["by"]
    lo, hi = int(t["lo"]), int(t["hi"])
    clusters = [c for c in (2 ** i for i in range(0, 31)) if c <= min(int(t["hi_clusters"]), points)]
    tried: list[dict] = []
    families: dict[str, Any] = {}
    t_start = time.perf_counter()

    cost = search_cost(cfg, points, dim)
    pruned: list[str] = []  # what branch and bound skipped, said in the record
    reused: list[str] = []  # probes answered by another family's fits

    fits: list[float] = []  # seconds of each probe run here (a record reused from an earlier run costs none)

    def evaluate(base: dict, **size) -> dict:
        t0 = time.perf_counter()
        r = run_setting({**base, **size})
        fits.append(time.perf_counter() - t0)
        tried.append(r)
        if log is not None:  # progress with an estimate: the bound's remaining fits at the mean cost so far
            left = cost["total"] - len(tried)
            log(f"[target] {len(tried)} of at most {cost['total']}: {r['setting_id']} {r[metric]:.2f} dB "
                f"({'meets' if r[metric] >= goal else 'below'} {goal:g}), {r['bytes_per_vertex']:.1f} B/vertex; "
                f"{time.perf_counter() - t_start:.0f} s so far, at most ~{left * sum(fits) / len(fits):.0f} s more")
        return r

    def from_pca(codec: str, base: dict, vectors: int) -> bool | None:
        """Whether ``codec`` at clusters=1 and ``vectors`` meets the goal, from a PCA probe of the same
        vectors and centring already made (one cluster's fit is that PCA fit), else None."""
        if codec not in _ONE_CLUSTER_IS_PCA:
            return None
        center = base.get("center", True)
        for r in tried:
            if r["codec"] == "pca" and r["params"].get("vectors") == vectors and r["params"].get("center", True) == center:
                return r[metric] >= goal
        return None

    for codec in dict.fromkeys(e["type"] for e in cfg["codecs"]):  # one search per family, config order
        base = _base(cfg, codec)
        axes = size_axes(codec)
        n0, found = len(tried), []
        vec_hi = min(hi, dim - 1 if base.get("center", True) else dim)

        def meets(r: dict) -> bool:
            return r[metric] >= goal

        if axes == ("clusters",):
            i = _bisect(0, len(clusters) - 1, lambda k: meets(evaluate(base, clusters=clusters[k])))
            found = [] if i is None else [next(r for r in tried[n0:] if r["params"]["clusters"] == clusters[i])]
        elif axes in (("vectors",), ("lobes",)):
            ax = axes[0]
            top = vec_hi if ax == "vectors" else hi
            v = _bisect(lo, top, lambda k: meets(evaluate(base, **{ax: k})))
            found = [] if v is None else [next(r for r in tried[n0:] if r["params"][ax] == v)]
        elif axes == ("latent",):  # the learned codec: bisection on its code size (its training is the costly fit)
            top = _latent_hi(base, hi, dim)
            cheapest = min((f["best"]["bytes_per_vertex"] for f in families.values() if f.get("best")), default=None)
            if by == "bytes" and cheapest is not None:  # branch and bound: only code sizes that could cost less
                full = top
                while top >= lo and bytes_floor({**base, "latent": top}, points, dim) >= cheapest:
                    top -= 1
                if top < full:
                    pruned.append(f"{codec} latent {top + 1}..{full}: floor >= {cheapest:.1f} B/vertex (the cheapest found)")
                if top < lo:
                    families[codec] = {"searched": False, "note": f"pruned: every latent size's bytes floor is >= {cheapest:.1f} "
                                                                  "B/vertex, the cheapest setting already found"}
                    continue
            v = _bisect(lo, top, lambda k: meets(evaluate(base, latent=k)))
            found = [] if v is None else [next(r for r in tried[n0:] if r["params"]["latent"] == v)]
        elif axes == ("clusters", "vectors"):
            for i, c in enumerate(clusters):  # the Pareto front: fewest vectors per cluster count
                top = vec_hi
                if by == "bytes" and found:  # branch and bound: only vector counts that could cost less
                    best = min(r["bytes_per_vertex"] for r in found)
                    while top >= lo and bytes_floor({**base, "clusters": c, "vectors": top}, points, dim) >= best:
                        top -= 1
                    if top < lo:  # the floor grows with the clusters too: no larger count can cost less
                        pruned.append(f"{codec} clusters {clusters[i:]}: every vector count's floor >= {best:.1f} B/vertex")
                        break
                    if top < vec_hi:
                        pruned.append(f"{codec} clusters={c}: vectors {top + 1}..{vec_hi} (floor >= {best:.1f} B/vertex)")
                def ok(k: int, c: int = c) -> bool:
                    known = from_pca(codec, base, k) if c == 1 else None
                    return known if known is not None else meets(evaluate(base, clusters=c, vectors=k))

                v = _bisect(lo, top, ok)
                hit = [r for r in tried[n0:] if r["params"]["clusters"] == c and r["params"]["vectors"] == v]
                if v is not None and not hit:  # decided by PCA's probes: one fit for its bytes, which must agree
                    r = evaluate(base, clusters=c, vectors=v)
                    if meets(r):
                        hit = [r]
                        reused.append(f"{codec} clusters=1: bisected on PCA's probes of the same vectors, one fit (vectors={v})")
                    else:  # the fits disagree at the threshold: bisect on this codec's own fits
                        v = _bisect(lo, top, lambda k: meets(evaluate(base, clusters=c, vectors=k)))
                        hit = [r for r in tried[n0:] if r["params"]["clusters"] == c and r["params"]["vectors"] == v]
                if v is not None:
                    found.append(hit[0])
        else:
            families[codec] = {"searched": False, "note": f"codec {codec!r} declares no size parameter"}
            continue
        mine = tried[n0:]
        key = (lambda r: r["bytes_per_vertex"]) if by == "bytes" else (lambda r: -r["fps"])
        fam = {"searched": True, "axes": list(axes), "evaluated": len(mine),
               "front": [_summary(r, metric) for r in sorted(found, key=key)]}
        if found:
            fam["best"] = _summary(min(found, key=key), metric)
        else:
            top_r = max(mine, key=lambda r: r[metric])
            fam["note"] = f"no setting in range reaches {goal} dB; the best was {top_r[metric]:.2f} dB by {top_r['setting_id']}"
        families[codec] = fam
    bests = [f["best"] for f in families.values() if f.get("best")]
    key = (lambda s: s["bytes_per_vertex"]) if by == "bytes" else (lambda s: -s["fps"])
    out = {"mode": "families", "met": bool(bests), "goal_db": goal, "metric": metric, "by": by, "families": families,
           "evaluated": len(tried), "distinct_settings": len({r["setting_id"] for r in tried}),
           "most_fits": cost["total"], "pruned": pruned, "reused": reused,
           "seconds": time.perf_counter() - t_start, "_records": tried}
    if bests:
        out["winner"] = min(bests, key=key)
        out["runners_up"] = sorted((b for b in bests if b is not out["winner"]), key=key)
    else:
        top_r = max(tried, key=lambda r: r[metric])
        out["note"] = (f"no setting of any family reaches {goal} dB ({metric}); the best was {top_r[metric]:.2f} dB by "
                       f"{top_r['setting_id']} — raise target.hi / target.hi_clusters or lower the target")
    return out
