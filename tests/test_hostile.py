"""Hostile input: unwritable outputs refused before any work, files written with the umask's
permissions, bad values refused by --dry-run exactly as by the real run."""
import os
import stat

import pytest
import torch
import yaml

from prt_torch import io
from prt_torch.cli import main as cli_main


def test_unwritable_output_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    import prt_torch.transfer.diffuse as d

    monkeypatch.setattr(d, "probe_self_occlusion", lambda *a, **k: pytest.fail("work started"))
    for bad in ("/proc/x.prt", str(tmp_path)):  # a path under /proc; a directory given as the output file
        assert cli_main(["precompute", "convex", "--samples", "8", "--no-progress", "-o", bad]) == 2
        err = capsys.readouterr().err
        assert bad in err and ("cannot be written" in err or "is a directory" in err), err
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        io.check_writable(tmp_path / "f" / "out.prt")


def test_files_get_the_umask_permissions(tmp_path):
    old = os.umask(0o027)
    try:
        p = io.save(tmp_path / "a.prt", {"x": torch.zeros(3)}, kind="test")
        io.atomic_write_json(tmp_path / "b.json", {"a": 1})
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(p).st_mode) == 0o640 == stat.S_IMODE(os.stat(tmp_path / "b.json").st_mode)


def test_save_to_an_impossible_place_is_a_clear_oserror(tmp_path):
    with pytest.raises(OSError, match="cannot write '/proc/"):
        io.save("/proc/nope/a.prt", {"x": torch.zeros(2)}, kind="test")


@pytest.mark.parametrize("override, match", [
    ("output_dir=/proc/reports", "output_dir"),
    ("cache_dir=/proc/cache", "cache_dir"),
    ("target.psnr=.nan", "target.psnr"),
    ("metrics.max_memory_gb=0.00001", "estimated"),
])
def test_dry_run_refuses_what_the_real_run_would(tmp_path, capsys, override, match):
    cfg = {"name": "h", "scene": {"name": "convex", "size": "small"}, "transfer": {"type": "diffuse", "bands": 3, "samples": 16},
           "lights": ["sky"], "codecs": [{"type": "pca", "vectors": 2}], "cache_dir": str(tmp_path / "c"),
           "output_dir": str(tmp_path / "r")}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    assert cli_main(["bench", str(p), override, "--dry-run"]) == 2
    assert match in capsys.readouterr().err
    assert not (tmp_path / "c").exists() and not (tmp_path / "r").exists()
    assert cli_main(["bench", str(tmp_path), "--dry-run"]) == 2  # a directory is not a config
    assert "is a directory" in capsys.readouterr().err


def test_inconsistent_files_are_refused_by_every_command(tmp_path, capsys):
    """Metadata that disagrees with the tensors (data shape, bands, row counts) is refused on
    load by one check, whichever command opens the file."""
    from prt_torch.scene import load_scene
    from prt_torch.transfer import Transfer, unshadowed_transfer

    mesh = load_scene("convex", size="small")
    tr = Transfer("diffuse", unshadowed_transfer(mesh.normals, 3).float(), mesh, {"bands": 3})
    good = tr.save(tmp_path / "t.prt")
    tensors, meta = io.load(good)
    for name, bad_meta in (("bands", {**meta, "bands": 4}), ("shape", {**meta, "data_shape": [5, 9]})):
        p = tmp_path / f"bad_{name}.prt"
        io.save(p, tensors, kind=meta["kind"], meta={k: v for k, v in bad_meta.items() if k not in ("format", "format_version", "kind")})
        for argv in (["info", str(p)], ["compress", str(p), "--codec", "pca", "--param", "vectors=2", "-o", str(tmp_path / "o.prt")],
                     ["render", str(p), "-o", str(tmp_path / "o.png")]):
            assert cli_main(argv) == 2, argv
            err = capsys.readouterr().err
            assert "inconsistent" in err and str(p) in err, (argv, err)
    assert cli_main(["info", str(tmp_path)]) == 2 and "is a directory" in capsys.readouterr().err


