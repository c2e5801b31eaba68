"""Relighting a Gaussian encoding (Green 2005 §2.3, eq. 2.7): each lobe is one lookup
w_k E_{σ_k}(μ_k) into a :class:`~prt_torch.lighting.prefilter.PrefilteredEnvironment`, fused over
the lobes by the compiled kernels (``relight_kernels.sg_*``; torch otherwise), and the prepared
form of ``GaussianCodec.relighter``: every lobe's pyramid addressing (or, with view taps, the
lobes blended across the taps and their addressing) kept while the lobes, taps and the light's
pyramid stay the same. The codec's ``relight`` (in the package) checks its arguments and calls
these.
"""
from __future__ import annotations

from typing import Any

import torch

from ..._checks import tensor_state
from ...lighting.prefilter import PrefilteredEnvironment
from ..base import Codec, Encoded, Relighter, grad_required
from ..relight_kernels import native, sg_lookup_prepared, sg_lookup_sum, sg_quads_worth, sg_taps_prepared, sg_taps_prepared_call

__all__ = ["lobe_sum", "fused", "lobes_state", "GaussianRelighter"]


def lobe_sum(light: PrefilteredEnvironment, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
             out: torch.Tensor | None = None, layout: tuple | None = None, prepared: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over the lobes (last axis of ``w [..., N]``) of w · E_σ(μ) — Green 2005 eq. 2.7 with
    ``mu [..., N, 3]``, ``sigma [..., N]`` → ``[..., C]`` float32: one fused pass per lobe
    (``relight_kernels.sg_lookup_sum``) where the kernels are compiled, else
    ``light.lookup`` and a sum (the same values to float32 rounding; tests compare them).
    ``out``: an optional contiguous float32 result of that shape, written and returned;
    ``layout``: ``relight_kernels.lobe_layout(w, mu, sigma)`` where the caller keeps it;
    ``prepared``: ``relight_kernels.sg_prepare``'s addressing of these lobes for this light's
    resolution and width ladder (``GaussianRelighter``), the same bits read faster. Levels that
    require grad: the torch lookup in their dtype, differentiable (``fused``)."""
    lib = fused(light)
    if lib is not None:
        table = light.table()
        quads = light.quads() if sg_quads_worth(table.shape[0], light.channels, light.res, w.numel()) else None
        if prepared is not None:
            return sg_lookup_prepared(lib, prepared, table, light.log_sigmas, light.res, w, mu, sigma, out=out, layout=layout,
                                      quads=quads)
        return sg_lookup_sum(lib, table, light.log_sigmas, light.res, mu, sigma, w, out=out, layout=layout, quads=quads)
    res = (w[..., None] * light.lookup(mu, sigma)).sum(-2)
    return res if out is None else out.copy_(res)


def fused(light: PrefilteredEnvironment):
    """The compiled kernels when they take this light (≤ 16 channels) and no gradient is required
    of its levels, else None: the torch path (``PrefilteredEnvironment.lookup``), which under
    autograd computes in the levels' dtype and is differentiable with respect to them (the
    kernels are forward-only; docs/inverse.md "Differentiable relighting")."""
    lib = native()
    return lib if lib is not None and light.channels <= 16 and not grad_required(light.levels) else None


def lobes_state(enc: Encoded) -> tuple:
    """What a cache derived from a Gaussian encoding's lobes compares: its point count, its tensors'
    names (the layout: view-major ``lobes_by_view`` or vertex-major ``lobes``) and each one's
    ``_checks.tensor_state`` (address, shape and strides too: ``t.data = t[..., :1]`` keeps the
    address and the version; ``base.encoding_state`` keys only identity, address and version)."""
    return (enc.meta.get("points"), tuple(enc.tensors), *(tensor_state(t) for t in enc.tensors.values()))


class GaussianRelighter(Relighter):
    """``GaussianCodec.relighter``: relighting from the lobes' prepared addressing
    (``relight_kernels.sg_prepare``; with taps ``sg_taps_prepare``, of the lobes blended across
    the taps), kept with the state it was computed from — the light's resolution and width
    ladder, the lobe tensors' names and states (``lobes_state``) and the
    taps' (``_checks.tensor_state``): an edit of the lobes or taps, a replaced tensor or a light
    of another pyramid computes it again. Lights of other channel counts than 3, or no compiled
    kernels, relight as ``relight`` does. Edits that bypass torch's version counter (through
    numpy) are not seen.

    With taps, a call takes a fast path when the last call took the prepared path and nothing it
    checked has changed since: the same light object with the same fields at the same states
    (``_checks.tensor_state``: what ``PrefilteredEnvironment.check`` memoises), the same ``out``
    at the same address and layout, the same taps and lobes at the same states, the codec not
    refitted (its views at the same state), the kernels not switched off (``PRT_TORCH_NATIVE``),
    and no SH diffuse part. Then only the prepared kernel runs (relight's checks cost
    about 25 µs a call: a tenth of a one-lobe relight of 50 000 vertices at 2 threads)."""

    __slots__ = ("_prep", "_taps", "_hot")

    def __init__(self, codec: Codec, enc: Encoded, view: Any, kwargs: dict):
        super().__init__(codec, enc, view, kwargs)
        self._prep: tuple | None = None  # GaussianCodec._prepare's entry: (key, prepared, held tensors, made)
        self._taps: tuple | None = None  # a view of directions: (key, its taps, the directions, the codec's views)
        self._hot: tuple | None = None  # taps: (light, out, _hot_key, lib, prepared, table, held, the kernel's arguments)

    def _hot_key(self, light: PrefilteredEnvironment, out: torch.Tensor | None) -> list | None:
        """What the fast path compares: the states of the light's fields, ``out``'s, the view's
        and the encoding's tensors, the light's sizes and the codec's views (the tensors are held
        with the key in ``_hot``, so that no id is reused); None where the view is not tensors."""
        view = self.view
        vt = view if isinstance(view, tuple) else (view,)
        if not all(isinstance(t, torch.Tensor) for t in vt):
            return None
        key = [light.res, light.channels, self.codec.J_, lobes_state(self.enc)]
        for t in (self.codec.views_, light.levels, light.sigmas, light.log_sigmas, light.cube, light.sh, out, *vt):
            key.append(tensor_state(t) if isinstance(t, torch.Tensor) else id(t))  # (a reassigned non-tensor: checked on the full path)
        return key

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> torch.Tensor:
        hot = self._hot
        if (hot is not None and light is hot[0] and out is hot[1] and native() is hot[3]
                and self._hot_key(light, out) == hot[2]):
            if out is not None:  # the kernel's arguments as the full call checked them (all unchanged since)
                if not hot[3].prt_sg_taps_prepared(*hot[7], torch.get_num_threads()):
                    return out
            else:
                res, flag = sg_taps_prepared(hot[3], hot[4], hot[5], light.log_sigmas, light.res)
                if not flag:
                    return res
        self._hot = None  # a full call (which raises for a bad tap), then the fast path again where it can
        res = self._full(light, out)
        prep = self._prep
        if (self.view is not None and isinstance(light, PrefilteredEnvironment) and prep is not None and prep[1] is not None
                and "diffuse" not in self.enc.tensors and fused(light) is not None and light.channels == 3):
            held = (self.codec.views_, light.levels, light.sigmas, light.log_sigmas, light.cube, light.sh, out, prep[2])
            key = self._hot_key(light, out)
            if key is not None:
                table = light.table()
                call = None if out is None else sg_taps_prepared_call(prep[1], table, light.log_sigmas, light.res, out)[1]
                self._hot = (light, out, key, fused(light), prep[1], table, held, call)
        return res

    def _full(self, light: Any, out: torch.Tensor | None) -> torch.Tensor:
        view = self.view
        if isinstance(view, torch.Tensor):  # global directions [V, 3]: their three nearest views' taps, kept
            hit, key = self._taps, (tensor_state(view), tensor_state(self.codec.views_))  # (a refit replaces the views)
            if hit is None or hit[0] != key:
                V, J, _ = self.codec.lobes_of(self.enc)[0].shape
                hit = self._taps = (key, self.codec.checked_taps(view, V, J, values=False), view, self.codec.views_)
            view = hit[1]
        return self.codec._relight_checked(self.enc, light, view, out, prepare=self._prepared)

    def _prepared(self, light: PrefilteredEnvironment, lobes: tuple, taps: tuple | None) -> tuple | torch.Tensor | None:
        prep, self._prep = self.codec._prepare(self.enc, light, lobes, taps, self._prep, eager=True)
        return prep
