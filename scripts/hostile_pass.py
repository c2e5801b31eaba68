"""A hostile user's pass over every prt subcommand (issue 36): run each bad input in-process and
classify how it ends — bad when it is accepted, ends with another status than 2, prints a
traceback or more than one stderr line (argparse's usage + error excepted), or its message holds
a raw Python text or internal name (WEAK), or it creates a file.

    .venv/bin/python scripts/hostile_pass.py OUT.json [--dir DIR]

DIR (default /tmp/prt_hostile) gets the inputs it needs (a small transfer, codec files, corrupt
copies) and a scratch directory the commands run in (emptied before each). Some inputs it expects
refused are valid by design (a writer creates missing parent directories, PCA with 0 vectors is
the mean alone, SHRM orders 0,0, target.lo=0): read the list, not only the count.
Run a revision's package by putting it first on PYTHONPATH."""
import contextlib
import io as _io
import json
import os
import re
import shutil
import signal
import sys
import warnings
from pathlib import Path

H = Path(sys.argv[sys.argv.index("--dir") + 1] if "--dir" in sys.argv else "/tmp/prt_hostile")
S = H / "scratch"
H.mkdir(parents=True, exist_ok=True)


def _prepare() -> None:
    """The inputs: t.prt (convex, diffuse, 3 bands), its PCA/CPCA/VQ codec files, u.prt (another
    mesh) and its CPCA file, and corrupt copies of t.cpca.prt (bad_<how>.prt)."""
    from prt_torch.cli import main as cli

    if not (H / "t.prt").exists():
        with contextlib.redirect_stderr(_io.StringIO()), contextlib.redirect_stdout(_io.StringIO()):
            cli(["precompute", "convex", "--samples", "16", "--bands", "3", "--no-progress", "-o", str(H / "t.prt")])
            for c, extra in (("pca", ["--vectors", "2"]), ("cpca", ["--clusters", "4", "--vectors", "2"]), ("vq", ["--clusters", "4"])):
                cli(["compress", str(H / "t.prt"), "--codec", c, *extra, "-o", str(H / f"t.{c}.prt")])
            cli(["precompute", "bumpy_sphere:small", "--samples", "16", "--bands", "3", "--no-progress", "-o", str(H / "u.prt")])
            cli(["compress", str(H / "u.prt"), "--codec", "cpca", "--clusters", "4", "--vectors", "2", "-o", str(H / "u.cpca.prt")])
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_hostile_2 import corrupt_codec  # the suite's corrupt copies, one definition

    for how in ("nan", "overflow", "labels", "kind", "clusters", "nvec"):
        corrupt_codec(H / "t.cpca.prt", H / f"bad_{how}.prt", how)


_prepare()
T, C, PCA = str(H / "t.prt"), str(H / "t.cpca.prt"), str(H / "t.pca.prt")
(H / "text.txt").write_text("hello\n")
(H / "empty.prt").write_bytes(b"")
(H / "garbage.prt").write_bytes(b"\x00" * 64)
(H / "bad.yaml").write_text("name: [unclosed\n")
(H / "list.yaml").write_text("- a\n- b\n")
(H / "fake.hdr").write_text("not an image")
(H / "bad.json").write_text("{not json")
(H / "norec.json").write_text(json.dumps({"format": "prt_torch.results"}))
(H / "adir").mkdir(exist_ok=True)
TXT, EMPTY, GARB = str(H / "text.txt"), str(H / "empty.prt"), str(H / "garbage.prt")

