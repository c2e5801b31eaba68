"""Every guide's command blocks, run in the order written, in a temporary directory: each line exits 0 and writes what
it names.

tests/test_docs_commands.py parses every documented command line and checks the names and the order of its files
(no work). What only a run finds depends on the data: ``prt compress --vectors 4`` of a 2-band transfer (4
coefficients) is refused by the fit, not by the parser (docs/validate.md had one). Here each guide's block lines
(README.md and docs/{wavelet,precompute,codecs,harness,lighting,render,validate,inverse,subsurface,ray}.md, as
tests/test_docs_commands.py extracts them) are executed, one test per guide, in process through the CLI
(``prt_torch.cli.main(argv)``: its return value is the exit status, argparse's usage errors ``SystemExit(2)``), in a
fresh directory per guide, with the line's ``NAME=value`` environment prefixes set for that line only.

To run on 2 cores in about a minute, the lines are changed by the rules of ``RULES`` below, each with its reason, and
by nothing else; a failure names the guide and line, the line as written, the line as run and the rules applied, the
exit status and the last lines of its stderr. A line the rules leave out is listed by ``SKIPS`` with its reason (never
skipped silently), and a command of a block that is not the project's (``pip``, ``ray start``, ``ruff``, ``pytest``)
is not run: ``FOREIGN`` names them. A user's own file a line reads (``scan.ply``, ``env.exr``, ``captures/``,
``TRANSFER.prt``, ``my_sweep.yaml``) is made in the directory before the line runs (``USER_FILES``); a ``.prt`` a
line reads from another guide its comment cites (``# a wavelet transfer (docs/wavelet.md)``) is made by running that
guide's line that writes it, under the same rules.

Checks per line: the exit status is 0 (2 where the line's comment says it is refused: ``REFUSED``; 130 for a line
interrupted by ``INTERRUPT_RULE``, which must leave its chunks in ``<out>.state/``); every output it names (``-o``,
``--compare``, ``--report``, ``--json PATH``) exists afterwards; a ``--dry-run`` or a refused line creates none of them;
a line that names no output file (``prt info``, ``prt light``, ``prt validate``) prints something.

GL (EGL offscreen) renders ``prt render``'s images and ``prt invert``'s photographs: a guide with such lines is skipped,
saying so, only with ``PRT_SKIP_GL=1`` outside CI, as tests/conftest.py's ``renderer`` fixture does.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import runpy
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from test_docs_commands import CITED, COMMANDS, GUIDES, PARSED, PYTHON, ROOT, Command, _inputs, _is_users_file

from prt_torch.cli import main

SMALL = "small"
CAPTURE_SIZE = (24, 24)  # photographs for prt invert: 4 views of this many pixels (half of tests/test_inverse.py's edge)
CAPS = {  # option -> the largest value run: (cap, reason)
    "--samples": (64, "rays per vertex: Monte Carlo noise, not what the line checks"),
    "--bounces": (1, "each bounce re-traces every vertex; one shows the path runs"),
    "--hit-samples": (4, "interreflection samples per texel hit"),
    "--res": (16, "wavelet cube face edge: 6 R^2 coefficients per vertex"),
    "--supersample": (1, "texel supersampling multiplies the rays"),
    "--spp": (256, "Mitsuba samples per vertex and depth: the reference's noise only"),
    "--vertices": (8, "vertices compared with Mitsuba"),
    "--batches": (2, "Mitsuba batches (for the standard error): 2 is the fewest that has one"),
    "--clusters": (16, "the small scene's points: 256 clusters would be a handful of points each"),
}
CAP_RULE = "cap"
SIZE_RULE = "size"
LOCAL_RULE = "ray-local"
DRY_RULE = "bench-dry-run"
HELP_RULE = "benchmark-help"
NEURAL_RULE = "neural-epochs"
INTERRUPT_RULE = "interrupt-then-resume"
PLOT_RULE = "plot-baseline"
RULES = {
    SIZE_RULE: "`prt precompute` of a built-in scene at its default size, or any command's built-in mesh, at medium, "
               "large or xl (~10k, 50k, ~1M vertices; the 1M mesh "
               "alone takes ~5 s to build) runs at :small (~2k): the commands and their files are the same, the vertex "
               "count is a parameter the scale tests (tests/test_scale.py) cover",
    CAP_RULE: "numeric options capped (CAPS, each with its reason): sampling and sizes that set the cost, not the path run",
    DRY_RULE: "`prt bench` runs a whole benchmark (minutes to hours): run with --dry-run --no-time, which loads and "
              "validates the config with its overrides and plans the sweep (tests/test_harness.py runs small configs)",
    HELP_RULE: "a benchmark script (minutes; it writes reports/benchmarks/): its --help, after the line's options, "
               "parses them",
    LOCAL_RULE: "`prt precompute --executor ray` starts a local Ray (processes on the 2 cores, ~10 s): run with the "
                "local executor, whose result the Ray run equals bit for bit (docs/ray.md; tests/test_ray.py runs Ray)",
    NEURAL_RULE: "the neural codec trains up to 300 epochs (tens of seconds): --param epochs=2",
    INTERRUPT_RULE: "a precompute line followed by the same line with --resume ('after Ctrl-C / SIGTERM / a crash') is "
                    "interrupted after its first chunk is saved, as Ctrl-C would (status 130, the chunks kept), so the "
                    "--resume line continues a run as the guide says (after a finished run --resume is refused: the "
                    "output exists)",
    PLOT_RULE: "`prt plot` of the reports the `prt bench` lines above would write (they ran --dry-run): the committed "
               "reports/baseline/results.json copied to each directory it names",
}
REFUSED = r"\b(refused|refuses)\b"  # a line whose comment says so is expected to end with status 2 and write nothing
SKIPS = [  # (pattern on the line as written, reason): the line is not run
    (r"^scripts/setup\b", "sets up the environment the test runs in (a virtual environment, Debian packages)"),
    (r"--ray-address (?!auto\b)\S+", "joins a Ray cluster at HEAD_IP that the line's block started on other nodes"),
    (r"--executor ray --ray-address auto", "joins the Ray cluster of the node it runs on (`ray start` above: other "
                                           "machines)"),
]
FOREIGN = "not the project's command (pip, ray start, ruff, pytest): installing, clusters and the suite itself"
GUIDES_WITHOUT_BLOCKS = {  # guides whose command lines are inline spans only (tests/test_docs_commands.py parses them)
    "docs/harness.md", "docs/lighting.md", "docs/render.md",
}


# ------------------------------------------------------------------------------------ users' files
def _mesh_file(path: Path, argv: list[str] | None = None) -> None:
    """A scan-like mesh (the built-in scan_blob, small) written as ``path`` (PLY or OBJ)."""
    import trimesh

    from prt_torch.scene import load_scene

    mesh = load_scene("scan_blob:small")
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(mesh.vertices.numpy(), mesh.faces.numpy(), process=False).export(path)


def _env_file(path: Path, argv: list[str]) -> None:
    """The built-in sky environment (lat-long, 32 rows) written as an HDR image."""
    from prt_torch.lighting import builtin_environment, write_image

    write_image(path, builtin_environment("sky", size=32).image.numpy())


def _transfer_file(path: Path, argv: list[str]) -> None:
    """A diffuse transfer of bumpy_sphere:small (5 bands: 25 coefficients, as the guides' max_vectors=16 needs; 64
    samples): a user's TRANSFER.prt / BIG.prt."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        status = main(["precompute", "bumpy_sphere:small", "--bands", "5", "--samples", "64", "-o", str(path)])
    assert status == 0, err.getvalue()