def test_ctrl_c_during_bench_is_quiet_and_says_how_to_continue(tmp_path, capsys, monkeypatch):
    from prt_torch.harness import run as hr

    cfg = {"name": "h", "scene": {"name": "convex", "size": "small"}, "transfer": {"type": "diffuse", "bands": 3, "samples": 16},
           "lights": ["sky"], "codecs": [{"type": "pca", "vectors": [1, 2]}], "render": {"enabled": False},
           "metrics": {"random_lights": 4, "repeats": 1, "warmup": 0},
           "cache_dir": str(tmp_path / "c"), "output_dir": str(tmp_path / "r")}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    real, calls = hr.evaluate_setting, []

    def interrupted(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(hr, "evaluate_setting", interrupted)
    assert cli_main(["bench", str(p), "--quiet"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "records" in err and "Traceback" not in err
    monkeypatch.setattr(hr, "evaluate_setting", real)
    assert cli_main(["bench", str(p), "--quiet"]) == 0
    assert "resumed: 1 finished setting" in capsys.readouterr().out


def test_lights_refuse_aliasing_and_negative_radiance():
    from prt_torch.lighting import load_light
    from prt_torch.lighting.environment import Environment

    env = Environment(torch.ones(8, 16, 3), "latlong")  # 128 pixels resolve l <= 4
    assert env.project(5).shape == (3, 25)
    with pytest.raises(ValueError, match="alias.*at most 5 bands"):
        env.project(6)
    with pytest.raises(ValueError, match="negative"):
        load_light("directional:direction=0,0,1;intensity=-1", bands=2)
    with pytest.raises(ValueError, match="negative"):
        load_light({"type": "cap", "direction": [0, 0, 1], "half_angle_deg": 10, "intensity": [1, -0.5, 1]}, bands=2)


def test_memory_refusal_rounds_honestly(tmp_path, capsys):
    cfg = {"name": "h", "scene": {"name": "convex", "size": "small"}, "transfer": {"type": "diffuse", "bands": 3, "samples": 16},
           "lights": ["sky"], "codecs": [{"type": "pca", "vectors": 2}], "cache_dir": str(tmp_path / "c"),
           "output_dir": str(tmp_path / "r"), "metrics": {"max_memory_gb": 0.00001}}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    assert cli_main(["bench", str(p), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "0.0 GiB" not in err and "KiB" in err and "MiB" in err, err


@pytest.mark.parametrize("argv, match", [
    (["--width", "0"], "--width '0'; accepted: an integer number of pixels"),
    (["--background", "nan"], "--background 'nan'; accepted: a finite number"),
])
def test_render_refuses_bad_numbers_by_name(tmp_path, capsys, argv, match):
    with pytest.raises(SystemExit) as e:
        cli_main(["render", str(tmp_path / "t.prt"), "-o", str(tmp_path / "o.png"), *argv])
    assert e.value.code == 2 and match in capsys.readouterr().err


def test_missing_light_file_is_refused_by_dry_run(tmp_path, capsys):
    assert cli_main(["bench", "default", "lights=[sky, nosuch.hdr]", f"output_dir={tmp_path}/r", f"cache_dir={tmp_path}/c",
                     "--dry-run"]) == 2
    assert "'lights.1' = 'nosuch.hdr'" in capsys.readouterr().err


@pytest.mark.parametrize("override", ["views=3", "metrics=[1]", "target=5", "render=true", "transfer.bands=[]",
                                      "codecs.0.clusters=[]", "codecs.0.type=[pca,vq]", "codecs=[3]", "transfer=3",
                                      "transfer.brdf=3", "lights=sky", "name=null"])
def test_malformed_config_structures_get_one_line(tmp_path, capsys, override):
    assert cli_main(["bench", "default", override, f"output_dir={tmp_path}/r", f"cache_dir={tmp_path}/c", "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("prt bench: error: config key") and err.count("\n") == 1, err
