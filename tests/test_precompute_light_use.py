"""``prt precompute --light`` is read only by the 'auto' choices that measure a light (plan 10, issue 39
review): a wavelet transfer's ``--res auto`` and an SH kind's ``--bands auto``. With an explicit
``--res R`` / ``--bands n`` (or a kind with no such choice) the light changed nothing and was accepted
silently; it is now refused in one line, before any work (house style: ``prt relight --selection`` on
an SH transfer, tests/test_wavelet_review.py)."""
from __future__ import annotations

import pytest

from prt_torch.cli import main as cli_main
from prt_torch.lighting import load_light
from prt_torch.transfer import get_kind
from prt_torch.transfer.auto import light_choices

CASES = [("diffuse", {}), ("diffuse", {"bands": 3}), ("diffuse", {"bands": "auto"}),
         ("glossy", {"bands": 3, "bands_out": "auto"}), ("glossy", {"bands": "auto", "bands_out": "auto"}),
         ("mrt", {"bands": 3, "bands_out": "auto", "M": "auto"}), ("wavelet", {}), ("wavelet", {"res": 8}),
         ("wavelet", {"res": "auto"}), ("transport", {}), ("subsurface", {"bands": 3})]


@pytest.mark.parametrize("kind,params", CASES)
def test_light_choices_is_exactly_where_a_light_changes_resolve(kind, params):
    """Independent of :func:`light_choices`' rule: resolve each kind's parameters with a constant light
    (only band 0 / a flat cube: 1 band, R = 1) and without a light (a flat spectrum: 3+ bands; R = 32).
    The decisions differ exactly where :func:`light_choices` says a light is read."""
    k = get_kind(kind)
    p = k.validate(params)
    light = ["constant"] if kind == "wavelet" else [load_light("constant", bands=32)]
    with_light = {n: d["value"] for n, d in k.resolve(p, light)[1].items()}
    without = {n: d["value"] for n, d in k.resolve(p, None)[1].items()}
    used = light_choices(kind, p)
    assert bool(used) == (with_light != without), (with_light, without, used)
    for n in used:
        assert with_light[n] != without[n]


WAVELET4, DIFFUSE2 = ["--kind", "wavelet", "--res", "4", "--terms", "20"], ["--kind", "diffuse", "--bands", "2", "--samples", "16"]


