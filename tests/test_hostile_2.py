"""Hostile input, second pass (issue 36): every shipped config passes its own dry run, options
may come between the config and its overrides, a warning on the command line is one line, and a
long run ends cleanly on SIGINT (to the process group, as Ctrl-C sends it), SIGTERM (what
``timeout``, schedulers and ``kill`` send) and SIGKILL, of the main process or of a ray-casting
worker: the exit status, one line naming what happened and how to continue, no traceback, no
output file half-written, no worker left behind."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from prt_torch.cli import main as cli_main
from prt_torch.harness.config import builtin_configs

PRT = [sys.executable, "-m", "prt_torch"]


@pytest.mark.parametrize("name", builtin_configs())
def test_every_shipped_config_passes_its_own_dry_run(name, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli_main(["bench", name, "--dry-run"]) == 0, capsys.readouterr().err
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
