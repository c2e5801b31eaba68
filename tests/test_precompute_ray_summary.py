"""``prt precompute``'s summary counts every ray (issue 42 §1): the vertices' own, the bounce hit
points' (intersect and occluded) and the probes (the hits' per-face probe of estimator 'auto',
the self-occlusion probe of ``--shadows auto``).

The reference counts are closed forms, independent of the code's bookkeeping: inside a closed,
inward-facing sphere every ray a vertex traces meets the front of a face, so with one bounce each
of the V·⌈N/2⌉ qmc vertex rays (diffuse) makes one hit that traces ``hit_samples`` rays (4 under the default estimator), and the
face probe traces ``FIRST_PROBE_RAYS`` rays per face its first hits land on (issue 42 §2: the sphere is curved,
no face has 8 coplanar neighbours, so none may be guided and each probes the thinned set): every face at N = 256
(46 336 hits on 720 faces), none on a lone plane (no ray of it meets the scene).
"""
from __future__ import annotations

import re

import pytest

from prt_torch.cli import main as cli_main
from prt_torch.cli.precompute import ray_counts
from prt_torch.scene import geodesic_sphere
from prt_torch.transfer.diffuse import FIRST_PROBE_RAYS, HIT_SAMPLES_AUTO


@pytest.fixture(scope="module")
def enclosure(tmp_path_factory):
    """An OBJ of a radius-3 sphere facing inwards (362 vertices, 720 faces): every ray from inside is blocked."""
    v, f = geodesic_sphere(6)
    f = f[:, ::-1]
    path = tmp_path_factory.mktemp("enc") / "enclosure.obj"
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in 3.0 * v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")
    return path, v.shape[0], f.shape[0]


def _summary(err: str) -> dict[str, int]:
    line = next(x for x in err.splitlines() if "wrote" in x)
    m = re.search(r"(\d+) rays: (\d+) from vertices, (\d+) from hit points, (\d+) probe in", line)
    assert m, line
    return dict(zip(("total", "vertex", "hit", "probe"), map(int, m.groups())))


def test_diffuse_summary_counts_vertex_hit_and_probe_rays(enclosure, tmp_path, capsys):
    path, V, F = enclosure
    N, M = 256, HIT_SAMPLES_AUTO["auto"]  # the default estimator's rays per hit
    out = tmp_path / "d.prt"
    assert cli_main(["precompute", str(path), "--kind", "diffuse", "--bands", "2", "--samples", str(N), "--bounces", "1",
                     "--shadows", "always", "--no-progress", "-o", str(out)]) == 0
    c = _summary(capsys.readouterr().err)
    assert c["vertex"] == V * (N // 2)  # qmc: ⌈N/2⌉ rays per vertex
    assert c["hit"] == M * c["vertex"]  # every vertex ray hits the inside; each hit traces M rays (one bounce: depth 1)
    assert c["probe"] == FIRST_PROBE_RAYS * F  # estimator 'auto': the hits' per-face probe, every face hit at this N
    assert c["total"] == c["vertex"] + c["hit"] + c["probe"]
    assert cli_main(["precompute", str(path), "--kind", "diffuse", "--bands", "2", "--samples", str(N), "--bounces", "1",
                     "--shadows", "always", "--no-progress", "--estimator", "plain", "--hit-samples", "3", "-o",
                     str(tmp_path / "p.prt")]) == 0
    c = _summary(capsys.readouterr().err)
    assert c["hit"] == 3 * c["vertex"] and c["probe"] == 0  # 'plain': no face probe; --hit-samples as given


def test_glossy_summary_counts_hit_and_probe_rays(enclosure, tmp_path, capsys):
    path, V, F = enclosure
    out = tmp_path / "g.prt"
    assert cli_main(["precompute", str(path), "--kind", "glossy", "--bands", "2", "--bands-out", "2", "--samples", "256",
                     "--bounces", "1", "--shadows", "always", "--no-progress", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    c = _summary(err)
    assert "bounces used 1;" in err  # glossy/MRT record 'bounces' (no stopping rule)
    assert 0 < c["vertex"] < V * 256  # the shared sphere set's directions above each tangent plane
    assert c["hit"] == HIT_SAMPLES_AUTO["auto"] * c["vertex"] and c["probe"] == FIRST_PROBE_RAYS * F
    assert c["total"] == c["vertex"] + c["hit"] + c["probe"]


@pytest.mark.parametrize("kind", ["diffuse", "glossy"])
def test_no_probe_where_no_hit_lands(tmp_path, capsys, kind):
    """A lone plane: no vertex ray meets the scene, so no first hit and no face probed (the probe
    of every face traced 32 rays per face here before issue 42 §2)."""
    g = [(x, y) for y in range(5) for x in range(5)]
    faces = [(a, a + 1, a + 6) for a in (y * 5 + x for y in range(4) for x in range(4))] + \
        [(a, a + 6, a + 5) for a in (y * 5 + x for y in range(4) for x in range(4))]
    path = tmp_path / "plane.obj"
    path.write_text("".join(f"v {x} {y} 0\n" for x, y in g) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    assert cli_main(["precompute", str(path), "--kind", kind, "--bands", "2", "--samples", "64", "--bounces", "1",
                     "--shadows", "always", "--no-progress", "-o", str(tmp_path / "o.prt")]) == 0
    line = next(x for x in capsys.readouterr().err.splitlines() if "wrote" in x)
    assert re.search(r"; \d+ rays in ", line) and " probe in " not in line, line  # the vertices' rays alone: no hit, no probe


def test_shadows_auto_probe_is_counted():
    """The self-occlusion probe's rays (``meta['probe']['rays']``) join the probe count; a run with
    nothing but vertex rays prints the plain count."""
    m = {"rays_traced": 100, "hit_rays_traced": 40, "hit_choice_rays": 7, "probe": {"rays": 3}}
    assert ray_counts(m) == {"vertex": 100, "hit": 40, "probe": 10, "total": 150}
    from prt_torch.cli.precompute import ray_summary

    assert ray_summary({"rays_traced": 5}) == "5 rays"
    assert ray_summary({}) == "0 rays"
    assert ray_counts({"probe": None})["total"] == 0
