"""The signal of a fit read by row chunks: held once, never copied whole (issue 42 part 3).

A codec fit needs the centred signal ``x_p − x̄`` (Sloan 2003 §4.1: PCA of the centred rows; the
offset is subtracted for float32 precision only) many times over: k-means assignments, cluster
means, scatter products, classifications. Materialising it costs a second copy of the signal,
and a tile-ordered copy per cluster layout a third and fourth (``segment``). Here the signal
stays where the caller has it — a tensor, a numpy array or a read-only ``np.memmap`` of a file
(``io.load_mmap``) — and every pass reads it by chunks of rows, centred on the fly:

* :class:`CentredRows` ``[P, D]``: ``rows[i:j]`` / ``rows.index_select(0, idx)`` give the centred
  rows in the fit dtype (each value computed exactly as the whole-signal expression would: the
  same elementwise operation, so a chunked fit equals a fit on a materialised copy bit for bit);
  ``rows.chunks()`` yields ``(i, j, Xc[i:j])`` blocks of :data:`CHUNK_BYTES`.
* :func:`centred` chooses: a signal of at most :data:`STREAM_BYTES` is materialised (one chunk:
  every pass works on a plain tensor, the former path, bit for bit), a larger one — or any
  signal with ``stream`` (a memory-mapped input) — is a :class:`CentredRows` read by chunks.
  Why a threshold: streaming re-reads the rows in cluster-tile order for every pass where the
  in-memory path orders them once per round; paired on this 2-core machine under load (12k ×
  600 float64, CPCA 32×8) the streamed fit took 2.6× the in-memory one's time, so streaming is
  what a large signal gets, not a small one.
* :func:`spans` / :func:`row_sq_norms`: the chunk boundaries and ``||x_p||²`` by chunks.

Shapes: ``X [P, D]`` float32/float64; offsets ``[D]`` float64.
"""
from __future__ import annotations

import torch

__all__ = ["CHUNK_BYTES", "STREAM_BYTES", "fit_memory", "BOOKKEEPING_BYTES", "FIXED_BYTES", "CentredRows", "centred",
           "spans", "row_chunks", "row_sq_norms", "chunk_rows"]

#: Bytes of signal per chunk of a streamed fit: the work memory of every pass is a few times
#: this (the chunk centred, its tile-ordered copy, its GEMM outputs), whatever P.
CHUNK_BYTES = 16 * 2**20
#: Signals larger than this are fitted by chunks by default (smaller ones: one materialised chunk).
STREAM_BYTES = 256 * 2**20


