"""Compression of PRT signals behind one interface: VQ, PCA, clustered PCA (static, iterative,
adaptive; Sloan 2003 §3.3–4) and MRT-PCA (Lehtinen & Kautz 2003 §6). Every codec is a
scikit-learn estimator (``get_params``/``set_params``/``clone``, ``fit`` returns self, ``score``).

    >>> from prt_torch import codecs
    >>> codec = codecs.get("cpca", clusters=64, vectors=8)          # validated, no work yet
    >>> enc = codec.fit_encode(X, matrix_shape=(n_out, n_in))         # X [P, D] float32
    >>> out = codec.relight(enc, light, view=y_local)                 # straight from the codes
    >>> r = codec.relighter(enc, view=y_local); r(light, out=out)     # a render loop: checks done once
    >>> codec.storage(enc)["compression_ratio"]
    >>> codec.save("out.prt", enc); codec2, enc2 = codecs.load("out.prt")

Names: ``codecs.available()``; parameters of one: ``codecs.describe(name)``. File layout and
use from other pipelines (numpy arrays in, numpy arrays out; ``transform``/``inverse_transform``
in a scikit-learn ``Pipeline``; GridSearchCV): docs/codecs.md.
"""
from .base import (CODEC_FORMAT_VERSION, Codec, ConvergenceError, ConvergenceWarning, Encoded, available,
                   describe, get, load, register)
from .affine import AffineCodec, label_dtype
from .cpca import CPCA, MRTPCA, PCA, VQ, CPCAAdaptive, CPCAIterative, CPCAStatic
from .gaussian import GaussianCodec
from .neural import NeuralCodec

__all__ = [
    "Codec", "Encoded", "AffineCodec", "VQ", "PCA", "CPCA", "CPCAStatic", "CPCAIterative", "CPCAAdaptive", "MRTPCA", "GaussianCodec", "NeuralCodec",
    "register", "get", "available", "describe", "load", "label_dtype",
    "ConvergenceWarning", "ConvergenceError", "CODEC_FORMAT_VERSION",
]