def _config_file(path: Path, argv: list[str]) -> None:
    """A user's config: the shipped default's file (loaded by path, as a user's is)."""
    shutil.copy(ROOT / "configs" / "default.yaml", path)


def _captures(path: Path, argv: list[str]) -> None:
    """Photographs of the line's ``--mesh`` file (made first if missing) under the studio light: 4 views, 24x24 float
    EXR with alpha, rendered by the engine (GL), and their ``transforms.json`` at ``path``: tests/test_inverse.py's
    cameras."""
    from test_inverse import _cams, _transforms

    from prt_torch import relight
    from prt_torch.lighting import load_light, write_image
    from prt_torch.render import Renderer
    from prt_torch.scene import load_scene
    from prt_torch.transfer.diffuse import precompute_diffuse

    mesh_file = _opt(argv, "--mesh")
    if not Path(mesh_file).exists():
        _mesh_file(Path(mesh_file))
    mesh = load_scene(mesh_file, albedo=0.8)
    T = precompute_diffuse(mesh, bands=4, samples=64, fold_albedo=False)
    rad = (relight.diffuse_transfer(T, load_light("studio", 4)) * 0.8).clamp(min=0)
    d = path.parent
    d.mkdir(parents=True, exist_ok=True)
    cams, (W, H), files = _cams(mesh, 4), CAPTURE_SIZE, []  # 24x24: the fits' cost, not what the lines check
    with Renderer(W, H) as r:
        for k, cam in enumerate(cams):
            img, m = r.render_radiance(mesh, rad, cam, W, H, background=float("nan"))
            write_image(d / f"v{k}.exr", np.concatenate([img, m[..., None].astype(np.float32)], 2))
            files.append(f"v{k}.exr")
    _transforms(d, cams, files, W, H)


