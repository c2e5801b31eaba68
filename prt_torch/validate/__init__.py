"""Independent ground truth: per-vertex exit radiance of a transfer against Mitsuba 3 path tracing
(docs/validate.md).

``validate(transfer, light)`` measures sampled vertices the way PRT defines them and compares,
with no scale fit. The package, one idea a module:

* here: :func:`validate`, the entry — every refusal before any work (transfer kind, light, BRDF,
  Mitsuba missing), the light as Mitsuba sees it, then the diffuse or the glossy comparison;
* :mod:`.lights`: the SH light on Mitsuba's lat-long grid, the check that Mitsuba can emit it,
  an environment's original image (``light_source='image'``);
* :mod:`.scenes`: the Mitsuba side — the scenes, the irradiance probes of diffuse transfer, the
  engine's BRDF as a Mitsuba BSDF and the radiance probes of glossy transfer;
* :mod:`.diffuse`: the engine side of diffuse transfer (direct and interreflected parts and
  their noise) and its comparison;
* :mod:`.glossy`: the engine side of glossy exit transfer (and its SH truncation bias) and its
  comparison;
* :mod:`.compare`: what both share — the sampled vertices, ratios of luminance sums with their
  noise, the report as text.

Mitsuba is an optional dependency (``pip install 'prt-torch[validate]'``); without it
:func:`require_mitsuba` raises :class:`ValidatorUnavailable` with that one line.
"""
from __future__ import annotations

import os
from typing import Any

import torch

from .._checks import check_choice, check_float, check_int
from ..lighting import load_light
from ..scene import Mesh
from ..transfer import Transfer
from .compare import format_report, sample_vertices
from .diffuse import engine_parts, sharp_vertices, validate_diffuse, validate_wavelet
from .glossy import engine_glossy, glossy_brdf, validate_glossy
from .lights import check_expressible, light_image, mitsuba_envmap_directions, source_image
from .lights import source_image as _source_image  # noqa: F401 (the name tests/test_validate.py uses)
from .scenes import (BSDF_PLUGIN, INSTALL_HINT, MITSUBA_DIAGONAL, MITSUBA_FRAMES, VARIANT, ValidatorUnavailable,  # noqa: F401 (VARIANT)
                     engine_bsdf, mitsuba_exit_radiance, mitsuba_frame, mitsuba_glossy_exit, require_mitsuba)

__all__ = [
    "ValidatorUnavailable",
    "INSTALL_HINT",
    "require_mitsuba",
    "mitsuba_envmap_directions",
    "light_image",
    "check_expressible",
    "sample_vertices",
    "sharp_vertices",
    "mitsuba_exit_radiance",
    "mitsuba_frame",
    "MITSUBA_DIAGONAL",
    "MITSUBA_FRAMES",
    "engine_parts",
    "validate",
    "validate_diffuse",
    "validate_wavelet",
    "format_report",
    "BSDF_PLUGIN",
    "engine_bsdf",
    "glossy_brdf",
    "engine_glossy",
    "mitsuba_glossy_exit",
    "validate_glossy",
]


