"""The command line's compile cache: where it goes, how it is turned off, a bad folder, a hit."""

import os
import subprocess
import sys

from coopjax import cli
from coopjax.cli import cache


def test_the_folder_follows_xdg_and_the_users_settings(tmp_path):
    assert cache.location({"XDG_CACHE_HOME": str(tmp_path)}) == (str(tmp_path / "coopjax" / "xla"), False)
    assert cache.location({cache.ENV: str(tmp_path)}) == (str(tmp_path), True)
    assert cache.location({cache.ENV: ""}) == (None, True)  # off
    # JAX's own setting wins: we leave its cache alone.
    assert cache.location({"JAX_COMPILATION_CACHE_DIR": "/x", cache.ENV: str(tmp_path)}) == (None, True)
    assert "off" in cache.describe({cache.ENV: ""})


def test_a_folder_that_cannot_hold_the_cache_is_one_line_and_exit_2(fresh_dir, capsys, monkeypatch):
    open("a-file", "w").close()
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv(cache.ENV, "a-file")
    assert cli.main(["params"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1
    assert "COOPJAX_CACHE=a-file" in captured.err and "not a folder" in captured.err
    assert os.listdir(fresh_dir) == ["a-file"]


def test_a_second_run_loads_what_the_first_compiled(tmp_path):
    """In real processes (JAX reads its cache settings once per process): the first run fills this
    machine's subfolder, and the same run again finds every program there and adds nothing."""
    folder = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"} | {cache.ENV: str(folder)}
    command = [sys.executable, "-m", "coopjax.cli", "simulate", "--scenario", "paper", "--out", str(tmp_path / "r.csv")]
    runs = []
    for _ in range(2):
        subprocess.run(command, env=env, check=True, capture_output=True)
        runs.append(
            sorted(os.path.relpath(os.path.join(d, f), folder) for d, _, files in os.walk(folder) for f in files)
        )
    assert runs[0], "nothing was cached"
    assert {os.path.dirname(f) for f in runs[0]} == {cache.machine_tag()}  # one subfolder, this machine's
    assert runs[1] == runs[0]