P = ["precompute", "convex", "--no-progress", "-o", "a.prt"]
R = ["render", T, "-o", "r.png"]
V = ["validate", T, "--light", "constant", "--vertices", "2", "--spp", "8", "--batches", "1"]
SH = ["shrm", "--brdf", "phong", "--light", "sky", "-o", "s.prt"]
B = ["bench", "default", "--dry-run"]
CASES = [
    # precompute
    ["precompute", "nosuchmesh", "-o", "a.prt"], P + ["--samples", "0"], P + ["--samples", "-5"], P + ["--samples", "abc"],
    P + ["--bands", "0"], P + ["--bands", "100"], P + ["--bounces", "-1"], P + ["--kind", "glossy", "--bands-out", "0"],
    P + ["--kind", "mrt", "--tents", "0"], P + ["--chunk", "0"], P + ["--workers", "0"], P + ["--workers", "-1"],
    P + ["--seed", "-1"], P + ["--albedo", "2"], P + ["--albedo", "nan"], P + ["--albedo", "0.5,0.5"], P + ["--up", "w"],
    P + ["--bands", "auto", "--light", "nosuch"], P + ["--bands", "auto", "--energy", "1.5"], P + ["--energy", "nan", "--bands", "auto"],
    ["precompute", "convex", "--no-progress", "-o", "/nonexistent/dir/a.prt"], ["precompute", "convex", "--no-progress", "-o", str(H / "adir")],
    P + ["--resume"], P + ["--kind", "transport", "--views", "0"], P + ["--kind", "transport", "--cube-res", "0"],
    P + ["--kind", "glossy", "--brdf", "nosuch"], P + ["--kind", "glossy", "--brdf", "phong", "--brdf-param", "s=-1"],
    P + ["--kind", "glossy", "--brdf", "phong", "--brdf-param", "s"], P + ["--kind", "glossy", "--brdf", "phong", "--brdf-param", "x=1"],
    P + ["--kind", "mrt", "--window-width", "-1"], P + ["--kind", "mrt", "--quad-bands", "0"], P + ["--kind", "mrt", "--rcond", "nan"],
    P + ["--memory-limit", "0"], P + ["--hit-samples", "0", "--bounces", "1"], P + ["--bounce-tol", "-1", "--bounces", "1"],
    ["precompute", TXT, "-o", "a.prt"], ["precompute", EMPTY, "-o", "a.prt"], ["precompute", "convex:huge", "-o", "a.prt"],
    P + ["--kind", "diffuse", "--tents", "4"], P + ["--samples", "1e9"], P + ["--bands", "3.5"],
    # compress
    ["compress", "nosuch.prt", "-o", "c.prt"], ["compress", T], ["compress", T, "--codec", "nosuch", "-o", "c.prt"],
    ["compress", T, "--codec", "cpca", "--clusters", "0", "-o", "c.prt"], ["compress", T, "--codec", "cpca", "--clusters", "-1", "-o", "c.prt"],
    ["compress", T, "--codec", "cpca", "--clusters", "100000", "-o", "c.prt"], ["compress", T, "--codec", "pca", "--vectors", "0", "-o", "c.prt"],
    ["compress", T, "--codec", "pca", "--vectors", "1000", "-o", "c.prt"], ["compress", T, "--codec", "cpca", "--method", "foo", "-o", "c.prt"],
    ["compress", T, "--codec", "cpca", "--method", "adaptive", "--budget", "-1", "-o", "c.prt"],
    ["compress", T, "--codec", "cpca", "--method", "adaptive", "--budget", "nan", "-o", "c.prt"],
    ["compress", T, "--codec", "pca", "--param", "foo=1", "-o", "c.prt"],
    ["compress", T, "--codec", "cpca", "--param", "max_iter=abc", "-o", "c.prt"],
    ["compress", T, "--codec", "pca", "--param", "noequals", "-o", "c.prt"], ["compress", C, "-o", "c.prt"], ["compress", TXT, "-o", "c.prt"],
    ["compress", GARB, "-o", "c.prt"], ["compress", T, "-o", "/nonexistent/x.prt"], ["compress", T, "--codec", "gaussian", "-o", "c.prt"],
    ["compress", T, "--codec", "mrt_pca", "-o", "c.prt"], ["compress", "--describe", "nosuch"], ["compress", T, "--seed", "-1", "-o", "c.prt"],
    ["compress", T, "--codec", "vq", "--vectors", "3", "-o", "c.prt"], ["compress", str(H / "adir"), "-o", "c.prt"],
    # light
    ["light", "nosuch"], ["light", "sky", "--bands", "0"], ["light", "sky", "--bands", "100"], ["light", "sky", "--window", "foo"],
    ["light", "sky", "--window", "-1"], ["light", "sky", "--rotate", "1,2"], ["light", "sky", "--rotate", "a,b,c"],
    ["light", "sky", "--size", "0", "--preview", "p.png"], ["light", "sky", "--irradiance-map", "i.png", "--irradiance-size", "0"],
    ["light", "directional:direction=0,0,0"], ["light", "directional:intensity=-1"], ["light", "cap:half_angle_deg=200"],
    ["light", "directional:foo=1"], ["light", "nosuchkind:x=1"], ["light", str(H / "fake.hdr")], ["light", "sky", "--up", "q"],
    ["light", "sky", "--preview", "/nonexistent/x.png"], ["light", "directional:direction=0,0,nan"], ["light", TXT],
    ["light", "sky", "--irradiance-map", "i.xyz"],
    # info
    ["info", "nosuch.prt"], ["info", TXT], ["info"], ["info", str(H / "adir")], ["info", EMPTY], ["info", GARB],
    # render
    R + ["--width", "0"], R + ["--height", "99999"], R + ["--fov", "0"], R + ["--fov", "180"], R + ["--fov", "nan"],
    R + ["--elevation", "nan"], R + ["--exposure", "foo"], R + ["--exposure", "nan"], R + ["--supersample", "0"],
    R + ["--supersample", "100"], R + ["--background", "inf"], ["render", T, "-o", "r.xyz"], R + ["--light", "nosuch"],
    R + ["--codec-file", "nosuch.prt"], R + ["--codec-file", T], ["render", C, "-o", "r.png"], R + ["--mesh", "nosuch"],
    ["render", T, "-o", "/nonexistent/r.png"], ["render", "nosuch.prt", "-o", "r.png"], R + ["--codec-file", GARB],
    R + ["--light", "directional:direction=0,0,0"], R + ["--elevation", "95"],
    # plot
    ["plot", "nosuch", "-o", "p"], ["plot", TXT, "-o", "p"], ["plot", str(H / "bad.json"), "-o", "p"],
    ["plot", str(H / "norec.json"), "-o", "p"], ["plot", str(H / "norec.json"), "--labels", "a", "b", "-o", "p"],
    # validate
    ["validate", T, "--light", "nosuch"], V + ["--vertices", "-1"], V + ["--spp", "abc"], V + ["--seed", "-1"],
    V + ["--mesh", "nosuch"], V + ["--view-deg", "0"], ["validate", C, "--light", "constant"], V + ["--codec-file", "nosuch.prt"],
    V + ["--vertices", "100000000"], V + ["--light-source", "image"],
    # shrm
    ["shrm", "--brdf", "nosuch", "--light", "sky", "-o", "s.prt"], SH + ["--brdf-param", "s=-1"], SH + ["--epsilon", "0"],
    SH + ["--epsilon", "2"], SH + ["--orders", "0,0"], SH + ["--orders", "a"], SH + ["--orders", "3"], SH + ["--size", "0"],
    SH + ["--max-memory", "0"], SH + ["--max-memory", "nan"], ["shrm", "--brdf", "phong", "--light", "nosuch", "-o", "s.prt"],
    SH + ["--epsilon", "nan"], SH + ["--brdf-param", "q=1"],
    # bench
    ["bench", "nosuchconfig", "--dry-run"], B + ["foo=1"], B + ["codecs.0.clusters=0"], B + ["transfer.bands=0"],
    B + ["metrics.repeats=0"], B + ["target.psnr=nan"], B + ["--target-psnr", "-5"], B + ["--target-codec", "nosuch", "--target-psnr", "30"],
    B + ["--target-psnr", "30", "--target-codec", "pca", "--target-param", "nosuch"], B + ["scene.size=huge"],
    ["bench", str(H / "bad.yaml"), "--dry-run"], ["bench", str(H / "list.yaml"), "--dry-run"], B + ["lights=[nosuch]"],
    B + ["views.count=0"], B + ["seed=-1"], B + ["render.width=0"], B + ["codecs=[]"], B + ["codecs.9.vectors=2"],
    B + ["transfer.type=nosuch"], B + ["metrics.max_memory_gb=nan"], B + ["target.hi_clusters=0", "--target-psnr", "30"],
    B + ["views.elevation=nan"], B + ["transfer.samples=abc"],
    # second wave: outputs under a file, corrupt codec files everywhere, more numbers
    ["precompute", "convex", "--no-progress", "-o", TXT + "/a.prt"], ["compress", T, "-o", TXT + "/c.prt"],
    ["render", T, "-o", TXT + "/r.png"], ["light", "sky", "--preview", TXT + "/p.png"], SH[:-1] + [TXT + "/s.prt"],
    V + ["--json", TXT + "/v.json"], ["plot", str(H / "norec.json"), "-o", TXT + "/p"],
    ["info", str(H / "bad_nan.prt")], ["info", str(H / "bad_labels.prt")], ["info", str(H / "bad_kind.prt")],
    R + ["--codec-file", str(H / "bad_nan.prt"), "--decode", "cpu"], R + ["--codec-file", str(H / "bad_labels.prt"), "--decode", "cpu"],
    R + ["--codec-file", str(H / "bad_overflow.prt"), "--decode", "cpu"], R + ["--codec-file", str(H / "bad_clusters.prt"), "--decode", "cpu"],
    R + ["--codec-file", str(H / "u.cpca.prt"), "--decode", "cpu"], V + ["--codec-file", str(H / "u.cpca.prt")],
    V + ["--codec-file", str(H / "bad_nvec.prt")], V + ["--codec-file", str(H / "bad_kind.prt")],
    ["light", "sky", "--bands", "-1"], ["light", "sky", "--irradiance-map", "i.png", "--irradiance-size", "-5"],
    ["light", "sky", "--size", "-1"], SH + ["--size", "-1"], ["shrm", "--brdf", "phong", "--light", "directional:direction=0,0,0", "-o", "s.prt"],
    V + ["--batches", "5000"], V + ["--spp", "1e9"], R + ["--width", "-1"], R + ["--azimuth", "inf"], R + ["--exposure", "inf"],
    P + ["--albedo", "-0.5"], P + ["--albedo", "1,1,1,1"], B + ["--target-psnr", "nan"], B + ["--target-psnr", "inf"],
    B + ["metrics.random_lights=0"], B + ["metrics.cold_pairs=-1"], B + ["views.count=-1"], B + ["transfer.samples=0"],
    B + ["codecs.0.type=nosuch"], B + ["target.lo=0", "--target-psnr", "30"], ["info", "--json", GARB],
    ["light", "directional:direction=1,0,0;intensity=nan"], ["light", "cap:direction=0,0,1;half_angle_deg=-5"],
    ["light", "constant:value=inf"], ["compress", T, "--codec", "cpca", "--clusters", "4", "--vectors", "0", "-o", "c.prt"],
    ["compress", T, "--codec", "gaussian", "--param", "lobes=0", "-o", "c.prt"],
    R + ["--decode", "glsl", "--codec-file", PCA, "--width", "8", "--height", "8", "--light", "nosuch"],
]
WEAK = re.compile(r"Errno|IndexError|KeyError|list index|NoneType|has no attribute|unsupported operand|invalid literal|"
                  r"could not convert|not subscriptable|\bconsts\b|quad_bands|Traceback|unexpected keyword|positional argument|"
                  r"safetensors|HeaderTooSmall|SafetensorError|object of type|cannot convert float|math domain|division by zero")


