"""Batched ray casting over Embree (the ``embreex`` binding, called directly).

``RayCaster(mesh)`` answers two batched queries:

* ``occluded(origins[R,3], dirs[R,3]) -> bool[R]`` (any hit; Embree ``rtcOccluded1``),
* ``intersect(origins, dirs) -> (hit bool[R], tri int64[R], bary float64[R,2], t float64[R])``
  (first hit; ``rtcIntersect1``), with the hit point ``(1-u-v)·v0 + u·v1 + v·v2``.

Frame: Embree's float32 ray tests run in a frame centred on the mesh (``center``, its bounding-box
centre, subtracted in float64 before any float32 cast), so a mesh far from the origin (a scan in
world or georeferenced coordinates) traces as it would at the origin: transfer under distant light
is translation-invariant. ``occluded``/``intersect`` take world coordinates and shift them; the bare
``trace`` takes float32 origins already in the caster's frame (``caster.local(points)`` in float64,
then offset and cast). Hit distances and (triangle, barycentrics) are the same in either frame.

Self-intersection: rays leaving a surface are offset by ``eps = offset · (bounding-box
diagonal)`` along the surface normal (towards the side the ray leaves on) when ``normals`` are
given, and by ``eps`` along the ray (equivalent to t_near = eps, which embreex does not expose);
``t`` is reported from the caller's origin.

Parallelism: embreex runs its per-ray loop holding the GIL (measured: two threads on two cores
are no faster than one, see reports/benchmarks/transfer_diffuse.md), so batches above
``min_parallel_rays`` are split over worker *processes* (``python -m
prt_torch.scene._embree_worker``, each with its own Embree scene built once, fed raw float32
arrays over pipes: no pickle, no re-import of the caller's ``__main__``); the calling process
traces one share itself.
"""
from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._checks import check_float, check_int

__all__ = ["RayCaster", "default_workers", "check_traceable"]

from ._embree_worker import INVALID as _INVALID
from ._embree_worker import build_scene as _build_scene
from ._embree_worker import decode_reply, encode_request
from ._embree_worker import trace as _run


