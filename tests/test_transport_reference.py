"""The harness's reference for transport tables (issue 42 §2): the exact radiance at each vertex's own view
(``Evaluator.reference`` → ``Evaluator.exact_transport``: Green 2005 eq. 1.1–1.2 over the table's texels with
their stored visibility, the BRDF at the exact view), checked against values that share none of its code — the
closed form of a Lambertian plane shadowed by a sphere (``scene.sphere_on_plane_visibility``) and a dense
(θ, φ) quadrature of a glossy lobe on a convex mesh —, and the stored visibility against the rays traced again
for a table written before it was stored."""
from __future__ import annotations

import math
import pickle

import pytest
import torch

from prt_torch import brdf as B
from prt_torch import codecs, io
from prt_torch.harness.evaluate import Evaluator, TransportView, load_directory_transfer
from prt_torch.lighting import load_light
from prt_torch.scene import geodesic_sphere, load_scene, sphere_on_plane_visibility
from prt_torch.scene.mesh import make_mesh
from prt_torch.sh import eval_sh
from prt_torch.transfer import precompute_transport
from prt_torch.transfer.transport import TransportTable, texel_visibility


@pytest.fixture(scope="module")
def shadowed(tmp_path_factory):
    """sphere_on_plane (small, 2323 vertices): a Lambertian kd = 0.5 table, 12 views, 6×8×8, shadows traced."""
    out = tmp_path_factory.mktemp("sop") / "table"
    precompute_transport(load_scene("sphere_on_plane", size="small"), out, brdf=B.Lambertian(0.5), views=1, res=8)
    return out


def test_exact_reference_matches_the_closed_form_of_a_plane_shadowed_by_a_sphere(shadowed):
    """Under a constant radiance 1 a Lambertian ground point at distance d from the sphere's contact point
    exits kd (1 − (r²/(d² + r²))^{3/2}) at every view: the reference at a camera overhead matches it within
    the visibility's 6×8×8 resolution (rms 0.4% of kd here), where the cross-faded table (12 views) is
    no closer; the note says the visibility was stored."""
    ev = Evaluator(load_directory_transfer(shadowed))
    assert "stored" in ev.reference_info["visibility"]
    L = load_light("constant:value=1", bands=ev.bands_in)
    view = ev.view_weights(torch.tensor([0.3, -0.2, 40.0], dtype=torch.float64))
    assert isinstance(view, TransportView)
    ref = ev.reference(L, view)[:, 0].double()
    p = ev.points
    r = p[:, :2].norm(dim=-1)
    plane = (p[:, 2].abs() < 1e-9) & (r > 0.3) & (r < 2.5)  # ground vertices, off the contact point
    want = 0.5 * torch.tensor([sphere_on_plane_visibility(float(d)) for d in r[plane]], dtype=torch.float64)
    assert int(plane.sum()) > 500 and float(want.min()) < 0.3  # real occlusion (down to 60% shadowed)
    err = ref[plane] - want
    assert float(err.abs().max()) < 0.025 and float(err.pow(2).mean().sqrt()) < 0.006


