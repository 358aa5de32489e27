"""The command line's compile cache: where it goes, how it is turned off, a bad folder, a hit."""

import os
import shutil
import subprocess
import sys

import pytest

import coopjax as cj
from coopjax import cli
from coopjax import cache


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


@pytest.mark.slow  # CI's time (25 s): the cache in real processes is checked below, in 13 s
def test_a_second_run_loads_what_the_first_compiled(tmp_path):
    """In real processes (JAX reads its cache settings once per process): the first run fills this
    machine's subfolder; damaged entries are dropped and compiled afresh; a copy of the folder at
    another path serves the same run without compiling anything anew."""
    folder = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"} | {cache.ENV: str(folder)}
    command = [sys.executable, "-m", "coopjax.cli", "simulate", "--scenario", "paper", "--out", str(tmp_path / "r.csv")]
    listing = lambda top: sorted(
        os.path.relpath(os.path.join(d, f), top) for d, _, files in os.walk(top) for f in files
    )
    subprocess.run(command, env=env, check=True, capture_output=True)
    filled = listing(folder)
    assert filled, "nothing was cached"
    assert {os.path.dirname(f) for f in filled} == {cache.machine_tag()}  # one subfolder, this machine's

    # Damage: two entries' contents swapped (each key holding the other program, the case that made
    # XLA abort). The next run drops them before JAX reads anything, compiles those programs afresh,
    # says nothing, and gives the same table. (Truncated and random entries: the test below.)
    sub = folder / cache.machine_tag()
    entries = sorted(p for p in sub.iterdir() if p.name.endswith(cache.SUFFIX))[:2]
    first = (tmp_path / "r.csv").read_bytes()
    a, b = entries[0].read_bytes(), entries[1].read_bytes()
    for damage in ((b, a),):
        for path, content in zip(entries, damage):
            path.write_bytes(content)
        done = subprocess.run(command, env=env, capture_output=True, text=True)
        assert done.returncode == 0 and done.stderr == "", done.stderr[-2000:]
        assert (tmp_path / "r.csv").read_bytes() == first
        # Compiled and written again (the entry holds its compile time, so not byte for byte the same).
        assert all(p.exists() and p.read_bytes() != d for p, d in zip(entries, damage))
        assert cache.verify(str(sub)) == []  # and recorded: every entry is what its name says

    # The same run again, from a copy of the folder at another path: it finds every program there
    # (nothing dropped, nothing added).
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    done = subprocess.run(command, env=env | {cache.ENV: str(copy)}, capture_output=True, text=True)
    assert done.returncode == 0
    assert listing(copy) == filled


def test_verify_keeps_recorded_entries_and_drops_every_other(tmp_path):
    names = ["good", "swapped_a", "swapped_b", "truncated", "random", "emptied"]
    entries = {n: tmp_path / f"{n}{cache.SUFFIX}" for n in names}
    for n, path in entries.items():
        path.write_bytes(f"program {n} ".encode() * 100)
    (tmp_path / f"swapped_a{cache.ATIME}").write_bytes(b"0")
    cache.record(str(tmp_path))
    a, b = entries["swapped_a"].read_bytes(), entries["swapped_b"].read_bytes()
    entries["swapped_a"].write_bytes(b)
    entries["swapped_b"].write_bytes(a)
    entries["truncated"].write_bytes(entries["truncated"].read_bytes()[:50])
    entries["random"].write_bytes(os.urandom(len(a)))
    entries["emptied"].write_bytes(b"")
    unknown = tmp_path / f"unknown{cache.SUFFIX}"
    unknown.write_bytes(b"nobody recorded me")
    removed = cache.verify(str(tmp_path))
    assert sorted(removed) == sorted(f"{n}{cache.SUFFIX}" for n in names[1:] + ["unknown"])
    assert entries["good"].exists() and not any(entries[n].exists() for n in names[1:])
    assert not (tmp_path / f"swapped_a{cache.ATIME}").exists()
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


def test_a_python_program_keeps_its_jitted_gradient_with_use_cache(tmp_path):
    """`coopjax.use_cache(folder)` in a script: the first run compiles its `jit(grad(...))` of a run
    (with the traced stability mark, the default under a trace) into the folder; a second run of the
    same script loads it and gives the same bits."""
    script = tmp_path / "script.py"
    script.write_text(
        "import sys, jax, coopjax as cj\n"
        "hits = []\n"
        "jax.monitoring.register_event_listener(lambda e, **k: hits.append(e) if 'cache_hits' in e else None)\n"
        "print(cj.use_cache(sys.argv[1]))\n"
        "loss = lambda k: cj.loss(cj.simulate(cj.make_params(K_GP=k), 'paper', switch='blend', T=0.05).metrics)\n"
        "print(repr(float(jax.jit(jax.grad(loss))(0.5))), len(hits))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    run = lambda: subprocess.run(
        [sys.executable, str(script), str(tmp_path / "cache")], env=env, capture_output=True, text=True, check=True
    ).stdout.split("\n")
    (sub, first, _), (_, second, _) = run(), run()
    assert sub == str(tmp_path / "cache" / cache.machine_tag())
    assert any(p.name.endswith(cache.SUFFIX) for p in (tmp_path / "cache" / cache.machine_tag()).iterdir())
    (slope, hits), (slope_again, hits_again) = first.split(), second.split()
    assert slope == slope_again and int(hits) == 0 and int(hits_again) >= 1


def test_use_cache_refuses_a_folder_it_cannot_use(tmp_path):
    import pytest

    (tmp_path / "a-file").write_text("")
    with pytest.raises(cj.InputError, match=r"use_cache\(.*a-file.*\): cannot keep the compile cache there"):
        cj.use_cache(tmp_path / "a-file")
    with pytest.raises(cj.InputError, match="a folder's path"):
        cj.use_cache(3)