USER_FILES = {  # a suffix or name a line reads -> (what is made, maker)
    ".ply": ("a scan: the built-in scan_blob (small) written as PLY", _mesh_file),
    ".obj": ("a scan: the built-in scan_blob (small) written as OBJ", _mesh_file),
    ".exr": ("an environment map: the built-in sky, lat-long, 32 rows", _env_file),
    "transforms.json": ("photographs: 4 engine renders of the line's --mesh under studio light (tests/test_inverse.py's "
                        "cameras)", _captures),
    "TRANSFER.prt": ("a transfer: bumpy_sphere:small, diffuse, 5 bands, 64 samples", _transfer_file),
    "BIG.prt": ("a transfer: bumpy_sphere:small, diffuse, 5 bands, 64 samples", _transfer_file),
    ".yaml": ("a user's config: a copy of configs/default.yaml", _config_file),
}


# ------------------------------------------------------------------------------------ the rules
@dataclass
class Run:
    """A documented line as it is run."""
    c: Command
    argv: list[str]  # the words after `prt` (or the script's words)
    rules: list[str]
    interrupt: bool = False


def _opt(words: list[str], name: str) -> str | None:
    return words[words.index(name) + 1] if name in words[:-1] else None


def _scenes(c: Command) -> list[str]:
    """The built-in scenes a parsed line names: ``prt precompute``'s MESH_OR_BUILTIN, and the mesh of ``prt render
    --mesh`` / ``--method shrm MESH``, ``prt invert --mesh`` and ``prt validate --mesh`` (the one rule for naming a mesh,
    ``prt_torch.scene.check_scene``: a size is taken everywhere)."""
    from prt_torch.scene import list_builtins

    a = PARSED[id(c)]
    if a.command == "precompute":
        return [a.scene]
    names = [getattr(a, "mesh", None)] if a.command in ("render", "invert", "validate") else []
    if a.command == "render" and getattr(a, "method", None) == "shrm":
        names.append(a.transfer)
    return [w for w in names if w and w.partition(":")[0] in list_builtins() and not _is_users_file(w)]


def _rewrite(c: Command, next_line: Command | None) -> Run:
    """The line ``c`` as run: RULES applied (SKIPS are decided before)."""
    words, rules = list(c.words[1:]), []
    if c.words[0] in PYTHON:
        return Run(c, [*words, "--help"], [HELP_RULE])
    sub = words[0]
    for w in _scenes(c):  # built-in scenes at a size (or precompute's default-size bumpy_sphere) -> :small
        name, _, size = w.partition(":")
        if not _is_users_file(w) and size != SMALL and (size or sub == "precompute"):
            words[words.index(w)] = f"{name}:{SMALL}"
            rules.append(SIZE_RULE)
    for opt, (cap, _) in CAPS.items():
        v = _opt(words, opt)
        if v is not None and v.isdigit() and int(v) > cap:
            words[words.index(opt) + 1] = str(cap)
            rules.append(f"{CAP_RULE} {opt} {v}->{cap}")
    if sub == "bench" and "--dry-run" not in words:
        words += ["--dry-run", "--no-time"]
        rules.append(DRY_RULE)
    elif sub == "bench" and "--no-time" not in words:
        words += ["--no-time"]
        rules.append(DRY_RULE)
    if sub == "precompute" and _opt(words, "--executor") == "ray":
        words[words.index("--executor") + 1] = "local"
        rules.append(LOCAL_RULE)
    if sub == "compress" and _opt(words, "--codec") == "neural":
        words += ["--param", "epochs=2"]
        rules.append(NEURAL_RULE)
    interrupt = (sub == "precompute" and next_line is not None and next_line.words == [*c.words, "--resume"])
    if interrupt:
        rules.append(INTERRUPT_RULE)
    if sub == "plot":
        rules.append(PLOT_RULE)
    return Run(c, words, rules, interrupt)


