"""prt_torch.transfer — the precomputation: per-vertex transfer vectors and matrices.

* ``base``: the ``Transfer`` container (save/load, ``signal()``) and the chunked, resumable
  runner ``run_chunks``.
* ``sampling``: stratified direction sets (uniform sphere, cosine-weighted hemisphere).
* ``diffuse``: unshadowed (analytic), shadowed (Monte Carlo) and interreflected diffuse
  transfer (Sloan 2002 / course notes 2005, "Diffuse PRT").
"""
from .base import KINDS, TRANSFER_VERSION, ChunkInterrupt, Transfer, default_state_dir, remove_state, run_chunks

__all__ = ["Transfer", "KINDS", "TRANSFER_VERSION", "run_chunks", "ChunkInterrupt", "default_state_dir", "remove_state"]

try:  # the diffuse precompute (this package's own module); optional so base stays importable alone
    from .diffuse import diffuse_radiance, precompute_diffuse, unshadowed_transfer  # noqa: F401

    __all__ += ["precompute_diffuse", "unshadowed_transfer", "diffuse_radiance"]
except ModuleNotFoundError as _e:  # pragma: no cover
    if _e.name != f"{__name__}.diffuse":
        raise

try:  # glossy / MRT / transport (issue 5); optional like diffuse
    from .glossy import precompute_glossy, precompute_mrt  # noqa: F401
    from .mrt import MRTBasis  # noqa: F401
    from .transport import TransportTable, precompute_transport  # noqa: F401

    __all__ += ["precompute_glossy", "precompute_mrt", "MRTBasis", "precompute_transport", "TransportTable"]
except ModuleNotFoundError as _e:  # pragma: no cover
    if _e.name not in (f"{__name__}.glossy", f"{__name__}.mrt", f"{__name__}.transport"):
        raise