def validate(transfer: Transfer | str | os.PathLike, light: Any, *, vertices: int = 32, spp: int = 1024, batches: int = 8,
             seed: int = 0, codec_file: str | os.PathLike | None = None, light_source: str = "sh", light_name: str | None = None,
             sharp_deg: float = 18.0, image_height: int = 128, idx: torch.Tensor | None = None, mesh: Mesh | None = None,
             view_deg: float = 60.0, mitsuba_frame: str = "normalized") -> dict[str, Any]:
    """Engine vs Mitsuba 3 at ``vertices`` sampled vertices (docs/validate.md); no scale fit.

    Args:
        transfer: a diffuse, glossy (exit) or wavelet :class:`Transfer` or its file; glossy goes
            to :func:`validate_glossy` (``mesh``: the full mesh of a vertex-subset transfer;
            ``view_deg``: the views' largest angle from the normal); wavelet to
            :func:`validate_wavelet` (``light_source='image'`` only: the kind is not band-limited).
        light: anything :func:`prt_torch.lighting.load_light` takes, or an SH tensor ``[C, n²]``.
        spp, batches: Mitsuba samples per vertex and depth, split into independent batches (noise).
        codec_file: also compare a codec's reconstruction of this transfer (total and
            interreflected against the engine's direct part).
        light_source: 'sh' (Mitsuba sees the band-limited light: exact comparison) or 'image'
            (Mitsuba sees the original environment; the report adds the SH-truncation effect).
        sharp_deg: vertices whose adjacent faces tilt at least this far from the vertex normal
            are reported separately.
        image_height: rows of Mitsuba's lat-long image of the SH light; an environment image
            (``light_source='image'``, wavelet) gets at least this and twice the environment's
            own (:func:`lights.source_height`), remapped with its power (:func:`lights.remap_to_mitsuba`).
        mitsuba_frame: 'normalized' (default: Mitsuba sees the mesh centred and scaled to a
            diagonal of :data:`MITSUBA_DIAGONAL`, so that its absolute ray epsilons are negligible
            against the engine's, whatever the mesh's units; :func:`mitsuba_frame`) or 'as_is'
            (the mesh's own units: Mitsuba then sees through surfaces within ~1e-4 units of a
            probe, which on a small mesh is several engine offsets — issue 37).
    Returns:
        a JSON-able dict: ``direct``/``inter``/``total`` ratios (engine/Mitsuba of summed
        luminance, with 1σ noise and z), the same over the sharp vertices, per-vertex arrays,
        the settings.
    Raises:
        ValueError: a transfer kind, light or BRDF the validator cannot express (before any work).
        ValidatorUnavailable: Mitsuba 3 is not installed.
    """
    if not isinstance(transfer, Transfer):
        transfer = Transfer.load(transfer)
    if transfer.kind == "wavelet":  # not band-limited: Mitsuba sees the original image
        name = light_name or str(light)
        if light_source != "image" or codec_file is not None:
            raise ValueError("a wavelet transfer is validated under the environment's original image; accepted: "
                             "light_source='image' (CLI --light-source image) and no codec file")
        vertices = check_int("vertices", vertices, 1)
        batches = check_int("batches", batches, 2, 4096)
        spp = check_int("spp", spp, batches, 1 << 24)
        seed = check_int("seed", seed, 0, 2**63 - 1)
        src_img = None if isinstance(light, torch.Tensor) else source_image(light, image_height)
        if src_img is None:
            raise ValueError(f"light {name!r}: no environment image behind it; accepted for a wavelet transfer: an "
                             "environment file or a built-in environment name")
        require_mitsuba()
        return validate_wavelet(transfer, light, name, src_img, vertices=vertices, spp=spp, batches=batches, seed=seed, idx=idx)
    if transfer.kind not in ("diffuse", "glossy"):
        raise ValueError(f"transfer kind {transfer.kind!r}: the validator expresses diffuse, glossy exit and wavelet transfer; "
                         "accepted: prt precompute --kind diffuse, glossy or wavelet")
    if transfer.kind == "glossy":
        glossy_brdf(transfer)  # a BRDF, quantity or bounces it cannot express: refused before any work
        if codec_file is not None:
            raise ValueError("codec_file with a glossy transfer: codec comparison is for diffuse transfer; accepted: no codec_file")
    codec = None
    if codec_file is not None:
        from .. import codecs, io
        from ..codecs.base import check_codec_matches

        codec = codecs.load(codec_file)  # the codec file's own checks (codecs.check_codec_values)
        d = transfer.data  # diffuse: [V, n²] grey vectors or [V, 3, n²] RGB matrices
        check_codec_matches(f"codec file {str(codec_file)!r}", *codec, io.load_meta(codec_file),
                            mesh_hash=transfer.mesh.content_hash() if transfer.mesh is not None else None,
                            points=int(d.shape[0]), dim=int(d[0].numel()),
                            matrix_shape=tuple(int(x) for x in d.shape[1:]) if d.ndim == 3 else None,
                            n_in=int(d.shape[-1]), kind=transfer.kind)
    check_choice("light_source", light_source, ["sh", "image"])
    vertices = check_int("vertices", vertices, 1)
    batches = check_int("batches", batches, 1, 4096)
    spp = check_int("spp", spp, batches, 1 << 24)  # every batch renders at least one sample
    seed = check_int("seed", seed, 0, 2**63 - 1)
    check_float("view_deg", view_deg, 0.0, 90.0, lo_open=True)
    check_float("sharp_deg", sharp_deg, 0.0, 180.0)
    check_choice("mitsuba_frame", mitsuba_frame, list(MITSUBA_FRAMES))
    bands = int(transfer.meta["bands"])
    name = light_name or (str(light) if not isinstance(light, torch.Tensor) else "SH tensor")
    L = light if isinstance(light, torch.Tensor) else load_light(light, bands)
    L = torch.as_tensor(L, dtype=torch.float64)
    L = L[None] if L.ndim == 1 else L
    if not bool(torch.isfinite(L).all()):
        raise ValueError(f"light {name!r} has non-finite SH coefficients; accepted: a light with finite values")
    if L.shape[1] != bands * bands:
        raise ValueError(f"light {name!r} has {L.shape[1]} SH coefficients; accepted: {bands * bands} (the transfer's {bands} bands)")
    src_img = None
    if light_source == "sh":
        sh_img = check_expressible(L, name, image_height)
    else:
        try:  # the band-limited light too, when Mitsuba can emit it: the SH truncation figure
            sh_img = check_expressible(L, name, image_height)
        except ValueError:
            sh_img = None
        if isinstance(light, torch.Tensor) or (src_img := source_image(light, image_height)) is None:
            raise ValueError(f"light_source='image' with light {name!r}: no environment image behind it; accepted: an "
                             "environment file or a built-in environment name, or light_source='sh'")
    require_mitsuba()
    if transfer.kind == "glossy":
        rep = validate_glossy(transfer, L, name, sh_img if src_img is None else src_img, mesh=mesh, vertices=vertices, spp=spp,
                              batches=batches, seed=seed, view_deg=view_deg, idx=idx, mitsuba_frame=mitsuba_frame)
        rep["light_source"] = light_source
        return rep
    return validate_diffuse(transfer, L, name, sh_img, src_img, light_source=light_source, codec=codec, codec_file=codec_file,
                            vertices=vertices, spp=spp, batches=batches, seed=seed, sharp_deg=sharp_deg, idx=idx,
                            mitsuba_frame=mitsuba_frame)
