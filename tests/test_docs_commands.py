"""Every command line the user's guides show still parses, names things that exist, and can be run in order.

The guides are README.md and docs/{wavelet,precompute,codecs,harness,lighting,render,validate,inverse,subsurface,
ray}.md (not the dated *_log.md records). What is read, and how:

* **Command blocks**: the lines of every ```bash block and of every unlabelled ``` block whose command is ``prt``
  (``.venv/bin/prt``), a ``python`` running ``benchmarks/X.py`` or ``scripts/X``; shell continuations (``\\``)
  joined, ``# comments`` dropped, ``&&`` splitting one line into commands, ``NAME=value`` environment prefixes
  dropped. Other commands (``pip``, ``ray start``) are not the project's and are not read.
* **Synopses**: a command whose words contain ``[`` option groups, ``|`` alternatives or ``...`` (docs/render.md's and
  docs/lighting.md's usage lines; the indented ``[...]`` lines under one continue it) is not a command line: each
  ``--option`` it names must be an option of its subcommand, nothing more.
* **Inline code spans** ```prt SUB ...``` in the prose are mostly fragments (``prt relight --terms N``, ``prt bench
  ... --target-psnr X``): their subcommand must exist and each ``--option`` they name must be one of its options; a
  span that parses as a whole command (as written, or with ``-o OUT`` added where it names no output: prose leaves
  it out, ``prt precompute cornell_box:small --bounces 1``) has its names checked as a block's line is (below).

A block's ``prt`` command line is parsed with the CLI's own parser (``prt_torch.cli.parse_args`` of
``build_parser()``, exactly as ``prt`` parses it: no work is done), then:

* every built-in name it uses exists: a scene (``precompute``'s MESH, ``render --method shrm``'s MESH, ``--mesh``;
  ``name`` or ``name:size``, ``prt_torch.scene.list_builtins`` / ``check_size``), a light (``--light``, ``prt light``'s
  LIGHT: a built-in environment or an analytic spec that loads), a config (``prt bench``: a shipped config or an
  existing ``configs/`` path, loaded with the line's ``key=value`` overrides and validated by
  ``harness.config.load_config``, which does no work), a codec (``--codec``), a BRDF model (``--brdf``,
  ``--transfer-brdf``; ``prt invert --brdf`` takes its own list), a subsurface ``--material``. **A value with a file suffix or a ``/`` is the user's
  file** (``scan.ply``, ``bust.obj``, ``env.exr``, ``light.json``, ``my_sweep.yaml``: the guides say so where they
  use them) and is not looked up, except a ``configs/...`` path, which must exist in the checkout; so is a
  placeholder in capitals (``MESH``, ``FILE``, ``TRANSPORT_DIR``);
* the files it reads were written before it: a ``.prt`` input (the positional TRANSFER of ``compress``, ``relight``,
  ``render``, ``validate``, ``info``; ``--codec-file``) is the ``-o`` output of an earlier command line of the same
  guide (not a ``--dry-run``, which writes nothing), or of a command line in a guide the line's comment names
  (``# a wavelet transfer (docs/wavelet.md)``), or a placeholder written in capitals (``TRANSFER.prt``, ``BIG.prt``);
  other inputs (meshes, images, directories) are the user's;
* its output is not one an earlier command line of the same guide wrote, unless it passes ``--overwrite`` or
  ``--resume``: every ``prt`` command refuses an existing output otherwise, ``--dry-run`` included, so a guide's
  second ``-o w.npy`` failed when copied in order.

Each ``benchmarks/X.py`` and ``scripts/X`` a guide names (anywhere in its text) exists, and each ``--option`` a
command line or code span gives a benchmark appears in that script's source as ``"--option"`` (the benchmarks build
their parsers inside ``main()``, so nothing cheaper shows them). Each ``PRT_*`` environment variable a guide names is
read somewhere in the project.

Running the commands is not done here: tests/test_docs_run.py runs each guide's block lines in order, on small
inputs (its rules say which), in about a minute. Only a run finds what depends on the data (``prt compress --vectors
4`` of a 2-band transfer, 4 coefficients, is refused by the fit, not by the parser: docs/validate.md had one). The
whole file takes about 2 s, most of it importing the CLI and the library.
"""

