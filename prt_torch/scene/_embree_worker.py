"""Embree scene construction and tracing loops, importing only numpy and embreex.

Kept free of torch so that ray-casting worker processes (``python -m
prt_torch.scene._embree_worker``) start in a fraction of a second: ``prt_torch.scene`` imports
its submodules lazily, so this module loads without torch or trimesh.
"""
from __future__ import annotations

import numpy as np

# Embree reports "no geometry" as RTC_INVALID_GEOMETRY_ID = 0xFFFFFFFF, i.e. -1 as int32.
INVALID = -1

def build_scene(vertices: np.ndarray, faces: np.ndarray):
    """An ``embreex`` scene holding one triangle mesh (float32 vertices, int32 indices)."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32))
    return scene


def trace(scene, query: str, o: np.ndarray, d: np.ndarray, tfar, chunk: int):
    """Trace rays in chunks of ``chunk`` (bounds embreex temporaries) on one scene; numpy in/out.

    ``query='occluded'`` -> bool [R]; ``'intersect'`` -> (primID int32, u, v, tfar float32).
    """
    R = o.shape[0]
    if query == "occluded":
        out = np.empty(R, dtype=bool)
    else:
        out = (np.empty(R, np.int32), np.empty(R, np.float32), np.empty(R, np.float32), np.empty(R, np.float32))
    for s in range(0, R, chunk):  # a handful of chunks per call
        e = min(R, s + chunk)
        dists = None if tfar is None else np.ascontiguousarray(tfar[s:e], np.float32)
        if query == "occluded":
            r = scene.run(o[s:e], d[s:e], dists=dists, query="OCCLUDED")
            out[s:e] = r != INVALID
        else:
            r = scene.run(o[s:e], d[s:e], dists=dists, output=1)
            out[0][s:e] = r["primID"]
            out[1][s:e] = r["u"]
            out[2][s:e] = r["v"]
            out[3][s:e] = r["tfar"]
    return out


# ----------------------------------------------------------------------------------------
# worker process: `python -m prt_torch.scene._embree_worker`, raw little-endian arrays over
# stdin/stdout (no pickle, no re-import of the caller's __main__, no torch).
#   init:     b"PRTE" uint64 V uint64 F | float32 [V,3] | int32 [F,3]
#   request:  uint8 op (0 quit, 1 occluded, 2 intersect) uint8 has_tfar uint64 R uint64 chunk
#             | float32 o [R,3] | float32 d [R,3] | (float32 tfar [R])
#   reply:    occluded: bool [R]; intersect: int32 prim [R] | float32 u, v, tfar [R]
# ----------------------------------------------------------------------------------------
import struct  # noqa: E402

_HDR = struct.Struct("<BBQQ")


def _read_exact(stream, n: int) -> bytes:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = stream.readinto(view[got:])
        if not k:
            raise EOFError
        got += k
    return bytes(buf) if n == 0 else buf


def encode_request(op: int, o: np.ndarray, d: np.ndarray, tfar, chunk: int) -> list:
    parts = [_HDR.pack(op, tfar is not None, o.shape[0], chunk), np.ascontiguousarray(o, "<f4").data,
             np.ascontiguousarray(d, "<f4").data]
    if tfar is not None:
        parts.append(np.ascontiguousarray(tfar, "<f4").data)
    return parts


def decode_reply(stream, op: int, R: int):
    if op == 1:
        return np.frombuffer(_read_exact(stream, R), dtype=bool).copy()
    raw = _read_exact(stream, 16 * R)
    prim = np.frombuffer(raw, "<i4", R, 0).copy()
    u = np.frombuffer(raw, "<f4", R, 4 * R).copy()
    v = np.frombuffer(raw, "<f4", R, 8 * R).copy()
    t = np.frombuffer(raw, "<f4", R, 12 * R).copy()
    return prim, u, v, t


def _serve(inp, out) -> None:
    magic = _read_exact(inp, 4)
    if bytes(magic) != b"PRTE":
        raise SystemExit("bad handshake")
    V, F = struct.unpack("<QQ", _read_exact(inp, 16))
    verts = np.frombuffer(_read_exact(inp, 12 * V), "<f4").reshape(V, 3)
    faces = np.frombuffer(_read_exact(inp, 12 * F), "<i4").reshape(F, 3)
    scene = build_scene(verts, faces)
    while True:
        try:
            op, has_t, R, chunk = _HDR.unpack(_read_exact(inp, _HDR.size))
        except EOFError:
            return
        if op == 0:
            return
        raw = _read_exact(inp, 24 * R + (4 * R if has_t else 0))
        o = np.frombuffer(raw, "<f4", 3 * R, 0).reshape(R, 3)
        d = np.frombuffer(raw, "<f4", 3 * R, 12 * R).reshape(R, 3)
        tf = np.frombuffer(raw, "<f4", R, 24 * R) if has_t else None
        res = trace(scene, "occluded" if op == 1 else "intersect", o, d, tf, int(chunk))
        if op == 1:
            out.write(np.ascontiguousarray(res).data)
        else:
            for a in res:
                out.write(np.ascontiguousarray(a).data)
        out.flush()


if __name__ == "__main__":  # pragma: no cover - runs in the worker process
    import signal
    import sys

    # Any signal ends the worker quietly: Ctrl-C reaches the whole process group (the parent says what
    # was kept and how to resume; a traceback from here would only bury that), SIGTERM/SIGHUP by default.
    for sig in ("SIGINT", "SIGTERM", "SIGHUP"):
        if hasattr(signal, sig) and signal.getsignal(getattr(signal, sig)) is not signal.SIG_IGN:  # ignored stays ignored,
            signal.signal(getattr(signal, sig), signal.SIG_DFL)  # as the parent's (a background job's SIGINT, nohup's SIGHUP)
    try:
        _serve(sys.stdin.buffer, sys.stdout.buffer)
    except (BrokenPipeError, ConnectionError, EOFError):  # the parent went away mid-request: nothing to report to
        sys.exit(1)