@pytest.mark.parametrize("option,argv,flag", [
    (["--light", "sun"], WAVELET4, "with --res 4: --kind wavelet reads the lights only to choose --res auto"),
    (["--light", "sun"], ["--kind", "wavelet", "--terms", "20"], "with the default --res 32"),
    (["--light", "sun"], DIFFUSE2, "with --bands 2: --kind diffuse reads the lights only to choose --bands auto"),
    (["--light", "sun"], ["--kind", "transport"], "on --kind transport: no 'auto' choice of this kind reads a light"),
    (["--energy", "0.9"], WAVELET4, "no effect: no 'auto' choice in this run; accepted: --res auto"),
    (["--energy", "0.9"], DIFFUSE2, "accepted: --bands auto with --energy"),
    (["--energy", "0.9"], ["--kind", "transport"], "on --kind transport: no 'auto' choice of this kind keeps a fraction"),
])
def test_precompute_refuses_an_option_nothing_reads(tmp_path, capsys, option, argv, flag):
    """One line (status 2) naming the option, its value and what would read it; nothing written."""
    out = tmp_path / "t.prt"
    capsys.readouterr()
    assert cli_main(["precompute", "occluder_over_plane", *argv, *option, "--workers", "1", "--no-progress",
                     "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    shown = f"{option[0]} 'sun'" if option[0] == "--light" else f"{option[0]} {option[1]}"
    assert len(err) == 1 and f"{shown} has no effect" in err[0] and flag in err[0] and "accepted:" in err[0], err
    assert not out.exists() and not (tmp_path / "t.prt.state").exists()


def test_precompute_light_with_auto_still_runs(tmp_path, capsys):
    """The lights a choice reads are still taken: ``--res auto --light constant`` chooses R = 1 (a flat
    light has no Haar detail), as without the refusal."""
    out = tmp_path / "w.prt"
    capsys.readouterr()
    assert cli_main(["precompute", "occluder_over_plane", "--kind", "wavelet", "--res", "auto", "--light", "constant",
                     "--workers", "1", "--no-progress", "--dry-run", "-o", str(out)]) == 0
    assert "res=1" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("kind,params", CASES)
def test_energy_choices_cover_every_decision_energy_changes(kind, params):
    """``--energy`` (the fraction an 'auto' choice keeps) was silently ignored without an 'auto' choice too. Where
    :func:`energy_choices` is empty, resolving with energy 0.5 and 0.9999 gives the same decisions; where it lists
    the choices, those are the decisions made (a different energy may or may not move them)."""
    from prt_torch.transfer.auto import energy_choices

    k = get_kind(kind)
    lo, hi = ({n: d["value"] for n, d in k.resolve(k.validate({**params, "energy": e}), None)[1].items()}
              for e in (0.5, 0.9999))
    used = energy_choices(kind, k.validate(params))
    if not used:
        assert lo == hi, (lo, hi)
    assert set(used) <= set(hi), (used, hi)


CONFIG = """name: t
scene: {{name: occluder_over_plane, size: small}}
transfer: {transfer}
lights: [sky]
codecs: {codecs}
"""


@pytest.mark.parametrize("transfer,codecs,refused", [
    ("{type: diffuse, bands: 3, samples: 16, energy: 0.9}", "[{type: pca, vectors: 2}]",
     "with transfer.bands = 3: no 'auto' choice in this run keeps it; accepted: transfer.bands: auto with transfer.energy"),
    ("{type: wavelet, terms: 20, energy: 0.9}", "[]", "with the default transfer.res = 32"),
    ("{type: wavelet, res: 8, terms: 20, energy: 0.9}", "[]", "with transfer.res = 8"),
    ("{type: mrt, bands: 3, bands_out: 3, M: 4, samples: 16, energy: 0.9}", "[{type: pca, vectors: 2}]",
     "accepted: transfer.bands: auto / transfer.bands_out: auto / transfer.M: auto with transfer.energy"),
    ("{type: diffuse, bands: auto, samples: 16, energy: 0.9}", "[{type: pca, vectors: 2}]", None),
    ("{type: diffuse, bands: [3, auto], samples: 16, energy: 0.9}", "[{type: pca, vectors: 2}]", None),  # auto reads it
    ("{type: wavelet, res: auto, terms: 20, energy: 0.9}", "[]", None),
])
def test_bench_config_refuses_energy_nothing_keeps(tmp_path, capsys, transfer, codecs, refused):
    """A config's ``transfer.energy`` was silently accepted where ``prt precompute --energy`` is refused (no 'auto'
    choice keeps it): now the same refusal, one line (status 2) naming the config file, the key and its value. Which
    runs read it is checked independently above (resolve() at two energies); a sweep with one 'auto' point reads it."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(CONFIG.format(transfer=transfer, codecs=codecs))
    capsys.readouterr()
    rc = cli_main(["bench", str(cfg), f"output_dir={tmp_path / 'rep'}", f"cache_dir={tmp_path / 'cache'}", "--dry-run",
                   "--no-time"])
    err = capsys.readouterr().err.strip().splitlines()
    if refused is None:
        assert rc == 0, err
        return
    assert rc == 2 and len(err) == 1, err
    assert f"config {str(cfg)!r}: key 'transfer.energy' = 0.9 has no effect" in err[0] and refused in err[0], err


def test_energy_dropped_where_a_sweep_point_does_not_keep_it():
    """``bands: [3, auto]`` with ``energy``: the bands-3 point's transfer is the one without ``energy`` (one cache
    entry), the auto point keeps it."""
    from prt_torch.harness.run import transfer_params

    base = {"seed": 0, "transfer": {"type": "diffuse", "samples": 16, "energy": 0.9}}
    assert "energy" not in transfer_params({**base, "transfer": {**base["transfer"], "bands": 3}})
    assert transfer_params({**base, "transfer": {**base["transfer"], "bands": "auto"}})["energy"] == 0.9
