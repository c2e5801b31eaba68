"""One rule for naming a mesh wherever the CLI or a config takes one (``prt_torch.scene.check_scene``):
a built-in scene ``NAME`` or ``NAME:SIZE``, or an existing mesh file.

For each taker — ``prt precompute MESH_OR_BUILTIN``, ``prt render --mesh`` / ``--method shrm MESH``,
``prt invert --mesh``, ``prt validate --mesh``, a harness config's ``scene.name`` and
``convex.meshes`` — a built-in with a size is accepted and yields the mesh of the built-in's own
constructor (``scene.builtin(name, size)``: same vertex count, or same content hash), and a bad
size / bad name is refused, before any work, in one line naming the parameter, the value and the
accepted forms."""
from __future__ import annotations

import json

import pytest

from prt_torch import scene
from prt_torch.cli import main
from prt_torch.scene import builtin

BAD = [("convex:tiny", "size 'tiny' is not accepted for 'convex'"),
       ("cornell_box:xl", "size 'xl' is not accepted for 'cornell_box'"),
       ("cornell_box:500", "size '500' is not accepted for 'cornell_box'"),
       ("bumpy_sphere:5", "size '5' is not accepted for 'bumpy_sphere'"),
       ("nosuch:small", "is neither a built-in scene nor an existing mesh file"),
       ("nosuch.ply", "is neither a built-in scene nor an existing mesh file")]
ACCEPTED = ("accepted: a built-in scene NAME or NAME:SIZE (NAME one of convex, sphere_on_plane, occluder_over_plane, "
            "bumpy_sphere, cornell_box, scan_blob; SIZE one of small, medium, large, for convex and bumpy_sphere also xl "
            "or a vertex count in [12, 20000000]; default small), or an existing mesh file")


