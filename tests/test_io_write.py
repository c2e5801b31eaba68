"""``io.save``'s own safetensors writer (issue 42 §2: chunks written from the tensors' memory, no serialised copy, and
the transport chunks past the page cache): checked against the ``safetensors`` library itself — the same bytes as its
``save_file`` for every dtype it lays out (order by dtype then name, padding, empty and 0-d tensors, non-ASCII
metadata), and ``direct=True`` files (``O_DIRECT``, header padded to the tensor's address) read back identically by
``safetensors.torch.load_file`` and ``io.load`` at every alignment and length tail; the atomic rename, and a failed
write (disk full, mid-file) leaving neither the file nor its temporary behind."""
from __future__ import annotations

import errno
import json
import os

import pytest
import torch
from safetensors.torch import load_file, save_file

from prt_torch import io


def _lib_bytes(tmp_path, tensors, kind, meta=None):
    """The file ``safetensors.torch.save_file`` writes for what ``io.save`` is given (the same metadata text)."""
    text = json.dumps({"format": io.FORMAT, "format_version": io.FORMAT_VERSION, "kind": kind, **(meta or {})})
    p = tmp_path / "lib.safetensors"
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(p), metadata={io.FORMAT: text})
    return p.read_bytes()


def _every_dtype():
    g = torch.Generator().manual_seed(3)
    out = {}
    for i, (dt, _) in enumerate(io._ST_DTYPES):
        x = torch.randint(0, 100, (2, 3), generator=g, dtype=torch.int64) if dt != torch.bool else torch.rand(2, 3, generator=g) > 0.5
        out[f"t{(7 * i) % 13}_{i}"] = x.to(dt)
    out["a_same_dtype_as_t0"] = torch.rand(5, generator=g).double()  # ties: by name
    out["scalar"] = torch.tensor(2.5)
    out["empty"] = torch.zeros(0, 4, dtype=torch.float16)
    return out


@pytest.mark.parametrize("case", ["every_dtype", "one_big", "none"])
def test_the_same_bytes_as_safetensors(tmp_path, case):
    tensors = {"every_dtype": _every_dtype, "one_big": lambda: {"data": torch.rand(1001, 37)[:, 1:]},  # made contiguous
               "none": dict}[case]()
    meta = {"név": "é \x01 \"quoted\" \\ /", "n": [1, 2.5, None]}
    io.save(tmp_path / "mine.prt", tensors, kind="test/bytes", meta=meta)
    assert (tmp_path / "mine.prt").read_bytes() == _lib_bytes(tmp_path, tensors, "test/bytes", meta)
    got, m = io.load(tmp_path / "mine.prt")
    assert m["név"] == meta["név"] and set(got) == set(tensors)
    assert all(torch.equal(got[k], v) and got[k].dtype == v.dtype for k, v in tensors.items())


@pytest.mark.parametrize("shift,length", [(0, io._DIRECT_MIN), (2, io._DIRECT_MIN + 4), (514, 3 * io._DIRECT_MIN + 4092),
                                          (1022, io._DIRECT_MIN + 4096)])
def test_direct_files_read_back_identically(tmp_path, shift, length):
    """A float32 tensor starting ``shift`` elements into its storage (addresses at several 8-byte residues modulo
    4 KiB), of lengths with and without a partial last block, a small int64 tensor laid out before it: the library
    reads the same values and names; the header is padded to the tensor's address (the page cache bypassed: not
    checked here, it is the system time the benchmark measures)."""
    base = torch.rand(shift + length // 4 + 1, generator=torch.Generator().manual_seed(shift))
    big = base[shift:shift + length // 4]
    small = torch.arange(5, dtype=torch.int64)
    io.save(tmp_path / "d.prt", {"data": big, "z_small": small}, kind="test/direct", meta={"x": 1}, direct=True)
    got = load_file(str(tmp_path / "d.prt"))
    assert torch.equal(got["data"], big) and torch.equal(got["z_small"], small)
    t, m = io.load(tmp_path / "d.prt")
    assert torch.equal(t["data"], big) and m["x"] == 1 and m["kind"] == "test/direct"
    raw = (tmp_path / "d.prt").read_bytes()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8:8 + n])
    assert list(header)[1:] == ["z_small", "data"]  # int64 before float32: the small tensor is staged before the big one
    assert (8 + n + header["data"]["data_offsets"][0]) % 4096 == big.data_ptr() % 4096  # padded to the tensor's address
    assert os.path.getsize(tmp_path / "d.prt") == 8 + n + big.numel() * 4 + 5 * 8
    assert not list(tmp_path.glob("*.partial"))