def _skip_reason(c: Command) -> str | None:
    if c.kind == "foreign":
        return FOREIGN
    text = " ".join(c.words)
    return next((why for pat, why in SKIPS if re.search(pat, text)), None)


# ------------------------------------------------------------------------------------ running
def _outputs(r: Run) -> list[str]:
    """The files and directories the line as run names as its outputs."""
    w = r.argv
    if w[0] not in ("precompute", "compress", "relight", "render", "shrm", "invert", "plot", "light", "validate"):
        return []
    if {"--list", "--describe"} & set(w):
        return []
    outs = [_opt(w, "-o") or _opt(w, "--output"), _opt(w, "--compare"), _opt(w, "--report")]
    json_out = _opt(w, "--json")
    if json_out is not None and not json_out.startswith("-"):
        outs.append(json_out)
    if w[0] == "light":
        outs.append(_opt(w, "--irradiance-map"))
    return [o for o in outs if o]


def _make_inputs(r: Run, cwd: Path) -> None:
    """The user's files the line reads (USER_FILES, by name or suffix), made if missing."""
    outs = set(_outputs(r))
    for w in r.argv:
        p = cwd / w
        made = USER_FILES.get(p.name) or USER_FILES.get(p.suffix)
        if made is not None and w not in outs and _is_users_file(w) and not p.exists():
            made[1](p, r.argv)
    if r.argv[0] == "plot":
        for d in r.argv[1:]:
            if d.startswith("-") or d == _opt(r.argv, "-o"):
                continue
            (cwd / d).mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / "reports" / "baseline" / "results.json", cwd / d / "results.json")


def _call(r: Run, monkeypatch) -> tuple[int, str, str]:
    """``(exit status, stdout, stderr)`` of the line run in process."""
    err, out = io.StringIO(), io.StringIO()
    with monkeypatch.context() as m, contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        for k, v in r.c.env.items():
            m.setenv(k, v)
        if "PRT_TORCH_KERNEL_ISA" in r.c.env:  # read once per process, at the first kernel load: this line gets its own
            from prt_torch import relight  # load (if it loads one), and the rest of the session keeps the one it had
            from prt_torch.codecs import relight_kernels

            m.setattr(relight_kernels, "_state", {})
            m.setattr(relight, "_WAVELET", {})
        if r.interrupt:
            import prt_torch.transfer as tr

            class Interrupted(tr.RunOptions):  # `prt precompute` imports RunOptions from prt_torch.transfer when it runs
                def __init__(self, *a, **k):
                    def stop(i, n):  # after chunk i of n is saved: Ctrl-C
                        raise KeyboardInterrupt()
                    super().__init__(*a, **{**k, "callback": stop})

            m.setattr(tr, "RunOptions", Interrupted)
        try:
            if r.c.words[0] in PYTHON:
                m.setattr(sys, "argv", [str(ROOT / r.argv[0]), *r.argv[1:]])
                m.syspath_prepend(str((ROOT / r.argv[0]).parent))  # as `python SCRIPT` puts its directory first
                runpy.run_path(str(ROOT / r.argv[0]), run_name="__main__")
                status = 0
            else:
                status = main(r.argv)
        except SystemExit as e:
            status = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    return status, out.getvalue(), err.getvalue()