def run(argv):
    from prt_torch.cli import main
    err, out = _io.StringIO(), _io.StringIO()
    signal.alarm(120)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                rc = main(argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else 2
            except BaseException as e:  # noqa: BLE001
                import traceback
                traceback.print_exc(file=err)
                rc = f"raised {type(e).__name__}"
    finally:
        signal.alarm(0)
    return rc, err.getvalue()


def judge(argv, rc, err):
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    why = []
    if rc == 0:
        why.append("accepted")
    elif rc != 2:
        why.append(f"status {rc}")
    if "Traceback" in err:
        why.append("traceback")
    argparse_style = len(lines) >= 2 and lines[0].startswith("usage:")
    if rc == 2 and not argparse_style and len(lines) != 1:
        why.append(f"{len(lines)} stderr lines")
    if WEAK.search(err):
        why.append("weak: " + WEAK.search(err).group(0))
    return why


def main():
    S.mkdir(exist_ok=True)
    os.chdir(S)
    results = []
    for argv in CASES:
        for p in S.iterdir():
            shutil.rmtree(p) if p.is_dir() else p.unlink()
        rc, err = run(argv)
        why = judge(argv, rc, err)
        made = sorted(p.name for p in S.iterdir())
        if made and rc != 0:
            why.append(f"created {made}")
        results.append({"argv": argv, "rc": rc if isinstance(rc, int) else str(rc), "stderr": err.strip()[-400:], "bad": why})
        print(("BAD " if why else "ok  ") + " ".join(argv)[:110] + (f"  -> {why}: {err.strip()[-200:]!r}" if why else ""), flush=True)
    bad = [r for r in results if r["bad"]]
    print(f"\n{len(results)} inputs, {len(bad)} ended badly")
    Path(sys.argv[1]).write_text(json.dumps(results, indent=1))


main()