def test_direct_below_its_threshold_is_the_library_file(tmp_path):
    """``direct=True`` for a small tensor, two big ones, a big one at an address not a multiple of 8 (its header
    could not be padded to it in 8-byte steps), or one after tensors whose bytes are not a multiple of 8 (the header
    would not be; safetensors' writers keep it so): the ordinary (library) bytes."""
    odd = torch.rand(io._DIRECT_MIN // 4 + 1)[1:]
    # int32 [3] (12 bytes) laid out before a float16 tensor: the header padded to its address would be no multiple of 8
    after_odd = {"data": torch.rand(io._DIRECT_MIN // 2).half(), "ids": torch.arange(3, dtype=torch.int32)}
    for tensors in ({"data": torch.rand(100)}, {"a": torch.rand(io._DIRECT_MIN // 4), "b": torch.rand(io._DIRECT_MIN // 4)},
                    {"data": odd}, after_odd):
        io.save(tmp_path / "s.prt", tensors, kind="k", direct=True)
        assert (tmp_path / "s.prt").read_bytes() == _lib_bytes(tmp_path, tensors, "k")


@pytest.mark.parametrize("direct", [False, True])
def test_a_failed_write_leaves_nothing_and_keeps_the_old_file(tmp_path, monkeypatch, direct):
    """Disk full in the middle of the data: OSError naming the path, no file, no temporary; an existing file at the path
    stays as it was (the rename never happened); the next write succeeds and replaces it."""
    path = tmp_path / "chunk.prt"
    data = {"data": torch.rand(io._DIRECT_MIN // 4 * 2)}
    real = os.write
    calls = {"n": 0}

    def full(fd, buf):
        calls["n"] += 1
        if calls["n"] == 2:  # the header went through; the data does not
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, buf)

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError, match=r"cannot write .*chunk\.prt.*No space left"):
        io.save(path, data, kind="k", direct=direct)
    assert not list(tmp_path.iterdir())
    monkeypatch.setattr(os, "write", real)
    io.save(path, {"old": torch.ones(3)}, kind="k")
    old = path.read_bytes()
    calls["n"] = 0
    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OSError, match="No space left"):
        io.save(path, data, kind="k", direct=direct)
    assert path.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["chunk.prt"]
    monkeypatch.setattr(os, "write", real)
    io.save(path, data, kind="k", direct=direct)
    assert torch.equal(load_file(str(path))["data"], data["data"])
    with pytest.raises(FileExistsError, match="exists"):
        io.save(path, data, kind="k", overwrite=False, direct=direct)


def test_direct_falls_back_where_the_file_system_refuses_it(tmp_path, monkeypatch):
    """EINVAL from an ``O_DIRECT`` open (tmpfs, some network file systems): the file is written through the page cache,
    the library's bytes."""
    real = os.open

    def no_direct(path, flags, *a):
        if flags & getattr(os, "O_DIRECT", 0):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real(path, flags, *a)

    monkeypatch.setattr(os, "open", no_direct)
    data = {"data": torch.rand(io._DIRECT_MIN // 4 + 3)}
    io.save(tmp_path / "f.prt", data, kind="k", direct=True)
    assert (tmp_path / "f.prt").read_bytes() == _lib_bytes(tmp_path, data, "k")


def test_views_are_written_as_their_values(tmp_path):
    """A conjugate (lazy: the conj bit), a negated view, a strided slice, two views of one storage (which
    ``safetensors``' ``save_file`` refuses): the values they show, each on its own."""
    z = torch.tensor([1 + 2j, -3 - 0.5j], dtype=torch.complex64)
    x = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    tensors = {"conj": z.conj(), "neg": z.conj().imag, "cols": x[:, 1::2], "all": x, "row": x[1]}
    io.save(tmp_path / "v.prt", tensors, kind="k")
    got, _ = io.load(tmp_path / "v.prt")
    assert torch.equal(got["all"], x) and torch.equal(got["row"], x[1])
    assert torch.equal(got["conj"], torch.tensor([1 - 2j, -3 + 0.5j], dtype=torch.complex64))
    assert torch.equal(got["neg"], torch.tensor([-2.0, 0.5])) and torch.equal(got["cols"], x[:, 1::2])


def test_the_transport_chunk_writer_writes_past_the_page_cache(tmp_path, monkeypatch):
    """``precompute_transport``'s chunks of ≥ 4 MiB go through the ``O_DIRECT`` writer (counted), and each file holds
    the chunk's table: the same values as the chunk computed again in memory (``_chunk_transport``, the same inputs)."""
    from prt_torch.brdf import AshikhminShirley
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, precompute_transport
    from prt_torch.transfer import transport as TT
    from prt_torch.transfer.glossy import check_frames

    calls = []
    real = io._write_direct
    monkeypatch.setattr(io, "_write_direct", lambda *a: (calls.append(a[3]), real(*a)))
    mesh = builtin("convex", "small")
    t = precompute_transport(mesh, tmp_path / "t", views=3, res=8, supersample=1, shadows=False, max_chunks=2,
                             run=RunOptions(chunk_size=32, workers=1))
    assert calls == ["data", "data"]  # 32 vertices x 92 views x 384 texels x 4 bytes = 4.5 MiB per chunk
    texels = TT.cube_directions(8)[0].reshape(-1, 3)
    F = check_frames(mesh)
    for a, b, T in t:
        want = TT._chunk_transport(None, AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0), mesh.vertices[a:b], mesh.normals[a:b],
                                   F[a:b], texels, t.views, None, False, torch.float32)
        assert torch.equal(T.reshape(b - a, -1), want.reshape(b - a, -1)) and float(want.max()) > 0


@pytest.mark.parametrize("direct", [False, True])
def test_short_writes_are_continued(tmp_path, monkeypatch, direct):
    """``os.write`` writing less than asked (Linux: at most 2 GiB - 4 KiB per call; a signal): the rest is written,
    the file whole — here at most 1 MiB per call (a whole number of blocks, as the kernel's own cap)."""
    real = os.write
    sizes = []

    def short(fd, buf):
        n = real(fd, memoryview(buf)[:1 << 20])
        sizes.append(n)
        return n

    monkeypatch.setattr(os, "write", short)
    data = {"data": torch.rand(io._DIRECT_MIN // 4 * 3 + 5), "ids": torch.arange(9, dtype=torch.int32)}
    io.save(tmp_path / "s.prt", data, kind="k", direct=direct)
    monkeypatch.setattr(os, "write", real)
    got = load_file(str(tmp_path / "s.prt"))
    assert torch.equal(got["data"], data["data"]) and torch.equal(got["ids"], data["ids"])
    assert len(sizes) > 12 and max(sizes) == 1 << 20
    if not direct:
        assert (tmp_path / "s.prt").read_bytes() == _lib_bytes(tmp_path, data, "k")


@pytest.mark.parametrize("bad", ["no", 1, None])
def test_direct_must_be_a_bool(tmp_path, bad):
    """``direct`` is refused unless True or False (a truthy string would take the O_DIRECT path unasked), naming the
    parameter and value, before anything is written."""
    with pytest.raises(ValueError, match=r"^direct=.*; accepted: True or False$"):
        io.save(tmp_path / "x.prt", {"a": torch.ones(2)}, kind="k", direct=bad)
    assert not list(tmp_path.iterdir())


def test_direct_falls_back_when_a_write_is_refused_midway(tmp_path, monkeypatch):
    """EINVAL from a write on the ``O_DIRECT`` descriptor after its first block went out (a device whose logical
    block is larger than 4 KiB): the file is rewritten from the start through the page cache — the library's bytes,
    nothing of the refused attempt left (not its length, not its padded header)."""
    real_open, real_write = os.open, os.write
    try:  # this file system must take O_DIRECT for the midway refusal to be reached (tmpfs refuses it at the open)
        os.close(real_open(tmp_path / "probe", os.O_WRONLY | os.O_CREAT | getattr(os, "O_DIRECT", 0)))
        os.unlink(tmp_path / "probe")
    except OSError as e:
        pytest.skip(f"no O_DIRECT here: {e}")
    direct_fds, calls = set(), {"n": 0}

    def opener(path, flags, *a):
        fd = real_open(path, flags, *a)
        if flags & getattr(os, "O_DIRECT", 0):
            direct_fds.add(fd)
        else:
            direct_fds.discard(fd)
        return fd

    def writer(fd, buf):
        if fd in direct_fds:
            calls["n"] += 1
            if calls["n"] == 2:
                raise OSError(errno.EINVAL, "Invalid argument")
        return real_write(fd, buf)

    monkeypatch.setattr(os, "open", opener)
    monkeypatch.setattr(os, "write", writer)
    data = {"data": torch.rand(io._DIRECT_MIN // 4 * 2 + 3), "ids": torch.arange(7, dtype=torch.int64)}
    io.save(tmp_path / "f.prt", data, kind="k", direct=True)
    monkeypatch.setattr(os, "write", real_write)
    assert calls["n"] == 2  # the O_DIRECT path was taken, and refused midway
    assert (tmp_path / "f.prt").read_bytes() == _lib_bytes(tmp_path, data, "k")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.prt", "lib.safetensors"]


def test_atomic_path_concurrent_threads_write_whole_files(tmp_path):
    """Eight threads saving to one path at once (each a different tensor): every save succeeds, the file left is
    exactly one thread's tensor (checked with the safetensors library, not io.load), and no temporary file remains.
    With one temporary name per process, the threads wrote into each other's file or renamed it away under each
    other (FileNotFoundError)."""
    import threading

    path = tmp_path / "shared.prt"
    tensors = [torch.full((50_000,), float(i)) for i in range(8)]
    errors, barrier = [], threading.Barrier(len(tensors))

    def write(i):
        barrier.wait()
        try:
            for _ in range(5):
                io.save(path, {"x": tensors[i]}, kind="test/threads")
        except Exception as e:  # noqa: BLE001 - collected for the assertion below
            errors.append(e)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(len(tensors))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    got = load_file(str(path))["x"]
    assert any(torch.equal(got, t) for t in tensors)
    assert not list(tmp_path.glob("*.partial"))


def test_save_writes_strict_json_metadata(tmp_path):
    """A NaN or infinity in the metadata is written as null: the header parses with a parser that refuses
    Python's NaN/Infinity tokens (json.loads with parse_constant raising, as JavaScript's or serde's would)."""
    import struct

    io.save(tmp_path / "m.prt", {"x": torch.zeros(2)}, kind="test/nan", meta={"a": float("nan"), "b": [1.0, float("inf")],
                                                                              "c": {"d": -float("inf")}, "e": 2.5})
    raw = (tmp_path / "m.prt").read_bytes()
    n = struct.unpack("<Q", raw[:8])[0]

    def refuse(tok):
        raise ValueError(f"non-standard JSON token {tok}")

    header = json.loads(raw[8:8 + n])
    meta = json.loads(header["__metadata__"]["prt_torch"], parse_constant=refuse)
    assert meta["a"] is None and meta["b"] == [1.0, None] and meta["c"] == {"d": None} and meta["e"] == 2.5
    _, m = io.load(tmp_path / "m.prt")
    assert m["a"] is None and m["e"] == 2.5