from __future__ import annotations

import contextlib
import functools
import io
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from prt_torch.cli import build_parser, parse_args

ROOT = Path(__file__).resolve().parents[1]
GUIDES = ["README.md"] + [f"docs/{n}.md" for n in ("wavelet", "precompute", "codecs", "harness", "lighting", "render",
                                                  "validate", "inverse", "subsurface", "ray")]
PRT = {"prt", ".venv/bin/prt"}
PYTHON = {"python", "python3", ".venv/bin/python", ".venv/bin/python3"}
ENV_PREFIX = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
FENCE = re.compile(r"^\s*```(\S*)\s*$")
INLINE = re.compile(r"`((?:[A-Z_][A-Z0-9_]*=\S+ )*(?:\.venv/bin/)?(?:prt|python3?|\.venv/bin/python3?) [^`]+)`")
NAMED_SCRIPT = re.compile(r"(?<![\w/.-])((?:benchmarks/\w+\.py)|(?:scripts/[\w.-]*\w))")
OPTION = re.compile(r"^\[?(--?[A-Za-z][\w-]*)")
CITED = re.compile(r"docs/(\w+)\.md")


@dataclass
class Command:
    where: str  # file:line
    words: list[str]  # environment prefixes dropped; words[0] is the program
    comment: str = ""
    kind: str = "line"  # line | synopsis | inline | foreign (a block's command that is not the project's: pip, ray)
    guide: str = ""
    env: dict[str, str] = field(default_factory=dict)  # the NAME=value prefixes dropped from words


def _split_comment(text: str) -> tuple[str, str]:
    """``(command, comment)``: the comment starts at the first ``#`` outside quotes that begins a word."""
    quote = None
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or text[i - 1].isspace()):
            return text[:i].rstrip(), text[i + 1:].strip()
    return text, ""


def _commands_of(text: str) -> list[tuple[dict[str, str], list[str]]]:
    """``(environment prefixes, words)`` of each ``&&``-separated command of a shell line, the prefixes dropped from
    the words."""
    out, cur = [], []
    for w in shlex.split(text):
        if w == "&&":
            out.append(cur)
            cur = []
        else:
            cur.append(w)
    out.append(cur)
    return [(_env_of(c), _drop_env(c)) for c in out if c]


def _env_of(words: list[str]) -> dict[str, str]:
    """The ``NAME=value`` prefixes of a command's words (``PRT_TORCH_KERNEL_ISA=avx2 prt bench``)."""
    n = len(words) - len(_drop_env(words))
    return dict(w.split("=", 1) for w in words[:n])


def _drop_env(words: list[str]) -> list[str]:
    i = 0
    while i < len(words) and ENV_PREFIX.match(words[i]):
        i += 1
    return words[i:]


def _is_project_command(words: list[str]) -> bool:
    return bool(words) and (words[0] in PRT or words[0].startswith("scripts/")
                            or words[0] in PYTHON and len(words) > 1 and words[1].startswith(("benchmarks/", "scripts/")))


def _is_synopsis(words: list[str]) -> bool:
    return any(w.startswith("[") or w == "..." or ("|" in w and "=" not in w) for w in words[1:])