def test_exact_reference_matches_a_dense_quadrature_of_a_glossy_lobe_on_a_convex_mesh(tmp_path):
    """Ashikhmin–Shirley N = 40 (a half-vector lobe: narrow at grazing views) on a convex icosphere under the
    'sky' SH light: at each of 12 vertices the reference equals ∫ f_r(ω_i, ω_o) cos θ_i L(ω_i) dω_i by a 128×256
    midpoint rule in the vertex's own (θ, φ) within 0.5% overall and 3% per vertex (views from 2° above the
    horizon to the normal) — where the table's three tapped views cross-faded are far off (12 stored views)."""
    v, f = geodesic_sphere(3)
    mesh = make_mesh(torch.from_numpy(v), torch.from_numpy(f), name="ico")
    brdf = B.AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)
    precompute_transport(mesh, tmp_path / "t", brdf=brdf, views=1, res=8, shadows=False)
    ev = Evaluator(load_directory_transfer(tmp_path / "t"))
    L = load_light("sky", bands=ev.bands_in).double()
    view = ev.view_weights(torch.tensor([4.0, 1.0, 0.5], dtype=torch.float64))
    ref = ev.reference(L, view).double()
    nt, nphi = 128, 256
    th = (torch.arange(nt, dtype=torch.float64) + 0.5) * (math.pi / 2 / nt)
    ph = (torch.arange(nphi, dtype=torch.float64) + 0.5) * (2 * math.pi / nphi)
    T, Ph = torch.meshgrid(th, ph, indexing="ij")
    local = torch.stack([T.sin() * Ph.cos(), T.sin() * Ph.sin(), T.cos()], -1).reshape(-1, 3)
    dw = (T.sin() * (math.pi / 2 / nt) * (2 * math.pi / nphi)).reshape(-1)
    wo = torch.einsum("vab,vb->va", ev.frames, view.directions)
    up = torch.nonzero(wo[:, 2] > 0).flatten()
    sel = up[torch.randperm(up.numel(), generator=torch.Generator().manual_seed(0))[:12]]
    quad = torch.stack([((brdf.eval(local, wo[i].expand_as(local)) * local[:, 2] * dw)[:, None]
                         * (eval_sh(local @ ev.frames[i], 10) @ L.T)).sum(0) for i in sel.tolist()])  # local -> world: Fᵀ
    assert float(wo[sel, 2].min()) < 0.1 and float(wo[sel, 2].max()) > 0.9
    got = ref[sel]
    assert float((got - quad).norm() / quad.norm()) < 0.005
    assert float(((got - quad).norm(dim=1) / quad.norm(dim=1)).max()) < 0.03
    unc = ev.uncompressed(L, view).double()[sel]
    assert float((unc - quad).norm() / quad.norm()) > 0.3
    assert bool((ev.reference(L, view)[wo[:, 2] <= 0] == 0).all())  # below the horizon: nothing


def test_a_table_without_stored_visibility_traces_the_same_bits(shadowed, tmp_path):
    """A table written before the visibility was stored (its chunk files rewritten without it): the reference
    traces the same rays (``texel_visibility``: the same bits as the stored ones, here with the straddling
    texels of a supersampled Ashikhmin–Shirley table), gives the same radiance and says it traced them; a
    table with only some chunks lacking it traces only those vertices."""
    import shutil

    mesh = load_scene("occluder_over_plane", size="small")
    out = tmp_path / "t"
    precompute_transport(mesh, out, views=1, res=8)  # default AS N = 40: texel averages, straddling texels
    table = TransportTable(out)
    assert int(table.meta["supersample"]["sub"]) > 1
    stored, have = table.visibility()
    assert bool(have.all()) and bool(stored.any()) and not bool(stored.all())
    traced = texel_visibility(mesh, 8, plan=table.meta["supersample"], offset=table.meta["fingerprint"]["offset"])
    assert torch.equal(traced, stored)
    ev = Evaluator(load_directory_transfer(out))
    L = load_light("sky", bands=ev.bands_in)
    view = ev.view_weights(torch.tensor([1.0, -3.0, 2.0], dtype=torch.float64))
    want = ev.reference(L, view)
    old = tmp_path / "old"
    shutil.copytree(out, old)
    n = int(table.meta["chunks"])
    assert n >= 2
    for c in range(n - 1):  # every chunk but the last as it was written before issue 42 §2
        t, m = io.load(old / f"chunk_{c:06d}.prt")
        io.save(old / f"chunk_{c:06d}.prt", {"data": t["data"]}, kind=m["kind"],
                meta={k: m[k] for k in ("chunk", "start", "stop")}, overwrite=True)
    ev_old = Evaluator(load_directory_transfer(old))
    k = int(table.meta["chunk_size"]) * (n - 1)
    assert ev_old.reference_info["visibility"].startswith(f"traced now for {k} of {ev.V} vertices")
    assert torch.equal(ev_old.reference(L, view), want)


def test_transport_view_is_the_taps_every_codec_takes_and_pickles(shadowed):
    """``view_weights`` gives the two tap tensors as a tuple (a codec unpacks it, checks and relights it as
    before) carrying the exact directions, kept through pickling (Ray tasks)."""
    ev = Evaluator(load_directory_transfer(shadowed))
    view = ev.view_weights(torch.tensor([0.0, -4.0, 2.0], dtype=torch.float64))
    idx, w = view
    back = pickle.loads(pickle.dumps(view))
    assert isinstance(back, TransportView) and torch.equal(back[0], idx) and torch.equal(back.directions, view.directions)
    c = codecs.get("pca", vectors=2)
    enc = c.fit_encode(ev.X, matrix_shape=ev.matrix_shape)
    L = ev.light_matrix(load_light("sky", bands=ev.bands_in))
    assert torch.equal(c.relight(enc, L, view=view), c.relight(enc, L, view=(idx, w)))


