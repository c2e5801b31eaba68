"""The README's benchmark figures come from the committed baseline (scripts/readme_baseline.py),
and its test command is what CI runs."""
import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("readme_baseline", ROOT / "scripts" / "readme_baseline.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_figures_are_generated_from_the_baseline_results():
    mod = _script()
    res = json.loads((ROOT / "reports" / "baseline" / "results.json").read_text())
    readme = (ROOT / "README.md").read_text()
    assert mod.render_readme(readme, res) == readme, "run scripts/readme_baseline.py"
    best = max((r for r in res["records"] if r["codec"] == "cpca"), key=lambda r: r["bytes_per_vertex"] * (r["bytes_per_vertex"] < 100))
    assert f"{best['psnr_lights_db']:.1f} dB" in readme


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    blocks = [b.split("```", 1)[0].strip() for b in readme.split("```bash\n")[1:3]]
    ci = (ROOT / ".ci" / "run").read_text()
    assert blocks[1] in ci.splitlines()
