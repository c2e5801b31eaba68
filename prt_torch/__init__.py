"""prt_torch: precomputed radiance transfer (PRT) and its compression, in PyTorch.

Modules, in dependency order (a module imports only those before it):
io, sh, lighting, scene, brdf, transfer, codecs, relight, harness, render, cli.
See docs/ARCHITECTURE.md.
"""
__version__ = "0.1.0"