def test_a_chunk_whose_visibility_has_the_wrong_shape_is_named(shadowed, tmp_path):
    """A chunk file whose ``visibility`` is not uint8 [its vertices, ceil(P/8)] (another table's chunk copied in,
    a truncated write by another tool): one line naming the file, what it holds and what is accepted — not a
    shape error from the unpacking, nor bits read as another texel layout."""
    import shutil

    out = tmp_path / "t"
    shutil.copytree(shadowed, out)
    t, m = io.load(out / "chunk_000000.prt")
    k, nb = t["visibility"].shape
    for bad in (t["visibility"][:, :-1], t["visibility"][:-1], t["visibility"].to(torch.int16)):
        io.save(out / "chunk_000000.prt", {"data": t["data"], "visibility": bad}, kind=m["kind"],
                meta={key: m[key] for key in ("chunk", "start", "stop")}, overwrite=True)
        with pytest.raises(ValueError, match=rf"chunk_000000\.prt'?: visibility is .*; accepted: uint8 \[{k}, {nb}\]"):
            TransportTable(out).visibility()


def test_texel_visibility_refuses_bad_arguments():
    """Vertex indices outside the mesh, a non-bool ``shadows``, a bad ``res`` or ``offset``: one line naming it."""
    mesh = load_scene("sphere_on_plane", size="small")
    V = mesh.num_vertices
    with pytest.raises(ValueError, match=rf"vertices holds indices in \[0, {V}\]; accepted: vertex indices in \[0, {V}\)"):
        texel_visibility(mesh, 4, vertices=torch.tensor([0, V]))
    with pytest.raises(ValueError, match=r"vertices holds indices in \[-1, 0\]"):
        texel_visibility(mesh, 4, vertices=[-1, 0])
    with pytest.raises(ValueError, match=r"^shadows='yes'; accepted: True or False"):
        texel_visibility(mesh, 4, shadows="yes", vertices=[0])
    with pytest.raises(ValueError, match=r"^res=0"):
        texel_visibility(mesh, 0, vertices=[0])
    with pytest.raises(ValueError, match=r"^offset=-1.0 is out of range"):
        texel_visibility(mesh, 4, offset=-1.0, vertices=[0])


def test_exact_transport_refuses_directions_of_another_shape(shadowed):
    """One line naming ``directions``, its shape and the [V, 3] accepted (not an einsum error)."""
    ev = Evaluator(load_directory_transfer(shadowed))
    L = load_light("sky", bands=ev.bands_in)
    for bad in (torch.zeros(ev.V - 1, 3, dtype=torch.float64), torch.zeros(ev.V, 2, dtype=torch.float64)):
        with pytest.raises(ValueError, match=rf"^directions has shape .*; accepted: \[V, 3\] = \[{ev.V}, 3\]"):
            ev.exact_transport(L, bad)


def test_exact_reference_with_per_vertex_materials_is_each_vertex_albedo(tmp_path):
    """Per-vertex parameters (a Lambertian kd [V] from 0.1 to 0.9, the manifest's lists): under a constant radiance 1
    an unshadowed convex vertex exits its own kd at every view (∫ kd/π cos θ dω = kd), through the per-vertex BRDF
    rows of the compiled pass and of the torch one (``PRT_TORCH_NATIVE=0``) alike, within the 6×8×8 texels'
    horizon error — so no vertex reads another's material."""
    v, f = geodesic_sphere(8)
    mesh = make_mesh(torch.from_numpy(v), torch.from_numpy(f), name="ico")
    kd = torch.linspace(0.1, 0.9, mesh.num_vertices, dtype=torch.float64)
    kd = kd[torch.randperm(kd.numel(), generator=torch.Generator().manual_seed(4))]
    precompute_transport(mesh, tmp_path / "t", brdf=B.Lambertian(kd), views=1, res=8, shadows=False)
    L = load_light("constant:value=1", bands=4)
    for native in ("1", "0"):
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("PRT_TORCH_NATIVE", native)
            ev = Evaluator(load_directory_transfer(tmp_path / "t"))
            assert ev.reference_info["brdf"] == "per-vertex"
            view = ev.view_weights(torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64))
            up = torch.einsum("vab,vb->va", ev.frames, view.directions)[:, 2] > 0
            ref = ev.reference(L, view)[:, 0].double()
        assert int(up.sum()) > 100 and bool((ref[~up] == 0).all())
        rel = (ref[up] - kd[up]).abs() / kd[up]
        assert float(rel.max()) < 0.02, (native, float(rel.max()))