def documented() -> list[Command]:
    """Every command of the guides (see the module docstring), in the order written."""
    out: list[Command] = []
    for guide in GUIDES:
        lines = (ROOT / guide).read_text().splitlines()
        lang = None  # inside a fence: its language ("" unlabelled)
        pending = ""  # a continued shell line
        start = 0
        for no, line in enumerate(lines, 1):
            m = FENCE.match(line)
            if m:
                lang = m.group(1) if lang is None else None
                continue
            if lang is None:
                for s in INLINE.finditer(line):
                    try:
                        words = _drop_env(shlex.split(s.group(1)))
                    except ValueError:  # an unbalanced quote in a fragment
                        words = _drop_env(s.group(1).split())
                    if words and not any(w.startswith("<") for w in words[:2]):
                        out.append(Command(f"{guide}:{no}", words, kind="inline", guide=guide))
                continue
            if lang not in ("bash", "sh", "shell", ""):
                continue
            text = line.strip()
            if not pending:
                start = no
            if text.endswith("\\"):
                pending += text[:-1] + " "
                continue
            text, pending = pending + text, ""
            if text.startswith("[") and out and out[-1].kind == "synopsis" and out[-1].where.startswith(guide + ":"):
                out[-1].words += text.split()  # an indented [...] line continues the synopsis above it
                continue
            cmd, comment = _split_comment(text)
            if not cmd:
                continue
            try:
                parts = _commands_of(cmd)
            except ValueError:  # unbalanced quotes: ASCII art in an unlabelled block
                continue
            for env, words in parts:
                if not words or not lang and not _is_project_command(words):  # an unlabelled block's other text
                    continue
                kind = "foreign" if not _is_project_command(words) else "synopsis" if _is_synopsis(words) else "line"
                out.append(Command(f"{guide}:{start}", words, comment, kind, guide, env))
    return out


COMMANDS = documented()
PRT_LINES = [c for c in COMMANDS if c.words[0] in PRT and c.kind == "line"]
PRT_OTHER = [c for c in COMMANDS if c.words[0] in PRT and c.kind != "line"]


def _parser():
    p = build_parser()
    return p, p._subparsers._group_actions[0].choices  # noqa: SLF001 (argparse has no public accessor)


PARSER, SUBS = _parser()


def _try_parse(c: Command):
    """``(namespace, None)``, or ``(None, argparse's error line)``; ``--help`` parses as nothing to check."""
    if {"-h", "--help"} & set(c.words):
        return None, None
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            return parse_args(PARSER, c.words[1:]), None
    except SystemExit:
        return None, (err.getvalue().strip().splitlines() or ["(no message)"])[-1]


PARSED = {id(c): _try_parse(c)[0] for c in PRT_LINES}  # what the chain test reads (a line that fails is reported once)


def _parse(c: Command):
    a, err = _try_parse(c)
    if a is None:
        pytest.fail(f"{c.where}: {' '.join(c.words)}: {err}")
    return a


def _is_users_file(value: str) -> bool:
    """A file the user supplies (a suffix or a directory in it), or a placeholder in capitals (``MESH``, ``FILE``)."""
    return "/" in value or Path(value).suffix != "" or value.replace("_", "").isupper()


@functools.cache
def _config_problem(name: str, overrides: tuple[str, ...]) -> str | None:
    """The shipped config loaded with the overrides and validated (``harness.config.load_config``: no work)."""
    from prt_torch.harness.config import load_config

    try:
        load_config(name, list(overrides))
    except (ValueError, FileNotFoundError) as e:
        return str(e)
    return None


def _scene_problem(value: str) -> str | None:
    """A mesh a guide names, by the commands' one rule (``prt_torch.scene.check_scene``: no mesh is built)."""
    from prt_torch.scene import check_scene

    if _is_users_file(value):
        return None
    try:
        check_scene(value, param="mesh")
    except (ValueError, FileNotFoundError) as e:
        return str(e)
    return None


def _light_problem(value: str) -> str | None:
    from prt_torch.lighting.builtin import list_builtin_environments
    from prt_torch.lighting.spec import load_light, parse_light_spec

    if value in list_builtin_environments():
        return None
    try:
        if parse_light_spec(value) is not None:
            load_light(value, bands=2)  # an analytic light: closed form, instant
            return None
    except ValueError as e:
        return str(e)
    if _is_users_file(value):
        return None
    return f"light {value!r} is neither a file, a built-in environment ({', '.join(list_builtin_environments())}) " \
           "nor an analytic spec"


