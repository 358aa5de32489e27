"""The command line's compile cache: where it goes, how it is turned off, a bad folder, a hit."""

import os
import shutil
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
    assert cli.main(["params"]) == 0  # compiles nothing: no cache, no word about it
    assert capsys.readouterr().err == ""
    assert cli.main(["simulate", "--T", "0.05", "--out", "r.csv"]) == 2
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

    # Damage: two entries' contents swapped (each key holding the other program), one truncated, one
    # random. The next run drops them before JAX reads anything, compiles those programs afresh, says
    # nothing, and gives the same table.
    sub = folder / cache.machine_tag()
    entries = sorted(p for p in sub.iterdir() if p.name.endswith(cache.SUFFIX))[:2]
    first = (tmp_path / "r.csv").read_bytes()
    a, b = entries[0].read_bytes(), entries[1].read_bytes()
    for damage in ((b, a),):  # swapped (truncated and random: `test_verify_keeps_recorded...`)
        for path, content in zip(entries, damage):
            path.write_bytes(content)
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
        assert (tmp_path / "r.csv").read_bytes() == first
        # Compiled and written again (the entry holds its compile time, so not byte for byte the same).
        assert all(p.exists() and p.read_bytes() != d for p, d in zip(entries, damage))
        assert cache.verify(str(sub)) == []  # and recorded: every entry is what its name says

    # A copy of the folder elsewhere is used there: nothing is dropped, nothing compiled anew.
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    before = sorted(p.name for p in (copy / cache.machine_tag()).iterdir())
    env_copy = env | {cache.ENV: str(copy)}
    done = subprocess.run(command, env=env_copy, capture_output=True, text=True)
    assert done.returncode == 0
    assert sorted(p.name for p in (copy / cache.machine_tag()).iterdir()) == before


def test_verify_keeps_recorded_entries_and_drops_every_other(tmp_path):
    good, swapped_a, swapped_b, unknown = (tmp_path / f"k{i}{cache.SUFFIX}" for i in range(4))
    for path, text in ((good, b"good"), (swapped_a, b"program A"), (swapped_b, b"program B")):
        path.write_bytes(text)
    (tmp_path / f"k1{cache.ATIME}").write_bytes(b"0")
    cache.record(str(tmp_path))
    swapped_a.write_bytes(b"program B")
    swapped_b.write_bytes(b"program A")
    unknown.write_bytes(b"nobody recorded me")
    removed = cache.verify(str(tmp_path))
    assert sorted(removed) == sorted(p.name for p in (swapped_a, swapped_b, unknown))
    assert good.exists() and not swapped_a.exists() and not (tmp_path / f"k1{cache.ATIME}").exists()
    assert cache.verify(str(tmp_path)) == []


def test_a_literal_tilde_is_the_home_folder(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    assert cache.location({cache.ENV: "~/x"}) == (str(tmp_path / "x"), True)
    assert cache.location({"XDG_CACHE_HOME": "~/c"}) == (str(tmp_path / "c" / "coopjax" / "xla"), False)


def test_a_cache_that_cannot_be_used_is_one_note_at_the_end_and_never_before_an_error(fresh_dir, capsys, monkeypatch):
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.delenv(cache.ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", "")
    monkeypatch.setenv("HOME", "/proc")  # the default folder cannot be made there
    monkeypatch.setattr(cache, "_notes", [])
    assert cli.main(["simulate", "--T", "0.05", "--dt", "5", "--out", "r.csv"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err and "note" not in err, err
    monkeypatch.setattr(cache, "_compiled", [False])
    assert cli.main(["params"]) == 0 and capsys.readouterr().err == ""
    assert cli.main(["simulate", "--T", "0.0513", "--out", "r.csv"]) == 0  # a new T: it compiles
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("coopjax: note: no compile cache"), err
