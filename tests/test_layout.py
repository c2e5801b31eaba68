"""The checkout's layout the project card names: ``configs/`` at the top level, beside
``prt_torch/``, ``benchmarks/``, ``tests/`` and ``reports/``, is the package's shipped configs (one set
of files: an installed user gets them from the wheel, a checkout user finds them where the README
says), so ``prt bench configs/default.yaml`` and ``prt bench default`` run the same config."""
from pathlib import Path

import pytest

from prt_torch.harness.config import builtin_configs, load_config

ROOT = Path(__file__).resolve().parents[1]
PACKAGED = ROOT / "prt_torch" / "configs"


@pytest.mark.skipif(not (ROOT / "configs").exists(), reason="not a checkout (an installed package has no top-level configs/)")
def test_top_level_configs_are_the_packaged_files():
    top = ROOT / "configs"
    assert top.resolve() == PACKAGED.resolve()  # the same directory, not a copy that could drift
    names = sorted(p.relative_to(PACKAGED).as_posix() for p in PACKAGED.rglob("*.yaml"))
    assert names == sorted(p.relative_to(top).as_posix() for p in top.rglob("*.yaml"))
    assert [f"{n[:-5]}" for n in names] == builtin_configs()


@pytest.mark.skipif(not (ROOT / "configs").exists(), reason="not a checkout")
@pytest.mark.parametrize("name", ["default", "glossy", "ablations/bands"])
def test_a_config_by_name_and_by_its_top_level_path_load_the_same(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    by_name, by_path = load_config(name), load_config(f"configs/{name}.yaml")
    assert Path(by_path.pop("_source")).resolve() == Path(by_name.pop("_source")).resolve()
    assert by_name == by_path