def _brdf_problem(value: str) -> str | None:
    from prt_torch import brdf

    key = brdf._ALIASES.get(value.lower(), value.lower())  # noqa: SLF001 (the aliases make_brdf accepts)
    return None if key in brdf.MODELS else f"BRDF {value!r}: accepted {sorted(brdf.MODELS)}"


def _names(c: Command, a) -> list[str]:
    """Problems with the built-in names the parsed command ``a`` uses."""
    from prt_torch import codecs
    from prt_torch.harness.config import builtin_configs

    sub, probs = a.command, []

    def lights(v):
        return [] if v is None else [v] if isinstance(v, str) else list(v)

    if sub == "precompute":
        probs.append(_scene_problem(a.scene))
        if a.k_brdf is not None:
            probs.append(_brdf_problem(a.k_brdf))
        if getattr(a, "k_material", None) is not None:
            from prt_torch.transfer.subsurface import resolve_material
            try:
                resolve_material(a.k_material)
            except ValueError as e:
                probs.append(str(e))
    if sub == "render" and a.method == "shrm" and a.transfer is not None:
        probs.append(_scene_problem(a.transfer))
    if getattr(a, "mesh", None) is not None:
        probs.append(_scene_problem(a.mesh))
    for v in lights(getattr(a, "light", None)):
        probs.append(_light_problem(v))
    if sub == "bench" and a.config is None:
        probs.append(_config_problem("default", tuple(a.overrides or ())))
    if sub == "bench" and a.config is not None:
        cfg = a.config
        if cfg.startswith("configs/") and not (ROOT / cfg).is_file():
            probs.append(f"config {cfg!r}: no such file in the checkout")
        elif not _is_users_file(cfg) and cfg not in builtin_configs():
            probs.append(f"config {cfg!r}: not shipped ({', '.join(builtin_configs())})")
        elif not _is_users_file(cfg) or cfg.startswith("configs/"):
            probs.append(_config_problem(cfg, tuple(a.overrides or ())))
    if sub == "compress" and a.codec is not None and a.codec not in codecs.available():
        probs.append(f"codec {a.codec!r}: accepted {codecs.available()}")
    if sub in ("render", "shrm") and getattr(a, "brdf", None) is not None:
        probs.append(_brdf_problem(a.brdf))
    if sub == "invert":
        from prt_torch.cli.invert import BRDF_TYPES
        if a.brdf is not None and a.brdf not in BRDF_TYPES:
            probs.append(f"prt invert --brdf {a.brdf!r}: accepted {BRDF_TYPES}")
        if a.transfer_brdf is not None:
            probs.append(_brdf_problem(a.transfer_brdf))
    return [p for p in probs if p]


def _inputs(a) -> list[str]:
    """The .prt files the parsed command reads."""
    files = []
    if a.command in ("compress", "relight", "validate") or a.command == "render" and a.method != "shrm":
        files.append(a.transfer)
    if a.command == "info":
        files.append(a.file)
    files.append(getattr(a, "codec_file", None))
    return [f for f in files if f and f.endswith(".prt")]


def _writes(guide_lines: list[tuple[Command, object]]) -> dict[str, str]:
    """output -> where, over the given parsed command lines that write (not --dry-run)."""
    return {a.output: c.where for c, a in guide_lines
            if getattr(a, "output", None) and not getattr(a, "dry_run", False) and not getattr(a, "list", False)}


def test_the_guides_show_commands():
    """The extraction finds what the guides hold (so a format change cannot silently empty this test)."""
    by_kind = {k: [c for c in COMMANDS if c.kind == k] for k in ("line", "synopsis", "inline")}
    assert len(PRT_LINES) >= 90, len(PRT_LINES)
    assert len(by_kind["synopsis"]) >= 5 and len(by_kind["inline"]) >= 100
    assert {c.guide for c in PRT_LINES} >= {"README.md", "docs/wavelet.md", "docs/validate.md", "docs/inverse.md"}
    joined = next(c for c in COMMANDS if c.words[:2] == ["prt", "light"] and c.kind == "synopsis")
    assert "[--irradiance-size" in joined.words  # docs/lighting.md's synopsis over three lines, joined