def _one_line(capsys, param, value, words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{param} {value!r}" in err[0] and words in err[0] and ACCEPTED in err[0], err


@pytest.fixture
def spy(monkeypatch):
    """Records each mesh the resolver builds (the commands import it at call time)."""
    seen = []
    real = scene.load_scene

    def load_scene(*a, **k):
        m = real(*a, **k)
        seen.append(m)
        return m
    monkeypatch.setattr(scene, "load_scene", load_scene)
    return seen


# ------------------------------------------------------------------------------------ precompute
def test_precompute_accepts_a_size_and_refuses_bad_names(tmp_path, capsys):
    assert main(["precompute", "convex:100", "-o", str(tmp_path / "t.prt"), "--dry-run"]) == 0
    assert f"convex: {builtin('convex', 100).num_vertices} vertices" in capsys.readouterr().err
    for value, words in BAD:
        assert main(["precompute", value, "-o", str(tmp_path / "t.prt"), "--dry-run"]) == 2
        _one_line(capsys, "MESH_OR_BUILTIN", value, words)


# ------------------------------------------------------------------------------------ render
def test_render_shrm_mesh_accepts_a_size(tmp_path, spy, monkeypatch):
    from prt_torch.render import shrm as R

    def stop(*a, **k):
        raise ValueError("stopped before rendering")
    monkeypatch.setattr(R, "render_shrm", stop)  # the mesh is resolved and built; no GL needed
    for argv in (["--mesh", "convex:100"], ["convex:100"]):
        assert main(["render", "--method", "shrm", "--brdf", "phong", "--map-size", "8", *argv,
                     "-o", str(tmp_path / "x.png")]) == 2
        assert spy[-1].num_vertices == builtin("convex", 100).num_vertices


@pytest.mark.parametrize("value,words", BAD)
def test_render_refuses_bad_mesh_names_before_any_work(tmp_path, capsys, spy, value, words):
    for argv, param in ((["--mesh", value], "--mesh"), ([value], "MESH")):
        assert main(["render", "--method", "shrm", "--brdf", "phong", *argv, "-o", str(tmp_path / "x.png")]) == 2
        _one_line(capsys, param, value, words)
    assert not spy and not (tmp_path / "x.png").exists()


# ------------------------------------------------------------------------------------ invert
def test_invert_mesh_accepts_a_size_and_refuses_bad_names(tmp_path, capsys, spy, monkeypatch):
    from prt_torch import inverse

    def stop(views):
        raise ValueError("stopped before the images")
    monkeypatch.setattr(inverse, "load_images", stop)  # after the mesh is built
    cams = tmp_path / "transforms.json"
    cams.write_text(json.dumps({"camera_angle_x": 0.8, "frames": [{"file_path": "v0.exr", "transform_matrix": [
        [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}))
    (tmp_path / "v0.exr").write_bytes(b"")  # never read: load_images stops first
    base = ["invert", "--cameras", str(cams), "--unknown", "light", "-o", str(tmp_path / "o.json")]
    assert main([*base, "--mesh", "bumpy_sphere:200"]) == 2
    assert "stopped before the images" in capsys.readouterr().err
    assert spy[-1].num_vertices == builtin("bumpy_sphere", 200).num_vertices
    spy.clear()
    for value, words in BAD:
        assert main([*base, "--mesh", value]) == 2
        _one_line(capsys, "--mesh", value, words)
    assert not spy


# ------------------------------------------------------------------------------------ validate
def test_validate_mesh_accepts_a_size_and_refuses_a_mismatch(tmp_path, capsys):
    import torch

    from prt_torch.brdf import Phong
    from prt_torch.transfer.glossy import precompute_glossy

    full = builtin("convex", 100)  # the built-in's own constructor
    out = tmp_path / "g.prt"
    precompute_glossy(full, 2, 2, brdf=Phong(s=4), samples=16, vertices=torch.arange(3), seed=0).save(out)
    args = ["validate", str(out), "--light", "constant", "--vertices", "3", "--spp", "16"]
    assert main([*args, "--mesh", "convex:100"]) == 0  # the same mesh: its content hash matches
    capsys.readouterr()
    assert main([*args, "--mesh", "convex:small"]) == 2  # a size the transfer was not computed on
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "vertex subset" in err[0] and "of convex:100" in err[0] and "'convex' size 'small'" in err[0] \
        and "pass --mesh the full mesh" in err[0], err
    for value, words in BAD:
        assert main([*args, "--mesh", value]) == 2
        _one_line(capsys, "--mesh", value, words)


# ------------------------------------------------------------------------------------ harness configs
def test_config_scene_name_accepts_a_size_and_refuses_bad_names(tmp_path):
    import yaml

    from prt_torch.harness import config as hc
    from prt_torch.harness.run import load_mesh_within_budget

    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump({"name": "t", "scene": {"name": "convex", "size": "small"},
                                 "transfer": {"type": "diffuse", "bands": 2, "samples": 16}, "codecs": [{"type": "pca", "vectors": 2}],
                                 "cache_dir": str(tmp_path / "c"), "output_dir": str(tmp_path / "r")}))
    cfg = hc.load_config(str(p), ["scene.name=bumpy_sphere:200"])
    assert load_mesh_within_budget(cfg)[0].num_vertices == builtin("bumpy_sphere", 200).num_vertices
    for value, words in BAD:
        with pytest.raises((ValueError, FileNotFoundError)) as e:
            hc.load_config(str(p), [f"scene.name={value}"])
        msg = str(e.value)
        assert "\n" not in msg and f"config key 'scene.name' = {value!r}" in msg and words in msg and ACCEPTED in msg
    assert not (tmp_path / "c").exists() and not (tmp_path / "r").exists()


def test_config_convex_meshes_take_the_same_rule():
    from prt_torch.harness.convex import _check_mesh_spec, load_convex_mesh

    _check_mesh_spec(0, "hull:convex:100")
    assert load_convex_mesh("bumpy_sphere:200").num_vertices == builtin("bumpy_sphere", 200).num_vertices
    for value, words in BAD:
        for spec in (value, "hull:" + value):
            with pytest.raises((ValueError, FileNotFoundError)) as e:
                _check_mesh_spec(3, spec)
            msg = str(e.value)
            assert f"config key 'convex.meshes.3' = {spec!r}: mesh {value!r}" in msg and words in msg and ACCEPTED in msg