def _run_line(r: Run, cwd: Path, monkeypatch, log: list[str]) -> None:
    c = r.c
    try:
        _make_inputs(r, cwd)
    except Exception as e:  # noqa: BLE001 (named with the line it was for)
        pytest.fail(f"{c.where}: `{' '.join(c.words)}`: making the user's files it reads (USER_FILES): {e!r}")
    before = {o: (cwd / o).exists() for o in _outputs(r)}
    t = time.perf_counter()
    status, out, err = _call(r, monkeypatch)
    dt = time.perf_counter() - t
    log.append(f"{dt:6.2f} s  {c.where}  {' '.join(r.argv)}")
    refused = re.search(REFUSED, c.comment)
    expected = 130 if r.interrupt else 2 if refused else 0
    what = (f"{c.where}: `{' '.join(c.words)}`\n  run as: {'python' if c.words[0] in PYTHON else 'prt'} {' '.join(r.argv)}"
            + (f"\n  rules: {', '.join(r.rules)}" if r.rules else ""))
    tail = "\n    ".join(err.strip().splitlines()[-6:])
    assert status == expected, f"{what}\n  exit status {status} (expected {expected}); stderr:\n    {tail}"
    if r.interrupt:  # Ctrl-C after a chunk: the chunks kept in <out>.state/ (--resume reads them), no output yet
        o = _opt(r.argv, "-o")
        assert (cwd / f"{o}.state").is_dir() and not (cwd / o).exists(), f"{what}\n  interrupted: no {o}.state/ kept"
    if r.interrupt or c.words[0] in PYTHON:
        return
    if not before and "--dry-run" not in r.argv:
        assert out.strip(), f"{what}\n  names no output file and printed nothing"
    for o, existed in before.items():
        if refused:
            assert (cwd / o).exists() == existed, f"{what}\n  refused (status 2) but created {o}"
        elif "--dry-run" in r.argv:
            assert (cwd / o).exists() == existed, f"{what}\n  --dry-run created {o}"
        else:
            assert (cwd / o).exists(), f"{what}\n  exit 0 but its output {o} does not exist; stderr:\n    {tail}"


def _lines(guide: str) -> list[Command]:
    return [c for c in COMMANDS if c.guide == guide and c.kind in ("line", "foreign")]


def _plan(guide: str) -> list[tuple[Command, Run | None, str | None]]:
    """Each block line of the guide: (line, the run or None, the skip reason or None)."""
    lines = _lines(guide)
    out = []
    for k, c in enumerate(lines):
        why = _skip_reason(c)
        nxt = lines[k + 1] if k + 1 < len(lines) else None
        out.append((c, None if why else _rewrite(c, nxt), why))
    return out


def _cited_input(r: Run, cwd: Path, monkeypatch, log: list[str]) -> None:
    """A .prt the line reads from a guide its comment cites: that guide's line writing it, run here first."""
    for g in CITED.findall(r.c.comment):
        for f in [f for f in _inputs(PARSED[id(r.c)]) if not (cwd / f).exists()]:
            for c, other, _ in _plan(f"docs/{g}.md"):
                if other is not None and _opt(other.argv, "-o") == f and "--dry-run" not in other.argv:
                    _run_line(other, cwd, monkeypatch, log)
                    break


RUN_GUIDES = [g for g in GUIDES if g not in GUIDES_WITHOUT_BLOCKS]


def test_guides_without_blocks_have_none():
    """The guides left out of the run have no command block lines (add one and it must be run)."""
    assert not [c.where for g in GUIDES_WITHOUT_BLOCKS for c in _lines(g) if c.kind == "line"]


@pytest.mark.parametrize("guide", RUN_GUIDES)
def test_guide_commands_run_in_order(guide, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYOPENGL_PLATFORM", os.environ.get("PYOPENGL_PLATFORM", "egl"))
    log: list[str] = []
    plan = _plan(guide)
    assert any(r is not None for _, r, _ in plan), f"{guide}: no command line is run"
    gl = [c.where for c, r, _ in plan if r is not None and (r.argv[0] == "render" or "--cameras" in r.argv)]
    if gl and os.environ.get("PRT_SKIP_GL") == "1" and os.environ.get("CI", "").lower() != "true":
        pytest.skip(f"PRT_SKIP_GL=1 outside CI (tests/conftest.py's rule): {guide} renders with GL at {', '.join(gl)}")
    for c, r, why in plan:
        if r is None:
            log.append(f"  skip  {c.where}  {' '.join(c.words)}: {why}")
            continue
        _cited_input(r, tmp_path, monkeypatch, log)
        _run_line(r, tmp_path, monkeypatch, log)
    print("\n".join(log))


def test_every_rule_is_used():
    """Each rule, cap and skip applies to some line of the guides today (a rule no line needs any more goes)."""
    plans = [p for g in RUN_GUIDES for p in _plan(g)]
    used = {rule.split()[0] for _, r, _ in plans if r is not None for rule in r.rules}
    caps = {rule.split()[1] for _, r, _ in plans if r is not None for rule in r.rules if rule.startswith(CAP_RULE)}
    texts = [" ".join(c.words) for c, _, _ in plans]
    assert set(RULES) <= used, sorted(set(RULES) - used)
    assert set(CAPS) <= caps, sorted(set(CAPS) - caps)
    assert all(any(re.search(pat, t) for t in texts) for pat, _ in SKIPS)
    assert any(why == FOREIGN for _, _, why in plans)
