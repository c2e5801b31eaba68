"""prt_torch.transfer — the precomputation: per-vertex transfer vectors and matrices.

* ``base``: the ``Transfer`` container (save/load, ``signal()``), :class:`RunOptions` (how a
  precompute runs) and the chunked, resumable runner ``run_chunks``.
* ``sampling``: stratified direction sets (uniform sphere, cosine-weighted hemisphere).
* ``diffuse``: unshadowed (analytic), shadowed (Monte Carlo) and interreflected diffuse
  transfer (Sloan 2002 / course notes 2005, "Diffuse PRT").
* ``glossy``: transferred radiance T_p and exit transfer M_p (Sloan 2003 §3.1), and the driver
  shared with ``mrt`` (matrix radiance transfer, Lehtinen & Kautz 2003) over the tent basis of
  ``tents``.
* ``transport``: tabulated direct transport functions on cube maps (Green 2005).
* ``registry``: every kind by name, with its precompute function and parameter constraints
  (:func:`get_kind`, :func:`kinds`) — what ``prt precompute``, configs and the harness use.
"""
from .base import (KINDS, TRANSFER_VERSION, ChunkInterrupt, RunOptions, Transfer, check_transfer_values, default_state_dir,
                   remove_state, run_chunks)
from .diffuse import precompute_diffuse, unshadowed_transfer
from .glossy import precompute_glossy
from .mrt import precompute_mrt
from .registry import TransferKind, get_kind, kinds
from .tents import MRTBasis
from .transport import TransportTable, precompute_transport

__all__ = [
    "Transfer", "KINDS", "TRANSFER_VERSION", "RunOptions", "run_chunks", "ChunkInterrupt", "default_state_dir",
    "remove_state", "check_transfer_values", "precompute_diffuse", "unshadowed_transfer", "precompute_glossy",
    "precompute_mrt", "MRTBasis", "precompute_transport", "TransportTable", "TransferKind", "get_kind", "kinds",
]
