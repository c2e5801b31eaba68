"""prt_torch.render — offscreen float rendering of per-vertex radiance (pyrender's EGL context,
Mesa llvmpipe without a GPU), GLSL decoder programs, and report images (heat maps, PNG/EXR,
side-by-side composites). See docs/render.md.

Importing this package sets ``PYOPENGL_PLATFORM=egl`` (unless already set) and loads no OpenGL;
the GL context is created on the first render.

Quick use::

    from prt_torch.render import render_radiance, Camera, error_heatmap, save_png
    img, mask = render_radiance(mesh, radiance)            # [H,W,3] float32, [H,W] bool
    cam = Camera.fit(mesh, azimuth=30, elevation=20, fov=35)
    with Renderer(320, 240) as r:                           # reuse for many renders
        ref, m = r.render_radiance(mesh, radiance_ref, cam)
        img, _ = r.render_radiance(mesh, radiance_codec, cam)
    heat = error_heatmap(img, ref, m, kind="rel", vmax=0.05)
"""
from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from .camera import Camera, bounding_sphere, look_at, orthographic, perspective  # noqa: E402
from .context import INSTALL_HINT, RenderUnavailable, gl_info  # noqa: E402
from .decoders import (  # noqa: E402
    Decoder,
    DrawInputs,
    IndexedRadianceDecoder,
    RadianceDecoder,
    TableData,
)
from .images import (  # noqa: E402
    auto_exposure,
    error_heatmap,
    error_map,
    save_exr,
    save_png,
    side_by_side,
    srgb_decode,
    srgb_encode,
    to_display,
    tonemap,
)
from .glsl import (  # noqa: E402
    AffineDecoder,
    CPCADecoder,
    MRTPCADecoder,
    NeuralDecoder,
    PCADecoder,
    TransferDecoder,
    VQDecoder,
    codec_decoder,
    codec_decoders,
    register_codec_decoder,
)
from .program import Attribute, FloatBuffer, FloatTexture, GLProgram, ShaderProgram  # noqa: E402
from .prt import GLSLCheck, PRTScene, check_codec_file, frame_rate, glsl_vs_cpu, psnr  # noqa: E402
from .renderer import Renderer, default_renderer, render, render_radiance  # noqa: E402

__all__ = [
    "Camera", "bounding_sphere", "look_at", "perspective", "orthographic",
    "RenderUnavailable", "INSTALL_HINT", "gl_info",
    "Renderer", "render", "render_radiance", "default_renderer",
    "Decoder", "DrawInputs", "TableData", "RadianceDecoder", "IndexedRadianceDecoder",
    "Attribute", "ShaderProgram", "GLProgram", "FloatTexture", "FloatBuffer",
    "error_map", "error_heatmap", "auto_exposure", "tonemap", "to_display", "srgb_encode", "srgb_decode",
    "save_png", "save_exr", "side_by_side",
    "TransferDecoder", "AffineDecoder", "VQDecoder", "PCADecoder", "CPCADecoder", "MRTPCADecoder", "NeuralDecoder",
    "register_codec_decoder", "codec_decoder", "codec_decoders",
    "PRTScene", "glsl_vs_cpu", "GLSLCheck", "check_codec_file", "psnr", "frame_rate",
]