def chunk_rows(D: int, itemsize: int = 4, chunk_bytes: int | None = None) -> int:
    """Rows per chunk: ``chunk_bytes`` (default :data:`CHUNK_BYTES`) of ``[rows, D]`` values, at
    least 256 rows (so that per-chunk work — a sort, a few batched GEMMs — stays amortised)."""
    b = CHUNK_BYTES if chunk_bytes is None else int(chunk_bytes)
    return max(256, b // max(1, D * itemsize))


def spans(P: int, rows: int) -> list[tuple[int, int]]:
    """``[(i, j), ...]`` covering ``range(P)`` in blocks of ``rows``."""
    return [(i, min(P, i + rows)) for i in range(0, P, max(1, rows))]


class CentredRows:
    """``x_p − offset`` of a signal ``X [P, D]`` in ``dtype``, computed by chunks when read.

    ``X`` is not copied (a memory-mapped array stays on disk; its pages are read per chunk).
    The centring is the elementwise expression of ``AffineCodec.fit``: float32 data in a
    float32 fit ``X − offset.to(float32)``, otherwise (and always with ``via64``, as ``encode``)
    ``(X.double() − offset).to(dtype)``.
    Supports what the fit's passes use: ``shape``, ``dtype``, ``element_size()``, slicing by a
    row range, ``index_select(0, idx)``, ``chunks()``; ``materialize()`` for a small signal.
    """

    def __init__(self, X: torch.Tensor, offset: torch.Tensor, dtype: torch.dtype, rows: int | None = None,
                 via64: bool = False):
        self.X, self.offset, self.dtype, self.via64 = X, offset.double(), dtype, via64
        self.shape = torch.Size(X.shape)
        self._off32 = self.offset.to(torch.float32)
        self.rows = int(rows) if rows is not None else chunk_rows(self.shape[1], torch.tensor([], dtype=dtype).element_size())

    def element_size(self) -> int:
        return torch.tensor([], dtype=self.dtype).element_size()

    def _centre(self, x: torch.Tensor) -> torch.Tensor:
        if self.dtype == x.dtype == torch.float32 and not self.via64:
            return x - self._off32
        return (x.double() - self.offset).to(self.dtype)

    def __getitem__(self, key) -> torch.Tensor:
        if not isinstance(key, slice):
            raise TypeError(f"CentredRows takes a row slice, got {type(key).__name__}")
        return self._centre(self.X[key])

    def index_select(self, dim: int, idx: torch.Tensor) -> torch.Tensor:
        if dim != 0:
            raise ValueError(f"CentredRows.index_select: dim={dim}; accepted: 0")
        return self._centre(self.X.index_select(0, idx))

    def chunks(self, rows: int | None = None):
        """Yield ``(i, j, centred rows i..j [j−i, D])`` over the signal, in order."""
        for i, j in spans(self.shape[0], rows or self.rows):
            yield i, j, self[i:j]

    def materialize(self) -> torch.Tensor:
        """The whole centred signal as one tensor (a copy; for small signals only)."""
        out = torch.empty(self.shape, dtype=self.dtype)
        for i, j, x in self.chunks():
            out[i:j] = x
        return out


def centred(X: torch.Tensor, offset: torch.Tensor, dtype: torch.dtype, chunk_bytes: int | None = None,
            via64: bool = False, stream_bytes: int | None = None, stream: bool = False):
    """The centred signal for a fit: a tensor when it takes at most ``stream_bytes`` (default
    :data:`STREAM_BYTES`) and ``stream`` is false (materialised: one chunk), else a
    :class:`CentredRows` read by chunks of ``chunk_bytes`` (default :data:`CHUNK_BYTES`)."""
    itemsize = torch.tensor([], dtype=dtype).element_size()
    b = CHUNK_BYTES if chunk_bytes is None else int(chunk_bytes)
    s = STREAM_BYTES if stream_bytes is None else int(stream_bytes)
    rows = CentredRows(X, offset, dtype, rows=chunk_rows(X.shape[1], itemsize, b), via64=via64)
    if not stream and X.shape[0] * X.shape[1] * itemsize <= s:
        return rows.materialize()
    return rows


def row_chunks(X, rows: int | None = None):
    """``(i, j, X[i:j])`` blocks of a tensor or :class:`CentredRows` (a tensor: one block when
    ``rows`` is None)."""
    if isinstance(X, CentredRows):
        yield from X.chunks(rows)
        return
    for i, j in spans(X.shape[0], rows or max(1, X.shape[0])):
        yield i, j, X[i:j]


def row_sq_norms(X, norm: bool = False) -> torch.Tensor:
    """``||x_p||²`` ``[P]`` in X's dtype (tensor or :class:`CentredRows`), by chunks of rows
    (no ``[P, D]`` temporary): ``Σ_d x²`` (``x.square().sum(1)``, k-means's form), or with
    ``norm`` the squared ``vector_norm`` (CPCA's)."""
    out = torch.empty(X.shape[0], dtype=X.dtype)
    rows = X.rows if isinstance(X, CentredRows) else chunk_rows(X.shape[1], X.element_size())
    for i, j, x in row_chunks(X, rows):
        out[i:j] = torch.linalg.vector_norm(x, dim=1).square_() if norm else x.square().sum(1)
    return out


#: Per-point bookkeeping of an affine fit besides the signal and its codes: labels (int64),
#: ``||x||²``, Lloyd's float64 bounds and their per-iteration temporaries, classification minima
#: and candidates. Measured: the peak of a streamed 1M × 16 CPCA 16×4 fit above the signal was
#: 151 B per point (``fit_encode`` of a tensor, after a warm-up).
BOOKKEEPING_BYTES = 160
#: Fixed work of a fit whatever P: the classification and assignment GEMM blocks
#: (``kmeans.CACHE_BLOCK_BYTES``) and their temporaries; the marginal memory of a 10k-point
#: CPCA 16×4 fit was 16.6 MiB for 7 MiB of counted arrays (reports/benchmarks/scale_stream.md).
FIXED_BYTES = 16 * 2**20


def fit_memory(P: int, D: int, clusters: int = 1, vectors: int = 0, streamed: bool | None = None,
               dtype_bytes: int | None = None, chunk_bytes: int | None = None, stream_bytes: int | None = None) -> dict:
    """What an affine codec fit + encode of ``[P, D]`` float32 will hold, before it starts
    (``prt compress --dry-run``): ``{'streamed', 'signal', 'copies', 'work', 'bookkeeping', 'codes',
    'peak'}`` in bytes; ``peak`` = the counted sum × ``transfer.estimate.ALLOCATOR_SLACK`` (freed
    temporaries the allocator keeps, as the precompute's estimate) + :data:`FIXED_BYTES`.
    ``signal``: the input loaded (0 when streamed from a memory-mapped file:
    its pages are read per chunk and can be dropped). In memory the fit holds the centred copy
    and two tile-ordered buffers (``copies``); streamed, three chunks (``work``). The fit dtype
    is float64 when P·D ≤ 2²³ (``fit_dtype='auto'``)."""
    s = dtype_bytes or (8 if P * D <= 2**23 else 4)
    b = CHUNK_BYTES if chunk_bytes is None else int(chunk_bytes)
    if streamed is None:
        streamed = P * D * s > (STREAM_BYTES if stream_bytes is None else int(stream_bytes))
    K = max(1, int(clusters))
    if streamed:
        rows = min(P, chunk_rows(D, s, b))
        T = 256
        signal, copies, work = 0, 0, (3 * rows + 2 * K * (T - 1)) * D * s
    else:
        T = 256
        signal, copies, work = P * D * 4, (P + 2 * (P + K * (T - 1))) * D * s, 0
    book = BOOKKEEPING_BYTES * P
    codes = P * (4 * int(vectors) + (1 if K <= 256 else 2 if K <= 32768 else 4))
    from ..transfer.estimate import ALLOCATOR_SLACK

    peak = int(ALLOCATOR_SLACK * (signal + copies + work + book + codes)) + FIXED_BYTES
    return {"streamed": bool(streamed), "signal": signal, "copies": copies, "work": work, "bookkeeping": book,
            "codes": codes, "fixed": FIXED_BYTES, "peak": peak}
