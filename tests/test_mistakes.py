"""Every mistake a user can make, per command: one line on stderr naming the problem, exit code 2,
no traceback, and the folder exactly as it was (no output, no OUT.parts/, no temporary file).

One table, run in-process through `coopjax.cli.main`. Each case may first write input files
(`setup`); the folder is compared, names and contents, before and after."""

import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import coopjax as cj
from coopjax import cli, io, sweeps

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMALL = ["--scenario", "paper", "--T", "0.05", "--devices", "1", "--quiet"]
VARY = ["--vary", "M_b=uniform:1:2", "--n", "4"]
SWEEP_TABLE = "sample,M_b,min_grip,finite\n0,1.0,nan,0\n1,2.0,nan,0\n"

# (id, setup: {file: text, or None for a folder}, argv, env, a fragment the one line must contain)
CASES = [
    # 1. A sweep that varies nothing.
    ("sweep-nothing-varies", {}, ["sweep", *SMALL, "--n", "8"], {}, "nothing varies"),
    ("sweep-nothing-varies-set", {}, ["sweep", *SMALL, "--n", "8", "--set", "K_GP=0.3"], {}, "nothing varies"),
    # 2. Output paths, before any work.
    ("sweep-out-folder", {"s.csv": None}, ["sweep", *SMALL, *VARY, "--out", "s.csv"], {}, "is a folder"),
    ("sweep-out-missing-folder", {}, ["sweep", *SMALL, *VARY, "--out", "no/s.csv"], {}, "does not exist"),
    ("sweep-out-extension", {}, ["sweep", *SMALL, *VARY, "--out", "s.txt"], {}, "must end in one of"),
    ("simulate-out-folder", {"run.csv": None}, ["simulate", "--out", "run.csv"], {}, "is a folder"),
    ("simulate-plot-folder", {"f.png": None}, ["simulate", "--plot", "f.png"], {}, "is a folder"),
    ("simulate-plot-empty", {}, ["simulate", "--plot", ""], {}, "must end in one of"),
    ("simulate-plot-extension", {}, ["simulate", "--plot", "f.txt"], {}, "must end in one of"),
    ("plot-sweep-out-folder", {"t.csv": SWEEP_TABLE, "p.png": None}, ["plot-sweep", "t.csv", "--out", "p.png"], {},
     "is a folder"),
    ("tune-history-folder", {"t_history.png": None}, ["tune", "--steps", "1", "--out", "t.json"], {}, "is a folder"),
    ("tune-traces-folder", {"t_traces.png": None}, ["tune", "--steps", "1", "--out", "t.json"], {}, "is a folder"),
    ("tune-out-extension", {}, ["tune", "--out", "t.txt"], {}, "must end in one of"),
    ("analyze-out-missing-folder", {}, ["analyze", "--out", "no/a"], {}, "does not exist"),
    # 4. Values refused before OUT.parts/ exists.
    ("sweep-set-unknown", {}, ["sweep", *SMALL, *VARY, "--set", "K_XX=1"], {}, "unknown parameter 'K_XX'"),
    ("sweep-set-nonpositive", {}, ["sweep", *SMALL, *VARY, "--set", "K_f=0"], {}, "must be positive"),
    ("sweep-set-not-a-number", {}, ["sweep", *SMALL, *VARY, "--set", "G_e=abc"], {}, "is not a number"),
    # 5. Table input.
    ("from-missing", {}, ["sweep", *SMALL, "--from", "t.csv"], {}, "no such file"),
    ("from-empty", {"t.csv": ""}, ["sweep", *SMALL, "--from", "t.csv"], {}, "is empty"),
    ("from-folder", {"t.csv": None}, ["sweep", *SMALL, "--from", "t.csv"], {}, "is a folder"),
    ("from-header-only", {"t.csv": "M_b\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "has no rows"),
    ("from-unknown-column", {"t.csv": "a,b\n1,2\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "unknown parameter 'a'"),
    ("from-ragged", {"t.csv": "M_b,K_GP\n1,2\n3\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "line 3"),
    ("from-not-numbers", {"t.csv": "M_b\n1\nheavy\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "not numbers"),
    ("from-results-only", {"t.csv": "sample,min_grip\n0,1\n"}, ["sweep", *SMALL, "--from", "t.csv"], {},
     "no parameter columns"),
    ("from-negative-mass", {"t.csv": "M_b\n1\n-2\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "at sample 1"),
    ("from-binary", {"t.parquet": "not parquet"}, ["sweep", *SMALL, "--from", "t.parquet"], {}, "not a readable Parquet"),
    ("plot-sweep-empty", {"t.csv": ""}, ["plot-sweep", "t.csv"], {}, "is empty"),
    ("plot-sweep-folder", {"t.csv": None}, ["plot-sweep", "t.csv"], {}, "is a folder"),
    ("plot-sweep-missing", {}, ["plot-sweep", "t.csv"], {}, "no such file"),
    ("plot-sweep-no-column", {"t.csv": "a,b\n1,2\n"}, ["plot-sweep", "t.csv"], {}, "no column 'M_b'"),
    ("plot-sweep-not-a-sweep", {"t.csv": "M_b,min_grip\n1,2\n"}, ["plot-sweep", "t.csv"], {}, "not a sweep table"),
    ("plot-sweep-text-column", {"t.csv": "M_b,min_grip,finite\nx,1,1\n"}, ["plot-sweep", "t.csv"], {}, "not numeric"),
    # 8. Huge numbers: a clear refusal with the limit.
    ("sweep-huge-horizon", {}, ["sweep", "--devices", "1", *VARY, "--T", "1e9"], {}, "at most 2,147,483,647"),
    ("sweep-tiny-step", {}, ["sweep", "--devices", "1", *VARY, "--dt", "1e-12"], {}, "at most 2,147,483,647"),
    ("simulate-huge-steps", {}, ["simulate", "--T", "1e7", "--dt", "1e-6"], {}, "32-bit step counter"),
    ("simulate-huge-every", {}, ["simulate", "--every", "1000000000000"], {}, "more than the run's 3000 steps"),
    ("sweep-huge-n", {}, ["sweep", "--devices", "1", "--vary", "M_b=uniform:1:2", "--n", "1000000000000"], {},
     "more than half of this machine's memory"),
    # 9. Unstable parameters blame the parameters, not the step.
    ("simulate-negative-force-limit", {}, ["simulate", "--set", "F_lim=-5"], {}, "make the loop unstable"),
    ("simulate-negative-gain", {}, ["simulate", "--set", "K_GP=-5"], {}, "make the loop unstable"),
    ("simulate-tiny-mass", {}, ["simulate", "--set", "M_b=1e-30"], {}, "extremely stiff"),
    ("simulate-step-too-large", {}, ["simulate", "--dt", "0.02"], {}, "too large for filippov"),
    # 11. Nothing silently accepted.
    ("sweep-devices-zero", {}, ["sweep", *SMALL[:4], *VARY, "--devices", "0"], {}, "--devices is 0"),
    ("sweep-repeated-vary", {}, ["sweep", *SMALL, *VARY, "--vary", "M_b=uniform:2:3"], {}, "more than once"),
    ("sweep-repeated-set", {}, ["sweep", *SMALL, *VARY, "--set", "G_e=1", "--set", "G_e=2"], {}, "more than once"),
    ("simulate-repeated-set", {}, ["simulate", "--set", "G_e=1", "--set", "G_e=2"], {}, "more than once"),
    ("sweep-env-processes", {}, ["sweep", *SMALL, *VARY], {"COOPJAX_NUM_PROCESSES": "two"}, "not a whole number"),
    ("sweep-distributed-partial", {}, ["sweep", *SMALL, *VARY, "--num-processes", "2"], {}, "go together"),
    ("sweep-process-id-range", {}, ["sweep", *SMALL, *VARY, "--coordinator", "h:1", "--num-processes", "2",
                                    "--process-id", "2"], {}, "between 0 and"),
    ("tune-devices-zero", {}, ["tune", "--devices", "0"], {}, "--devices is 0"),
    ("tune-steps-zero", {}, ["tune", "--steps", "0"], {}, "at least 1"),
    ("tune-repeated-set", {}, ["tune", "--set", "G_e=1", "--set", "G_e=2"], {}, "names a parameter twice"),
    ("analyze-alpha", {}, ["analyze", "--alpha", "1,x"], {}, "comma-separated numbers"),
    ("analyze-robot", {}, ["analyze", "--robot", "Q"], {}, "invalid choice"),
    ("unknown-command", {}, ["orbit"], {}, "invalid choice"),
]


def snapshot(folder):
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = os.path.join(root, name)
            out[os.path.relpath(path, folder)] = None if os.path.isdir(path) else open(path, "rb").read()
    return out


@pytest.mark.parametrize("setup, argv, env, fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_mistake_is_one_line_exit_2_and_leaves_the_folder_as_it_was(fresh_dir, capsys, monkeypatch, setup, argv,
                                                                       env, fragment):
    for name, text in setup.items():
        os.mkdir(name) if text is None else open(name, "w").write(text)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    before = snapshot(fresh_dir)
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert fragment in err, err
    assert snapshot(fresh_dir) == before


def test_the_table_covers_every_command():
    commands = {c[2][0] for c in CASES}
    assert {"simulate", "sweep", "plot-sweep", "tune", "analyze"} <= commands and len(CASES) >= 50


def test_the_python_api_raises_the_same_value_errors():
    with pytest.raises(ValueError, match="nothing varies"):
        cj.sweep("paper", 8, T=0.05)
    with pytest.raises(ValueError, match="make the loop unstable"):
        cj.simulate(cj.make_params(K_GP=-5.0), "paper")
    with pytest.raises(ValueError, match="32-bit step counter"):
        cj.simulate(cj.make_params(), "paper", T=1e7, dt=1e-6)


def test_a_stale_temporary_file_from_a_killed_write_is_gone_after_the_next_success(fresh_dir):
    # What a kill -9 between writing and renaming leaves: the target's temporary file.
    stale = fresh_dir / ".s.csv.tmp-abcd1234.csv"
    stale.write_text("half a table")
    other = fresh_dir / ".other.csv.tmp-zz.csv"  # another target's file is not ours to remove
    other.write_text("x")
    io.write_csv("s.csv", {"a": np.arange(3.0)})
    assert not stale.exists() and other.exists()
    # A write that fails leaves nothing, and the old file stays whole.
    with pytest.raises(RuntimeError):
        with io.atomic_path("s.csv") as tmp:
            open(tmp, "w").write("partial")
            raise RuntimeError
    assert sorted(os.listdir(fresh_dir)) == [".other.csv.tmp-zz.csv", "s.csv"]
    assert io.read_csv("s.csv")["a"].tolist() == [0.0, 1.0, 2.0]


def test_kill_9_during_the_final_write_then_resume_leaves_no_temporary_file(tmp_path):
    """A real kill -9 while the table is being written (a hook sleeps inside the write), then --resume."""
    args = [sys.executable, "-c",
            "import time, coopjax.io as io, sys; real = io.write_csv\n"
            "def slow(path, columns):\n"
            "    with io.atomic_path(path) as tmp:\n"
            "        open(tmp, 'w').write('partial'); print('writing', flush=True); time.sleep(60)\n"
            "io.write_csv = slow\n"
            "import coopjax.sweeps as s; s.write_csv = slow\n"
            "from coopjax.cli import main; sys.exit(main(sys.argv[1:]))",
            "sweep", *SMALL, *VARY, "--chunk", "2", "--out", "s.csv"]
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("writing"):
            break
    proc.kill()
    proc.wait()
    assert any(n.startswith(".s.csv.tmp-") for n in os.listdir(tmp_path))
    done = subprocess.run([sys.executable, "-m", "coopjax.cli", "sweep", *SMALL, *VARY, "--chunk", "2", "--out", "s.csv",
                           "--resume"], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert sorted(os.listdir(tmp_path)) == ["s.csv"]


def test_ctrl_c_is_one_line_that_says_how_to_resume(tmp_path):
    # The carry scenario's 4 s on 256 samples per chunk: about half a second per chunk, 32 chunks.
    # pytest-xdist's workers ignore SIGINT and a child inherits that, so the child restores Python's handler.
    args = [sys.executable, "-c", "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from coopjax.cli import main; sys.exit(main(sys.argv[1:]))",
            "sweep", "--devices", "1", "--vary", "M_b=uniform:1:2", "--n", "256", "--chunk", "8", "--out", "s.csv"]
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    parts = tmp_path / "s.csv.parts"
    deadline = time.time() + 120
    while time.time() < deadline and not any(p.name.startswith("chunk-") for p in parts.glob("*")):
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    lines = [ln for ln in err.splitlines() if ln.strip() and "sweep [" not in ln]
    assert len(lines) == 1 and "--resume" in lines[0] and "Traceback" not in err, err


def test_csv_and_parquet_of_one_sweep_are_equal(fresh_dir):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    spec = sweeps.make_spec("paper", 6, {"K_GP": "choice:0.5,30,-3", "M_b": "loguniform:0.5:5"}, T=0.3, seed=2,
                            integrator="rk4", dt=2e-3)
    table = sweeps.run(spec, chunk=6)
    assert len(set(table["status"])) >= 2  # strings and numbers both round-trip
    sweeps.write_table("s.csv", table)
    sweeps.write_table("s.PARQUET", table)  # the extension in any case
    assert open("s.PARQUET", "rb").read(4) == b"PAR1"
    csv, parquet = sweeps.read_table("s.csv"), sweeps.read_table("s.PARQUET")
    assert list(csv) == list(parquet) == list(table)
    for name in table:
        if table[name].dtype.kind in "fb":
            np.testing.assert_array_equal(csv[name], np.asarray(parquet[name], np.float64), err_msg=name)
            np.testing.assert_array_equal(csv[name], np.asarray(table[name], np.float64), err_msg=name)
        else:
            assert csv[name].tolist() == parquet[name].tolist() == table[name].tolist()
    assert pd.read_csv("s.csv")["peak_grip"].equals(pd.read_parquet("s.PARQUET")["peak_grip"])


def test_blown_up_and_unstable_samples_are_flagged_and_their_neighbours_stay_exact():
    """Paper scenario at dt = 3 ms: K_GP = 10 puts the step beyond the linearised limit (its run stays
    finite but means nothing), K_GP = 100 does too and blows up, K_GP = -3 makes the loop itself
    unstable. Table 1 (K_GP = 0.5) is fine, and its rows equal a single run."""
    spec = sweeps.make_spec("paper", 8, {"K_GP": "choice:0.5,10,-3,100"}, T=1.0, seed=0, integrator="rk4", dt=3e-3)
    table = sweeps.run(spec, chunk=8)
    expect = {0.5: "ok", 10.0: "step_beyond_limit", -3.0: "unstable_loop", 100.0: "step_beyond_limit"}
    for k, status in zip(table["K_GP"], table["status"]):
        assert status == expect[k], (k, status)
    assert set(table["K_GP"]) == set(expect)
    blew_up = np.isfinite(table["t_diverged"])
    assert blew_up[table["K_GP"] == 100].all() and not blew_up[np.isin(table["K_GP"], [0.5, 10])].any()
    assert (table["finite"] == (table["status"] == "ok")).all()
    beyond = table["status"] == "step_beyond_limit"
    assert (table["dt_limit"][beyond] < 3e-3).all() and (table["dt_limit"][table["status"] == "ok"] >= 3e-3).all()
    single = cj.simulate(cj.make_params(K_GP=0.5), "paper", T=1.0, integrator="rk4", dt=3e-3).metrics
    ok = table["status"] == "ok"
    np.testing.assert_allclose(table["peak_grip"][ok], float(single.peak_grip), rtol=1e-12)


def test_help_and_readme_agree():
    """Every flag in `coopjax COMMAND --help` is in the README's synopsis for that command, and back."""
    readme = open(os.path.join(ROOT, "README.md")).read()
    block = readme.split("## Command line", 1)[1].split("```", 2)[1]
    synopsis = {}
    command = None
    for line in block.splitlines():
        m = re.match(r"coopjax ([a-z-]+)", line.strip())
        if m:
            command = m.group(1)
        if command:
            synopsis.setdefault(command, set()).update(re.findall(r"(--[A-Za-z0-9-]+)", line))
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(synopsis) == set(sub.choices)
    for name, p in sub.choices.items():
        flags = {s for a in p._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
        assert flags == synopsis[name], (name, flags ^ synopsis[name])
    # The defaults the README quotes in `[--flag VALUE]` form are the parser's.
    for name, p in sub.choices.items():
        for a in p._actions:
            for s in a.option_strings:
                m = re.search(re.escape(s) + r" ([0-9][0-9.e-]*)\]", block)
                if m and isinstance(a.default, (int, float)) and not isinstance(a.default, bool):
                    assert float(m.group(1)) == float(a.default), (name, s, m.group(1), a.default)