@pytest.mark.parametrize("c", PRT_LINES, ids=lambda c: c.where)
def test_command_line_parses_and_names_what_exists(c):
    a = _parse(c)
    assert a.command in SUBS, f"{c.where}: no subcommand"
    probs = _names(c, a)
    assert not probs, f"{c.where}: {' '.join(c.words)}: " + "; ".join(probs)


@pytest.mark.parametrize("c", PRT_OTHER, ids=lambda c: f"{c.where}-{c.kind}")
def test_synopsis_and_inline_options_exist(c):
    sub = next((w for w in c.words[1:] if not w.startswith("-")), None)
    assert sub in SUBS, f"{c.where}: `{' '.join(c.words)}`: {sub!r} is no subcommand ({', '.join(SUBS)})"
    known = SUBS[sub]._option_string_actions  # noqa: SLF001
    for w in c.words[1:]:
        m = OPTION.match(w)
        if m and m.group(1) not in known:
            pytest.fail(f"{c.where}: `{' '.join(c.words)}`: prt {sub} has no option {m.group(1)}")
    a, _ = _try_parse(c) if c.kind == "inline" else (None, None)
    if a is None and c.kind == "inline" and not {"-o", "--output"} & set(c.words):  # prose leaves the output out
        a, _ = _try_parse(Command(c.where, [*c.words, "-o", "OUT"], kind="inline"))
    if a is not None:  # an inline span that is a whole command: its names too
        probs = _names(c, a)
        assert not probs, f"{c.where}: `{' '.join(c.words)}`: " + "; ".join(probs)


@pytest.mark.parametrize("guide", GUIDES)
def test_files_are_written_before_they_are_read(guide):
    """In the order written, each .prt a guide's command line reads was written before, and no command line writes
    an output that an earlier one wrote without --overwrite / --resume (see the module docstring)."""
    parsed = {g: [(c, PARSED[id(c)]) for c in PRT_LINES if c.guide == g and PARSED[id(c)] is not None] for g in GUIDES}
    done: list[tuple[Command, object]] = []
    probs = []
    for c, a in parsed[guide]:
        written = _writes(done)
        cited = [f"docs/{m}.md" for m in CITED.findall(c.comment)]
        for f in _inputs(a):
            if f in written or Path(f).stem.isupper():
                continue
            if any(f in _writes(parsed.get(g, [])) for g in cited):
                continue
            probs.append(f"{c.where}: reads {f}, which no earlier command line of {guide} writes")
        out = getattr(a, "output", None)
        if out in written and not (getattr(a, "overwrite", False) or getattr(a, "resume", False)):
            probs.append(f"{c.where}: -o {out} exists (written at {written[out]}): refused without --overwrite")
        done.append((c, a))
    assert not probs, "\n".join(probs)


def test_named_scripts_exist_and_take_the_options_given():
    probs = []
    for guide in GUIDES:
        for name in sorted(set(NAMED_SCRIPT.findall((ROOT / guide).read_text()))):
            if not (ROOT / name).is_file():
                probs.append(f"{guide}: names {name}, which does not exist")
    for c in COMMANDS:
        script = c.words[0] if c.words[0].startswith("scripts/") else c.words[1] if c.words[0] in PYTHON else None
        if script is None or not (ROOT / script).is_file():
            continue
        src = (ROOT / script).read_text()
        for w in c.words:
            m = OPTION.match(w)
            if m and f'"{m.group(1)}"' not in src:
                probs.append(f"{c.where}: {script} has no option {m.group(1)}")
    assert not probs, "\n".join(probs)


