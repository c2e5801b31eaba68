"""Hostile input, second pass (issue 36): every shipped config passes its own dry run, options
may come between the config and its overrides, a warning on the command line is one line, and a
long run ends cleanly on SIGINT (to the process group, as Ctrl-C sends it), SIGTERM (what
``timeout``, schedulers and ``kill`` send) and SIGKILL, of the main process or of a ray-casting
worker: the exit status, one line naming what happened and how to continue, no traceback, no
output file half-written, no worker left behind."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from prt_torch.cli import main as cli_main
from prt_torch.harness.config import builtin_configs

PRT = [sys.executable, "-m", "prt_torch"]


@pytest.mark.parametrize("name", builtin_configs())
def test_every_shipped_config_passes_its_own_dry_run(name, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["bench", name, "--dry-run", "--no-time"]) == 0, capsys.readouterr().err  # time: test_stream_outputs
    out = capsys.readouterr().out
    assert "codec settings" in out
    assert not (tmp_path / "reports").exists() and not (tmp_path / "cache").exists()  # a dry run writes nothing


def test_options_may_come_between_the_config_and_its_overrides(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["bench", "default", "--dry-run", "metrics.repeats=3", "seed=7"]) == 0
    out = capsys.readouterr().out
    assert '"repeats": 3' in out and '"seed": 7' in out
    with pytest.raises(SystemExit):  # an unknown option is still refused, naming it
        cli_main(["bench", "default", "--dry-run", "--no-such-option"])
    assert "--no-such-option" in capsys.readouterr().err


def test_a_warning_on_the_command_line_is_one_line(tmp_path, capsys):
    src = tmp_path / "t.prt"
    assert cli_main(["precompute", "convex", "--samples", "16", "--bands", "3", "--no-progress", "-o", str(src)]) == 0
    capsys.readouterr()
    # a k-means stopped after one iteration warns that it did not converge
    assert cli_main(["compress", str(src), "--codec", "vq", "--clusters", "16", "--param", "max_iter=1", "-o",
                     str(tmp_path / "t.vq.prt")]) == 0
    err = capsys.readouterr().err
    warns = [ln for ln in err.splitlines() if "warning" in ln.lower()]
    assert warns, err
    for ln in warns:
        assert ln.startswith("prt compress: warning: "), ln
    assert "Warning:" not in err and ".py:" not in err, err  # not Python's file:line: Category: format, nor its source line


def _precompute(tmp_path: Path) -> subprocess.Popen:
    """A precompute long enough to be signalled mid-run (two ray-casting processes), SIGINT not
    ignored (a background job of a non-interactive shell would inherit it ignored)."""
    return subprocess.Popen([*PRT, "precompute", "bumpy_sphere", "--size", "medium", "--samples", "4096", "--bounces", "1",
                             "--workers", "2", "--chunk", "128", "--no-progress", "-o", str(tmp_path / "t.prt")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for_a_chunk(p: subprocess.Popen, tmp_path: Path) -> None:
    t0 = time.monotonic()
    while not list((tmp_path / "t.prt.state").glob("chunk_*.prt")):
        assert p.poll() is None, p.communicate()[1]
        assert time.monotonic() - t0 < 120, "no chunk finished in 120 s"
        time.sleep(0.1)


def _workers_of(pid: int) -> list[int]:
    out = subprocess.run(["pgrep", "-P", str(pid), "-f", "_embree_worker"], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


@pytest.mark.skipif(sys.platform != "linux" or not Path("/usr/bin/pgrep").exists(), reason="POSIX signals and pgrep")
@pytest.mark.parametrize("sig, to, status, says", [
    ("SIGINT", "group", 130, "interrupted"),
    ("SIGTERM", "main", 143, "terminated (SIGTERM)"),
    ("SIGKILL", "worker", 2, "ended by SIGKILL"),
    ("SIGTERM", "worker", 2, "ended by SIGTERM"),
])
def test_a_signalled_precompute_ends_cleanly_with_a_resume_hint(sig, to, status, says, tmp_path):
    p = _precompute(tmp_path)
    try:
        _wait_for_a_chunk(p, tmp_path)
        workers = _workers_of(p.pid)
        assert workers, "the run was meant to use a ray-casting worker"
        s = getattr(signal, sig)
        if to == "group":
            os.killpg(p.pid, s)
        elif to == "main":
            p.send_signal(s)
        else:
            os.kill(workers[0], s)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == status, err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("prt precompute: ") and says in last and "--resume" in last, err
    assert not (tmp_path / "t.prt").exists()  # nothing half-written
    assert list((tmp_path / "t.prt.state").glob("chunk_*.prt"))  # the finished chunks kept
    time.sleep(0.5)
    assert not [w for w in workers if Path(f"/proc/{w}").exists() and "zombie" not in Path(f"/proc/{w}/status").read_text()]


@pytest.mark.skipif(sys.platform != "linux" or not Path("/usr/bin/pgrep").exists(), reason="POSIX signals and pgrep")
def test_a_killed_main_process_leaves_no_worker_and_no_output(tmp_path):
    p = _precompute(tmp_path)
    try:
        _wait_for_a_chunk(p, tmp_path)
        workers = _workers_of(p.pid)
        assert workers
        p.send_signal(signal.SIGKILL)
        p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    t0 = time.monotonic()
    while [w for w in workers if Path(f"/proc/{w}").exists()] and time.monotonic() - t0 < 10:
        time.sleep(0.1)  # the workers read EOF on their pipe and return (reparented: nobody reaps them as zombies)
    assert not [w for w in workers if Path(f"/proc/{w}").exists()], "a worker outlived its killed parent"
    assert not (tmp_path / "t.prt").exists()
    assert list((tmp_path / "t.prt.state").glob("chunk_*.prt"))  # what --resume continues from


# ------------------------------------------------------------------ data loss: outputs that would destroy files

@pytest.fixture(scope="module")
def small_transfer(tmp_path_factory):
    d = tmp_path_factory.mktemp("tr")
    src = d / "t.prt"
    assert cli_main(["precompute", "convex", "--samples", "16", "--bands", "3", "--no-progress", "-o", str(src)]) == 0
    return src


def _refused(argv, capsys, *names):
    """The command ends with status 2 and one line on stderr naming each of ``names``."""
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"prt {argv[0]}: error: "), err
    for n in names:
        assert n in err[0], err
    return err[0]


def _snapshot(d: Path) -> dict:
    return {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(d.rglob("*")) if p.is_file()}


def test_render_refuses_a_comparison_onto_its_own_output(small_transfer, tmp_path, capsys):
    out = tmp_path / "x.png"
    out.write_bytes(b"an earlier render")
    before = _snapshot(tmp_path)
    _refused(["render", str(small_transfer), "-o", str(out), "--compare", str(out), "--overwrite"], capsys, "--compare", "same file")
    assert _snapshot(tmp_path) == before


def test_render_refuses_to_write_over_its_input(small_transfer, tmp_path, capsys):
    link = tmp_path / "same.png"  # another name of the transfer file: the same file
    link.symlink_to(small_transfer)
    before = small_transfer.read_bytes()
    _refused(["render", str(small_transfer), "-o", str(link), "--overwrite"], capsys, "TRANSFER", "destroy the input")
    assert small_transfer.read_bytes() == before


def test_compress_refuses_to_replace_its_own_input(small_transfer, capsys):
    before = (small_transfer.stat().st_mtime_ns, small_transfer.read_bytes())
    _refused(["compress", str(small_transfer), "--codec", "pca", "--vectors", "2", "-o", str(small_transfer), "--overwrite"], capsys,
             "-o/--output", "TRANSFER")
    assert (small_transfer.stat().st_mtime_ns, small_transfer.read_bytes()) == before


def test_precompute_refuses_to_replace_its_mesh(tmp_path, capsys):
    import trimesh

    mesh = tmp_path / "m.ply"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    before = mesh.read_bytes()
    _refused(["precompute", str(mesh), "--samples", "8", "--no-progress", "-o", str(mesh), "--overwrite"], capsys, "MESH_OR_BUILTIN")
    assert mesh.read_bytes() == before and not (tmp_path / "m.ply.state").exists()


def test_light_refuses_a_preview_over_its_image(tmp_path, capsys):
    from prt_torch.lighting import write_image

    img = tmp_path / "env.png"
    write_image(img, torch.rand(16, 32, 3))
    before = img.read_bytes()
    _refused(["light", str(img), "--preview", str(img), "--overwrite"], capsys, "--preview", "LIGHT")
    assert img.read_bytes() == before


def test_plot_needs_overwrite_for_existing_plots(tmp_path, capsys):
    res = {"version": 1, "records": []}
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "results.json").write_text(json.dumps(res))
    out = tmp_path / "plots"
    out.mkdir()
    (out / "rd.png").write_bytes(b"kept")
    _refused(["plot", str(tmp_path / "run"), "-o", str(out)], capsys, "rd.png", "--overwrite")
    assert (out / "rd.png").read_bytes() == b"kept" and not (out / "speed_accuracy.png").exists()


def test_validate_refuses_impossible_sampling_and_its_json_over_an_input(small_transfer, tmp_path, capsys):
    for opt, val, name in (("--spp", "0", "--spp"), ("--vertices", "0", "--vertices"), ("--batches", "0", "--batches"),
                           ("--view-deg", "nan", "--view-deg")):
        _refused(["validate", str(small_transfer), "--light", "sky", opt, val], capsys, name)
    _refused(["validate", str(small_transfer), "--light", "sky", "--json", str(small_transfer), "--overwrite"], capsys, "--json", "TRANSFER")
    (tmp_path / "r.json").write_text("{}")
    _refused(["validate", str(small_transfer), "--light", "sky", "--json", str(tmp_path / "r.json")], capsys, "--overwrite")


def test_strict_json_has_no_nan():
    from prt_torch.io import strict_json

    obj = {"a": float("nan"), "b": [1.0, float("inf"), {"c": -float("inf")}], "d": torch.tensor([1.0, float("nan")])}
    text = json.dumps(strict_json(obj), allow_nan=False)
    assert json.loads(text) == {"a": None, "b": [1.0, None, {"c": None}], "d": [1.0, None]}


# ------------------------------------------------------------------ hangs: an unreachable Ray address

@pytest.mark.parametrize("cmd", [["precompute", "convex", "--samples", "8", "--no-progress", "-o", "out.prt"],
                                 ["bench", "default", "--no-render"]])
def test_an_unreachable_ray_address_is_refused_in_time_creating_nothing(cmd, tmp_path):
    pytest.importorskip("ray")
    import socket

    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PRT_TORCH_RAY_TIMEOUT": "3"}
    t0 = time.monotonic()
    r = subprocess.run([*PRT, *cmd, "--executor", "ray", "--ray-address", f"127.0.0.1:{port}"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=120)
    assert time.monotonic() - t0 < 60
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and f"127.0.0.1:{port}" in err[0] and "Traceback" not in r.stderr, r.stderr
    assert list(tmp_path.iterdir()) == []  # no output, no state directory, no reports or cache


# ------------------------------------------------------------------ silent acceptance: one check per file kind

def _corrupt(src: Path, dst: Path, how: str) -> Path:
    """A copy of a transfer file with one defect the engine must refuse wherever it reads the file."""
    from prt_torch import io

    tensors, meta = io.load(src)
    kind = meta.pop("kind")
    meta = {k: v for k, v in meta.items() if k not in ("format", "format_version", "prt_torch_version")}
    t = {k: v.clone() for k, v in tensors.items()}
    if how == "nan":
        t["data"].view(-1)[5] = float("nan")
    elif how == "overflow":
        t["data"] *= 1e38
    elif how == "faces":
        t["mesh.faces"].view(-1)[0] = 10 ** 6
    elif how == "vertices":
        t["mesh.vertices"].view(-1)[0] = float("inf")
    elif how == "kind":
        kind = "transfer/glossy"
    io.save(dst, t, kind=kind, meta=meta)
    return dst


@pytest.mark.parametrize("how, says", [("nan", "non-finite"), ("overflow", "beyond"), ("faces", "mesh.faces"),
                                       ("vertices", "mesh.vertices"), ("kind", "labelled kind=transfer/glossy")])
def test_every_command_refuses_a_corrupt_transfer_file_alike(how, says, small_transfer, tmp_path, capsys):
    bad = _corrupt(small_transfer, tmp_path / f"{how}.prt", how)
    lines = []
    for argv in (["info", str(bad)],
                 ["compress", str(bad), "--codec", "pca", "--vectors", "2", "-o", str(tmp_path / "c.prt")],
                 ["render", str(bad), "--decode", "cpu", "-o", str(tmp_path / "r.png")],
                 ["validate", str(bad), "--light", "sky", "--vertices", "2", "--spp", "8", "--batches", "1"]):
        lines.append(_refused(argv, capsys, str(bad), says))
    assert len({ln.split(": error: ", 1)[1] for ln in lines}) == 1  # the same check, the same words, in every command
    assert sorted(p.name for p in tmp_path.iterdir()) == [bad.name]  # nothing written


def corrupt_codec(src: Path, dst: Path, how: str) -> Path:
    """A copy of a CPCA codec file with one defect every reader must refuse alike (also the
    corrupt inputs of scripts/hostile_pass.py). `how`: nan, overflow, labels, kind, clusters, nvec."""
    from prt_torch import io

    tensors, meta = io.load(src)
    kind = meta.pop("kind")
    meta = {k: v for k, v in meta.items() if k not in ("format", "format_version", "prt_torch_version")}
    t = {k: v.clone() for k, v in tensors.items()}
    if how == "nan":
        t["model.basis"].view(-1)[3] = float("nan")
    elif how == "overflow":
        t["codes.coeffs"] *= 1e30
    elif how == "labels":
        t["codes.labels"][7] = 9
    elif how == "kind":
        kind = "codec/vq"
    elif how == "clusters":
        meta["model"]["clusters"] = meta["encoded"]["clusters"] = 5
    elif how == "nvec":
        t["model.n_vectors"][0] = 7
    else:
        raise ValueError(f"corrupt_codec: how={how!r}; accepted: nan, overflow, labels, kind, clusters, nvec")
    io.save(dst, t, kind=kind, meta=meta, overwrite=True)
    return dst


@pytest.fixture(scope="module")
def small_codec(small_transfer, tmp_path_factory):
    d = tmp_path_factory.mktemp("codec")
    out = d / "t.cpca.prt"
    assert cli_main(["compress", str(small_transfer), "--codec", "cpca", "--clusters", "4", "--vectors", "2", "-o", str(out)]) == 0
    return out


@pytest.mark.parametrize("how, says", [("nan", "model.basis holds 1 non-finite"), ("overflow", "codes.coeffs reaches"),
                                       ("labels", "codes.labels name clusters 0..9; accepted: 0..3"),
                                       ("kind", "labelled kind=codec/vq but holds codec 'cpca'"),
                                       ("clusters", "model.clusters=5 but model.basis has 4 rows"), ("mesh", "another mesh")])
def test_every_command_refuses_a_corrupt_codec_file_alike(how, says, small_transfer, small_codec, tmp_path, capsys):
    """One consistency check for codec files, as for transfer files: info, render --codec-file and
    validate --codec-file refuse with the same line; a codec file of another mesh by the two that
    know the transfer."""
    if how == "mesh":  # a sound codec file of another transfer (another mesh)
        other = tmp_path / "o.prt"
        assert cli_main(["precompute", "bumpy_sphere:small", "--samples", "8", "--bands", "3", "--no-progress", "-o", str(other)]) == 0
        bad = tmp_path / "mesh.prt"
        assert cli_main(["compress", str(other), "--codec", "cpca", "--clusters", "4", "--vectors", "2", "-o", str(bad)]) == 0
        other.unlink()
        says = "was compressed from a mesh with hash"
    else:
        bad = corrupt_codec(small_codec, tmp_path / f"{how}.prt", how)
    capsys.readouterr()
    lines = []
    readers = [["render", str(small_transfer), "--codec-file", str(bad), "--decode", "cpu", "-o", str(tmp_path / "r.png")],
               ["validate", str(small_transfer), "--light", "constant", "--codec-file", str(bad), "--vertices", "2", "--spp", "8",
                "--batches", "1"]]
    if how != "mesh":
        readers.insert(0, ["info", str(bad)])
    for argv in readers:
        lines.append(_refused(argv, capsys, str(bad), says))
    assert len({ln.split(": error: ", 1)[1] for ln in lines}) == 1  # the same check, the same words, in every command
    assert sorted(p.name for p in tmp_path.iterdir()) == [bad.name]  # nothing written


# ------------------------------------------------------------------ numeric options: finite, in their units

@pytest.mark.parametrize("argv, names", [
    (["light", "sky", "--rotate", "nan,0,0"], ["rotation", "finite"]),
    (["light", "sky", "--rotate", "10,0,inf"], ["rotation", "finite"]),
    (["precompute", "convex", "--samples", "8", "--no-progress", "-o", "{tmp}/p.prt", "--memory-limit", "nan"], ["--memory-limit", "GiB"]),
    (["precompute", "convex", "--samples", "8", "--no-progress", "-o", "{tmp}/p.prt", "--memory-limit", "inf"], ["--memory-limit", "GiB"]),
    (["precompute", "convex", "--samples", "8", "--no-progress", "-o", "{tmp}/p.prt", "--memory-limit", "-1"], ["--memory-limit", "GiB"]),
    (["render", "{transfer}", "-o", "{tmp}/r.png", "--azimuth", "nan"], ["azimuth"]),
    (["validate", "{transfer}", "--light", "sky", "--view-deg", "inf"], ["--view-deg"]),
    (["shrm", "--brdf", "phong", "--light", "sky", "-o", "{tmp}/s.prt", "--max-memory", "nan"], ["--max-memory", "GiB"]),
])
def test_numeric_options_are_finite_and_in_their_units(argv, names, small_transfer, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, transfer=small_transfer) for a in argv]
    _refused(argv, capsys, *names)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ late refusals: what a dry run can know, it checks

@pytest.mark.parametrize("override, names", [
    ("codecs.0.clusters=100000", ["vq-clusters100000", "clusters=100000", "10242"]),
    ("codecs.1.vectors=5000", ["pca-vectors5000", "vectors=5000", "D=1024"]),
    ("lights=[{bad}]", ["lights.0", "cannot read image"]),
])
def test_dry_run_refuses_data_dependent_sizes_and_unreadable_lights(override, names, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.hdr").write_bytes(b"bad")
    before = sorted(p.name for p in tmp_path.iterdir())
    for extra in (["--dry-run"], []):  # the real run refuses the same, before any precompute
        _refused(["bench", "default", override.format(bad=tmp_path / "bad.hdr"), *extra], capsys, *names)
        assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_sweeps_later_point_is_refused_before_the_first_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _refused(["bench", "default", "transfer.M=[4,64]", "metrics.max_memory_gb=1", "--no-render"], capsys, "sweep point", "M64",
             "max_memory_gb")
    assert list(tmp_path.iterdir()) == []  # the first point (M=4) did not run: no cache, no report


def test_a_transport_table_larger_than_the_free_disk_is_refused_before_any_ray(tmp_path, capsys, monkeypatch):
    import collections
    import shutil

    import prt_torch.transfer.transport as T

    monkeypatch.setattr(T, "decide_shadows", lambda *a, **k: pytest.fail("rays were traced before the disk check"))
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(2**40, 2**40 - 2**30, 2**30))  # 1 GiB free
    out = tmp_path / "tables"
    assert cli_main(["precompute", "convex", "--kind", "transport", "--views", "3", "--cube-res", "32", "--no-progress",
                     "-o", str(out)]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]  # after the mesh's one-line summary
    assert last.startswith("prt precompute: error: ") and "GiB" in last and "free" in last and "fewer views" in last, last
    assert list(tmp_path.iterdir()) == []


def test_a_broken_pipe_to_another_process_is_an_error_not_a_closed_stdout(monkeypatch, capfd):
    """`prt ... | head` ends quietly (the reader left); a BrokenPipeError from any other pipe (a worker's)
    is an error with status 2, and standard output stays open for what follows."""
    import prt_torch.cli.info as info

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(info, "run", broken)
    assert cli_main(["info", "x.prt"]) == 2
    out, err = capfd.readouterr()
    assert err.strip().startswith("prt info: error: a pipe to another process broke"), err
    print("stdout still open")
    assert "stdout still open" in capfd.readouterr().out


# ------------------------------------------------------------------ weak messages: in the words the user typed

@pytest.mark.parametrize("argv, names, not_in", [
    # a library parameter name where the user typed an option (quad_bands, chunk_size, up=)
    (["precompute", "convex", "--no-progress", "-o", "{tmp}/a.prt", "--kind", "mrt", "--quad-bands", "0"],
     ["--quad-bands", "unset"], ["quad_bands", "None"]),
    (["precompute", "convex", "--no-progress", "-o", "{tmp}/a.prt", "--chunk", "0"], ["--chunk"], ["chunk_size"]),
    (["light", "sky", "--up", "q"], ["--up", "'q'"], []),  # a built-in environment ignored --up before, whatever it said
    # Python's call-signature texts (missing positional argument, unexpected keyword argument)
    (["light", "directional:foo=1"], ["unknown parameter 'foo'", "accepted: direction (required), intensity"], ["keyword"]),
    (["light", "cap:half_angle_deg=20"], ["needs 'direction'", "half_angle_deg"], ["positional", "half_angle,"]),
    (["shrm", "--brdf", "phong", "--light", "sky", "-o", "{tmp}/s.prt", "--brdf-param", "q=1"], ["unknown parameter 'q'", "accepted: s"],
     ["__init__", "keyword"]),
    # a progress line before the refusal: the light is read before the scene is announced
    (["precompute", "convex", "--no-progress", "-o", "{tmp}/a.prt", "--bands", "auto", "--light", "nosuch"], ["--light", "nosuch"],
     ["vertices"]),
    # a results file without records reached a KeyError traceback in prt plot
    (["plot", "{tmp}/r.json", "-o", "{tmp}/p"], ["r.json", "records"], ["KeyError"]),
])
def test_messages_name_what_the_user_typed(argv, names, not_in, tmp_path, capsys):
    (tmp_path / "r.json").write_text(json.dumps({"format": "prt_torch.results"}))
    before = _snapshot(tmp_path)
    line = _refused([a.format(tmp=tmp_path) for a in argv], capsys, *names)
    for w in not_in:
        assert w not in line, line
    assert _snapshot(tmp_path) == before  # nothing created or changed


def test_an_os_error_is_one_line_without_its_errno(monkeypatch, tmp_path, capsys):
    """A raw OSError text ('[Errno 13] Permission denied: ...') is said as the file and the reason."""
    from prt_torch.cli import info

    def denied(path):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(info, "describe_file", denied)
    line = _refused(["info", str(tmp_path / "x.prt")], capsys, "x.prt", "Permission denied")
    assert "Errno" not in line


def test_the_glsl_decoder_names_the_light_constants_not_an_internal_name():
    import numpy as np

    from prt_torch.render.glsl import AffineDecoder

    with pytest.raises(ValueError, match="per-cluster light constants"):
        AffineDecoder(np.zeros(4, np.int64), np.zeros((4, 2), np.float32), np.zeros((1, 2, 1, 3), np.float32))


def test_shrm_orders_with_no_fourier_terms_build(tmp_path, capsys):
    """--orders 0,P (F_B = 0: the constant row of the Fourier basis alone) reached a RuntimeError
    traceback (a reshape of zero elements); now the file is written."""
    out = tmp_path / "s.prt"
    assert cli_main(["shrm", "--brdf", "phong", "--light", "constant", "--orders", "0,1", "--size", "8", "-o", str(out)]) == 0
    assert out.is_file() and "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("flags, says", [([], "run the same command again to continue"),
                                         (["--no-resume"], "run the same command again without --no-resume")])
def test_an_interrupted_bench_says_the_flags_that_continue_it(flags, says, tmp_path, capsys, monkeypatch):
    """The resume hint names what continues the run: with --no-resume, the same command would
    recompute every finished setting, so the hint says to drop that flag."""
    from prt_torch.harness import run as hr

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(hr, "run_benchmark", interrupted)
    assert cli_main(["bench", "default", "--no-render", *flags]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("prt bench: interrupted; finished settings are kept in") and says in err[0], err


def test_library_names_become_the_options_typed_but_a_named_option_is_left_alone():
    from prt_torch.cli import _in_cli_words, build_parser

    p = build_parser()
    assert _in_cli_words(p, "validate", "spp=0 is out of range") == "--spp 0 is out of range"
    kept = "output 'x' exists; pass overwrite=True (CLI: --overwrite) to replace it"
    assert _in_cli_words(p, "precompute", kept) == kept
    assert _in_cli_words(p, "bench", "config key 'seed' seed=-1") == "config key 'seed' seed=-1"  # bench speaks config keys


def test_resume_without_an_interrupted_run_says_so(tmp_path, capsys):
    out = tmp_path / "a.prt"
    assert cli_main(["precompute", "convex", "--samples", "8", "--no-progress", "-o", str(out), "--resume"]) == 0
    warns = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert warns == [f"prt precompute: warning: --resume: no interrupted run in {str(out) + '.state'!r}; starting from the beginning"]