def default_workers() -> int:
    """Cores available to this process (``os.sched_getaffinity`` where supported)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def _as_np3(name: str, x: Any) -> np.ndarray:
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} has shape {a.shape}; accepted: [R, 3]")
    return a


#: the coordinate magnitudes Embree's float32 ray-triangle tests handle (measured on occluder_over_plane,
#: 8 rays per vertex against the same mesh at scale 1: identical occlusion for bounding-box diagonals
#: 2.9e-17 … 2.9e13, none of the blocker's shadow at 2.9e-18 and 2.9e14 — products of coordinates
#: leave float32's range); accepted with a margin of 100 to 10^5. Checked on the mesh-centred
#: coordinates (:class:`RayCaster` traces in that frame): a mesh's own extent, not its distance from the origin
MAX_COORDINATE, MIN_DIAGONAL = 1e12, 1e-12


def check_traceable(vertices: np.ndarray, diagonal: float, eps: float, offset: float) -> None:
    """Refuse (ValueError, one line) a mesh Embree cannot trace correctly in float32 even centred on itself:
    ``vertices [N, 3]`` float64 in the caster's frame (the bounding-box centre subtracted, so ``|vertices|``
    is at most half the ``diagonal``). Refused: coordinates above :data:`MAX_COORDINATE` (an extent beyond
    float32's products) or a bounding-box diagonal below :data:`MIN_DIAGONAL`, or float32's spacing at the
    largest coordinate above half the self-intersection offset ``eps`` (= offset × diagonal: only an offset
    below ~1e-7 of the diagonal, the offset origins would round back into the surface). Before the frame was
    centred, a mesh far from the origin was refused here (occluder_over_plane moved by 1e4: float32's spacing
    1.7× eps there, 65% of the rays started inside the surface, every transfer black); it now traces as at the
    origin."""
    far = float(np.abs(vertices).max()) if vertices.size else 0.0
    if far > MAX_COORDINATE or (diagonal < MIN_DIAGONAL and far > 0):
        raise ValueError(f"mesh extent reaches {far:.3g} from its centre with a bounding-box diagonal of {diagonal:.3g}; "
                         f"accepted for ray tracing (Embree, float32, centred on the mesh): |coordinates - centre| <= "
                         f"{MAX_COORDINATE:g} and a diagonal >= {MIN_DIAGONAL:g} (rescale the mesh)")
    spacing = float(np.spacing(np.float32(far)))
    if eps > 0 and spacing > eps / 2:
        raise ValueError(f"self-intersection offset {offset:g} x the bounding-box diagonal {diagonal:.3g} = {eps:.2g} is "
                         f"below twice float32's spacing {spacing:.2g} at the mesh's extent ({far:.3g} from its centre): "
                         f"rays would start inside the surface; accepted: offset >= {2 * spacing / diagonal:.2g}")


def _ended_by_signal(pool: list) -> str | None:
    """The name of the signal that ended one of the worker processes ``pool``, if one did (waiting
    briefly for a dying one), else None."""
    for p in pool:
        try:
            rc = p.wait(timeout=0.2)
        except subprocess.TimeoutExpired:
            continue
        if rc is not None and rc < 0:
            try:
                return signal.Signals(-rc).name
            except ValueError:
                return f"signal {-rc}"
    return None


class RayCaster:
    """Embree ray casting over one triangle mesh.

    Args:
        mesh: a ``prt_torch.scene.Mesh`` (or pass ``vertices=``/``faces=`` arrays).
        workers: processes to split large batches over; ``None`` = all cores, 1 = in-process only.
        offset: self-intersection offset as a fraction of the bounding-box diagonal (default 1e-4,
            about 1000 float32 ulps of the scene extent).
        min_parallel_rays: batches smaller than this are traced in-process (process hand-off
            costs ~24 bytes/ray each way plus a one-off pool start of ~1-2 s).
        chunk_rays: rays per embreex call (bounds temporaries).
    """

    def __init__(self, mesh=None, *, vertices: Any = None, faces: Any = None, workers: int | None = 1,
                 offset: float = 1e-4, min_parallel_rays: int = 200_000, chunk_rays: int = 1 << 20):
        if mesh is not None:
            vertices, faces = mesh.vertices, mesh.faces
        if vertices is None or faces is None:
            raise ValueError("RayCaster needs a mesh or both vertices= and faces=")
        v = _as_np3("vertices", vertices).astype(np.float64)
        f = np.asarray(faces.numpy() if isinstance(faces, torch.Tensor) else faces)
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
            raise ValueError(f"faces have shape {f.shape}; accepted: [F, 3] with F >= 1")
        if not np.isfinite(v).all():
            raise ValueError("vertices hold NaN or Inf; accepted: finite coordinates")
        self.vertices = v
        self.faces = f.astype(np.int64)
        lo, hi = (v.min(0), v.max(0)) if v.shape[0] else (np.zeros(3), np.zeros(3))
        self.center = (lo + hi) / 2  # float64 [3]: the frame Embree traces in (module docstring)
        self._local = v - self.center
        self.scale = float(np.linalg.norm(hi - lo))
        self.offset = check_float("offset", offset, 0.0, 0.1)
        self.eps = self.offset * self.scale
        check_traceable(self._local, self.scale, self.eps, self.offset)
        self.workers = default_workers() if workers is None else check_int("workers", workers, 1, 256)
        self.min_parallel_rays = check_int("min_parallel_rays", min_parallel_rays, 1)
        self.chunk_rays = check_int("chunk_rays", chunk_rays, 1)
        self._scene = _build_scene(self._local, self.faces)
        self._pool = None
        self.rays_traced = 0

    # ---------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Stop the worker processes (the in-process scene stays usable)."""
        if self._pool is not None:
            for p in self._pool:
                try:
                    p.stdin.close()  # EOF: the worker returns
                    p.wait(timeout=5)
                except Exception:
                    p.kill()
                    p.wait()
                try:
                    p.stdout.close()
                except Exception:
                    pass
            self._pool = None

    def __enter__(self) -> "RayCaster":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):  # pragma: no cover - best effort
        try:
            self.close()
        except Exception:
            pass

    def start(self) -> "RayCaster":
        """Start the worker processes now rather than at the first large batch, so that their
        start (interpreter, numpy, embreex, scene build: a few tenths of a second) overlaps the
        caller's own set-up instead of delaying its first batch. No-op with ``workers=1``."""
        if self.workers > 1:
            self._get_pool()
        return self

    def _get_pool(self) -> list:
        """Start ``workers - 1`` worker processes (each builds its own Embree scene once)."""
        if self._pool is None:
            env = dict(os.environ)
            root = str(Path(__file__).resolve().parents[2])
            env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
            v = np.ascontiguousarray(self._local, "<f4")  # the caster's frame, as the in-process scene
            f = np.ascontiguousarray(self.faces, "<i4")
            procs = []
            for _ in range(self.workers - 1):
                p = subprocess.Popen([sys.executable, "-m", "prt_torch.scene._embree_worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=env)
                p.stdin.write(b"PRTE" + struct.pack("<QQ", v.shape[0], f.shape[0]))
                p.stdin.write(v.data)
                p.stdin.write(f.data)
                p.stdin.flush()
                procs.append(p)
            self._pool = procs
        return self._pool

    # ---------------------------------------------------------------- helpers
    def local(self, points: Any) -> Any:
        """World positions ``[..., 3]`` in the caster's frame, ``points - center`` in float64 (torch in, torch out;
        otherwise numpy): what :meth:`trace`'s float32 origins are built from (offset, then cast), so that a mesh
        far from the origin keeps its float32 precision."""
        if isinstance(points, torch.Tensor):
            return points.to(torch.float64) - torch.from_numpy(self.center)
        return np.asarray(points, np.float64) - self.center

    def prepare(self, origins: Any, dirs: Any, normals: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Offset origins off the surface and return contiguous float32 ``(origins, dirs)``, the origins in the
        caster's frame (world ``origins`` minus :attr:`center`, in float64 before the cast).

        ``o' = o + eps·sign(n·d)·n + eps·d`` (the normal term only when ``normals`` are given).
        """
        o = _as_np3("origins", origins).astype(np.float64) - self.center
        d = _as_np3("dirs", dirs).astype(np.float64)
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and dirs {d.shape} differ; accepted: equal [R, 3] shapes")
        if normals is not None:
            n = _as_np3("normals", normals).astype(np.float64)
            if n.shape != o.shape:
                raise ValueError(f"normals {n.shape} and origins {o.shape} differ; accepted: equal [R, 3] shapes")
            side = np.where(np.einsum("ij,ij->i", n, d) >= 0, self.eps, -self.eps)
            o = o + side[:, None] * n
        o = o + self.eps * d
        return np.ascontiguousarray(o, np.float32), np.ascontiguousarray(d, np.float32)

    def _dispatch(self, query: str, o: np.ndarray, d: np.ndarray, tfar: np.ndarray | None):
        R = o.shape[0]
        self.rays_traced += R
        if self.workers == 1 or R < self.min_parallel_rays:
            return _run(self._scene, query, o, d, tfar, self.chunk_rays)
        pool = self._get_pool()
        op = 1 if query == "occluded" else 2
        bounds = np.linspace(0, R, self.workers + 1).astype(np.int64)
        try:
            for w, p in enumerate(pool, start=1):  # hand each worker its share, then trace ours
                s, e = bounds[w], bounds[w + 1]
                for part in encode_request(op, o[s:e], d[s:e], None if tfar is None else tfar[s:e], self.chunk_rays):
                    p.stdin.write(part)
                p.stdin.flush()
            s, e = bounds[0], bounds[1]
            parts = [_run(self._scene, query, o[s:e], d[s:e], None if tfar is None else tfar[s:e], self.chunk_rays)]
            for w, p in enumerate(pool, start=1):
                parts.append(decode_reply(p.stdout, op, int(bounds[w + 1] - bounds[w])))
        except (EOFError, BrokenPipeError, OSError) as err:
            ended_by = _ended_by_signal(pool)
            self.close()
            if ended_by:  # Ctrl-C or kill to the process group: this process was signalled too; let its handler raise
                time.sleep(0.5)  # (KeyboardInterrupt, or the CLI's SIGTERM) instead of reporting the worker's end as a failure
                raise ChildProcessError(f"a ray-casting worker process was ended by {ended_by} (not this process); "
                                   "retry, or with workers=1") from None
            raise ChildProcessError(f"a ray-casting worker process failed ({err!r}); retry with workers=1") from None
        if query == "occluded":
            return np.concatenate(parts)
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(4))

    # ---------------------------------------------------------------- queries
    def trace(self, origins: np.ndarray, dirs: np.ndarray, query: str = "occluded", tfar: np.ndarray | None = None):
        """The bare path: float32 numpy rays, no offsets, straight to Embree (split over workers). ``origins`` are in
        the caster's frame: build them from :meth:`local` positions (float64) before the float32 cast — world
        coordinates cast to float32 lose the precision the offsets need far from the origin.

        Returns numpy ``bool [R]`` for ``query='occluded'``, or ``(primID int32 [R] (-1 = miss),
        u float32 [R], v float32 [R], tfar float32 [R])`` for ``'intersect'``.
        """
        if query not in ("occluded", "intersect"):
            raise ValueError(f"query={query!r}; accepted: 'occluded' or 'intersect'")
        o = np.ascontiguousarray(origins, np.float32)
        d = np.ascontiguousarray(dirs, np.float32)
        if o.ndim != 2 or o.shape[1] != 3 or o.shape != d.shape:
            raise ValueError(f"origins {o.shape} / dirs {d.shape}; accepted: equal [R, 3] shapes")
        return self._dispatch(query, o, d, None if tfar is None else np.ascontiguousarray(tfar, np.float32))

    def occluded(self, origins: Any, dirs: Any, normals: Any = None, tfar: Any = None) -> torch.Tensor:
        """Any-hit test.

        Args:
            origins, dirs: ``[R,3]`` (torch or numpy; dirs unit length).
            normals: optional ``[R,3]`` surface normals at the origins (self-intersection offset).
            tfar: optional ``[R]`` or scalar maximum distance (default: infinite).
        Returns:
            ``bool [R]`` torch tensor, True where the ray hits any triangle.
        """
        o, d = self.prepare(origins, dirs, normals)
        tf = None
        if tfar is not None:
            tf = np.broadcast_to(np.asarray(tfar.numpy() if isinstance(tfar, torch.Tensor) else tfar, np.float64),
                                 (o.shape[0],)) - self.eps
            tf = np.ascontiguousarray(np.maximum(tf, 0.0), np.float32)
        return torch.from_numpy(self._dispatch("occluded", o, d, tf))

    def intersect(self, origins: Any, dirs: Any, normals: Any = None):
        """First-hit query.

        Returns:
            ``hit bool[R]``, ``tri int64[R]`` (-1 on a miss), ``bary float64[R,2]`` = (u, v) with
            hit point (1-u-v)·v0 + u·v1 + v·v2 of ``faces[tri]``, ``t float64[R]`` distance from
            the offset origin plus eps, i.e. ≈ from the given origin (inf on a miss).
        """
        o, d = self.prepare(origins, dirs, normals)
        prim, u, v, t = self._dispatch("intersect", o, d, None)
        hit = prim != _INVALID
        tri = np.where(hit, prim, -1).astype(np.int64)
        bary = np.stack([u, v], 1).astype(np.float64)
        bary[~hit] = 0.0
        t = np.where(hit, t.astype(np.float64) + self.eps, np.inf)
        return torch.from_numpy(hit), torch.from_numpy(tri), torch.from_numpy(bary), torch.from_numpy(t)