def test_documented_environment_variables_are_read():
    """Each ``PRT_*`` environment variable a guide names (``PRT_TORCH_KERNEL_ISA=avx2 prt bench``, ``PRT_TORCH_NATIVE=0``)
    is read somewhere in the project: the package (Python or C), the tests, the benchmarks or the scripts."""
    sources = "".join(p.read_text(errors="replace") for top in ("prt_torch", "tests", "benchmarks", "scripts")
                      for p in sorted((ROOT / top).rglob("*")) if p.suffix in (".py", ".c", ".h", "")
                      and p.is_file() and p.name != Path(__file__).name)
    named = {v for g in GUIDES for v in re.findall(r"\bPRT_[A-Z0-9_]+", (ROOT / g).read_text())}
    assert len(named) >= 5, named
    read = set(re.findall(r"\bPRT_[A-Z0-9_]+", sources))
    assert not sorted(named - read), "named by a guide, read nowhere"


def _python_blocks():
    """``(guide:line, code)`` of every ```python block of the guides (an indented block dedented)."""
    for guide in GUIDES:
        text = (ROOT / guide).read_text()
        for m in re.finditer(r"^([ \t]*)```python\n(.*?)^[ \t]*```", text, re.S | re.M):
            line = text.count("\n", 0, m.start()) + 1
            yield f"{guide}:{line}", "\n".join(ln[len(m.group(1)):] for ln in m.group(2).splitlines())


def test_python_snippets_name_what_exists():
    """Each ```python block of the guides compiles, every name it imports from prt_torch exists (an attribute or a
    submodule), and every attribute it reads from an imported prt_torch module (``codecs.get``, ``relight.
    WaveletRelighter``, ``io.load_mmap``) exists. Names only: the snippets assume inputs (``X``, ``light``, ``mesh``) and
    are run by hand (docs/codecs.md's pipeline examples are run whole by tests/test_codecs.py and
    tests/test_sklearn_api.py)."""
    import ast
    import importlib

    def exists(module: str, name: str) -> bool:
        mod = importlib.import_module(module)
        if hasattr(mod, name):
            return True
        try:
            importlib.import_module(f"{module}.{name}")
        except ModuleNotFoundError:
            return False
        return True

    blocks = list(_python_blocks())
    assert len(blocks) >= 10
    probs = []
    for where, code in blocks:
        tree = ast.parse(code, where)
        modules = {}  # local name -> module path, for names bound to prt_torch modules
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "prt_torch":
                for a in node.names:
                    if not exists(node.module, a.name):
                        probs.append(f"{where}: from {node.module} import {a.name}: no such name")
                    elif isinstance(getattr(importlib.import_module(node.module), a.name, None), type(importlib)) \
                            or not hasattr(importlib.import_module(node.module), a.name):
                        modules[a.asname or a.name] = f"{node.module}.{a.name}"
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules:
                if not exists(modules[node.value.id], node.attr):
                    probs.append(f"{where}: {node.value.id}.{node.attr}: {modules[node.value.id]} has no {node.attr}")
    assert not probs, "\n".join(probs)


def test_named_ablation_configs_are_shipped():
    """Each ``ablations/NAME`` a guide names (the README's table, ``prt bench ablations/<bands, samples, ...>``) is a
    config shipped with the package, and docs/harness.md's list of the shipped ones is complete."""
    from prt_torch.harness.config import builtin_configs

    shipped = {c for c in builtin_configs() if c.startswith("ablations/")}
    named = set()
    for guide in GUIDES:
        text = (ROOT / guide).read_text()
        named |= {f"ablations/{n}" for n in re.findall(r"ablations/(\w+)", text)}
        for group in re.findall(r"ablations/<(\w+(?:, \w+)+)>", text):  # a list; ablations/<name> is a placeholder
            named |= {f"ablations/{n.strip()}" for n in group.split(",")}
    assert len(named) >= 8 and not sorted(named - shipped), sorted(named - shipped)
    listed = re.search(r"Shipped: `prt bench ablations/<([\w, ]+)>`", (ROOT / "docs/harness.md").read_text()).group(1)
    assert {f"ablations/{n.strip()}" for n in listed.split(",")} == shipped
