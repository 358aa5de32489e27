"""What a user meets outside the happy path: Ctrl-C at any moment, a full disk, unusual but common
files, names that overlap, and results that must be standard JSON.

The interrupt test starts real `coopjax` processes and interrupts them at random moments (import,
compile, run, write): a few in CI, many with `-m slow`. The moments start at 1 s: the first tenth of
a second or so (several tenths on a loaded machine) is the Python interpreter's own start, before
coopjax runs and installs its handling.
"""

import concurrent.futures
import errno
import json
import os
import signal
import subprocess
import sys
import time

import jax
import matplotlib.figure
import numpy as np
import pandas as pd
import pytest

import coopjax as cj
from coopjax import cli, io

COMMANDS = {
    "simulate": ["simulate", "--T", "0.5", "--plot", "fig.png"],
    "sweep": [
        "sweep",
        "--scenario",
        "paper",
        "--T",
        "0.3",
        "--n",
        "48",
        "--chunk",
        "4",
        "--vary",
        "M_b=uniform:1:2",
        "--devices",
        "1",
        "--quiet",
        "--out",
        "s.csv",
    ],
    "tune": [
        "tune",
        "--steps",
        "3",
        "--polish",
        "2",
        "--screen",
        "8",
        "--local",
        "2",
        "--starts",
        "2",
        "--train-masses",
        "2",
        "--held-out",
        "2",
        "--validation-draws",
        "8",
        "--params",
        "gains",
        "--quiet",
    ],
    "analyze": ["analyze", "--alpha", "1"],
}
BAR = "it/s]"  # tqdm's progress lines


def _restore_sigint():  # pytest-xdist's workers ignore SIGINT, and a child would inherit that
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt(command, delay, folder):
    """Start `coopjax COMMAND` in `folder`, send SIGINT after `delay` s; returns (code, stderr, seconds to exit)."""
    os.makedirs(folder)
    proc = subprocess.Popen(
        [sys.executable, "-m", "coopjax.cli", *COMMANDS[command]],
        cwd=folder,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_restore_sigint,
    )
    time.sleep(delay)
    sent = time.perf_counter()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err, time.perf_counter() - sent


def check_trial(command, folder, code, err, took):
    files = sorted(os.listdir(folder))
    lines = [ln for ln in err.splitlines() if ln.strip() and BAR not in ln and not ln.startswith("tune (")]
    assert not any(".tmp-" in n for n in files), files  # nothing half-written
    if code == 0:  # it finished before the signal
        return "finished"
    if code == -signal.SIGINT and not err:
        # Killed by the default action, silently: the signal came while the interpreter had no handler
        # of its own, before it installed one (its start took the whole delay, on a loaded machine)
        # or after it removed it at exit, the work done. A shell reports either as status 130 too.
        for name in files:  # what is there is whole
            path = os.path.join(folder, name)
            if name.endswith(".png"):
                assert open(path, "rb").read(8) == b"\x89PNG\r\n\x1a\n", name
            if name.endswith(".json"):
                json.load(open(path))
            if name.endswith(".csv"):
                assert len(pd.read_csv(path)) > 0, name
        return "not started" if not files else "finished"
    assert code == 130, (code, err[-2000:])
    assert took < 10, took  # the watcher acts at once, even inside XLA
    assert len(lines) == 1 and lines[0].startswith("coopjax: interrupted; ") and "Traceback" not in err, (
        command,
        took,
        err[-2000:],
    )
    said = lines[0]
    outputs = [n for n in files if not n.endswith(".parts") and not n.endswith(".ckpt")]
    if "nothing was written" in said or "nothing was kept" in said:
        assert outputs == [] and not any(n.endswith((".parts", ".ckpt")) for n in files), (said, files)
    for name in outputs:  # what was written is whole, and said
        assert name in said, (said, files)
        if name.endswith(".csv"):
            assert len(pd.read_csv(os.path.join(folder, name))) > 0
        if name.endswith(".png"):
            assert open(os.path.join(folder, name), "rb").read(8) == b"\x89PNG\r\n\x1a\n"
        if name.endswith(".json"):
            json.load(open(os.path.join(folder, name)))
    if command == "sweep" and "s.csv.parts" in files:
        chunks = [n for n in os.listdir(os.path.join(folder, "s.csv.parts")) if n.startswith("chunk-")]
        assert f"{len(chunks)} finished chunk" in said and "--resume" in said, (said, chunks)
    if command == "tune" and "tuned.json.ckpt" in files:
        assert "--resume" in said, said
    return "interrupted"


def run_trials(tmp_path, delays):
    jobs = [(command, delay, str(tmp_path / f"{command}-{i}")) for i, (command, delay) in enumerate(delays)]
    with concurrent.futures.ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(lambda job: interrupt(*job), jobs))
    return [check_trial(c, folder, *r) for (c, _, folder), r in zip(jobs, results)]


def test_ctrl_c_at_random_moments_is_one_truthful_line_exit_130_and_nothing_half_written(tmp_path):
    rng = np.random.default_rng(int(time.time()))  # a different moment every run: that is the point
    outcome = run_trials(tmp_path, [(c, float(rng.uniform(1.0, 8.0))) for c in COMMANDS])
    assert outcome.count("interrupted") >= 2, outcome


@pytest.mark.slow
def test_ctrl_c_at_many_random_moments(tmp_path):
    rng = np.random.default_rng(int(time.time()))
    delays = [(c, float(rng.uniform(1.0, 12.0))) for _ in range(10) for c in COMMANDS]
    outcome = run_trials(tmp_path, delays)
    assert outcome.count("interrupted") >= 20, outcome


# ------------------------------------------------------------------------------------------------
# A full disk: one line, exit 1, nothing partial, resumable where that makes sense


def full_disk(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.slow
def test_a_full_disk_leaves_no_partial_output(fresh_dir, capsys, monkeypatch):
    with monkeypatch.context() as patch:
        patch.setattr(pd.DataFrame, "to_csv", full_disk)
        assert cli.main(["simulate", "--T", "0.2", "--out", "run.csv"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no space left on device" in err and "Traceback" not in err, err
    assert os.listdir(fresh_dir) == []
    # The CSV and the plot go together: a plot that cannot be written takes the CSV with it.
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full_disk)
    assert cli.main(["simulate", "--T", "0.2", "--out", "run.csv", "--plot", "fig.png"]) == 1
    assert "no space left" in capsys.readouterr().err
    assert os.listdir(fresh_dir) == []


def test_a_full_disk_in_a_sweep_keeps_the_finished_chunks_and_resume_finishes_it(fresh_dir, capsys, monkeypatch):
    args = [
        "sweep",
        "--scenario",
        "paper",
        "--T",
        "0.2",
        "--n",
        "12",
        "--chunk",
        "4",
        "--vary",
        "M_b=uniform:1:2",
        "--devices",
        "1",
        "--quiet",
        "--out",
        "s.csv",
    ]
    real, calls = np.save, []

    def fills_up(f, data, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            full_disk()
        return real(f, data, *a, **k)

    with monkeypatch.context() as patch:
        patch.setattr(np, "save", fills_up)
        assert cli.main(args) == 1
    err = capsys.readouterr().err
    assert "no space left" in err and "1 finished chunk kept in s.csv.parts" in err and "--resume" in err, err
    assert sorted(os.listdir(fresh_dir)) == ["s.csv.parts"]
    assert not any(".tmp-" in n for n in os.listdir("s.csv.parts"))
    assert cli.main(args + ["--resume"]) == 0
    assert sorted(os.listdir(fresh_dir)) == ["s.csv"]
    assert cli.main(args[:-1] + ["whole.csv"]) == 0
    resumed, whole = io.read_table("s.csv"), io.read_table("whole.csv")
    for name in resumed:
        assert np.array_equal(resumed[name], whole[name]) or np.array_equal(resumed[name], whole[name], equal_nan=True)


@pytest.mark.slow
def test_a_real_full_disk(tmp_path):
    """A 16 KiB tmpfs (needs root): the commands fail with one line and leave no partial output."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16k", "tmpfs", str(disk)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        for args in (
            ["simulate", "--T", "4", "--scenario", "carry", "--every", "1"],
            [
                "sweep",
                "--scenario",
                "paper",
                "--T",
                "0.1",
                "--n",
                "2000",
                "--chunk",
                "500",
                "--vary",
                "M_b=uniform:1:2",
                "--devices",
                "1",
                "--quiet",
                "--out",
                "s.csv",
            ],
        ):
            run = subprocess.run([sys.executable, "-m", "coopjax.cli", *args], cwd=disk, capture_output=True, text=True)
            assert run.returncode == 1 and "no space left on device" in run.stderr, run.stderr[-2000:]
            assert "Traceback" not in run.stderr
            left = [n for n in os.listdir(disk) if not n.endswith(".parts")]
            assert left == [], left
            subprocess.run(["rm", "-rf", *[str(disk / n) for n in os.listdir(disk)]])
    finally:
        subprocess.run(["umount", str(disk)])


# ------------------------------------------------------------------------------------------------
# Files as people have them, names that overlap, standard JSON


def test_tables_as_spreadsheets_write_them_are_read(fresh_dir):
    """A UTF-8 byte-order mark (Excel's "CSV UTF-8"), a field longer than the csv module's default
    limit, and an int64 Parquet column."""
    open("bom.csv", "w", encoding="utf-8-sig").write("M_b,K_GP\n1,0.5\n2,0.6\n")
    assert list(io.read_table("bom.csv")) == ["M_b", "K_GP"]
    open("long.csv", "w").write("M_b,note\n1," + "x" * 200_000 + "\n")
    assert io.read_table("long.csv")["M_b"].tolist() == [1.0]
    pd.DataFrame({"M_b": np.array([1, 2, 3], np.int64)}).to_parquet("ints.parquet")
    table = io.read_table("ints.parquet")
    assert table["M_b"].dtype == np.float64 and table["M_b"].tolist() == [1.0, 2.0, 3.0]
    assert (
        cli.main(
            [
                "sweep",
                "--scenario",
                "paper",
                "--T",
                "0.05",
                "--from",
                "ints.parquet",
                "--devices",
                "1",
                "--quiet",
                "--out",
                "s.csv",
            ]
        )
        == 0
    )


def test_a_per_robot_name_wins_over_the_shared_one_in_any_order(fresh_dir):
    a = cj.make_params(K_GP_L=0.3, K_GP=1.0)
    b = cj.make_params(K_GP=1.0, K_GP_L=0.3)
    assert np.asarray(a.K_GP).tolist() == np.asarray(b.K_GP).tolist() == [0.3, 1.0]
    # In a sweep, a fixed per-robot value holds against a varied shared name.
    base = [
        "sweep",
        "--scenario",
        "paper",
        "--T",
        "0.1",
        "--n",
        "4",
        "--vary",
        "K_GP=uniform:0.2:1",
        "--devices",
        "1",
        "--quiet",
        "--x64",
    ]
    assert cli.main(base + ["--out", "plain.csv"]) == 0
    assert cli.main(base + ["--set", "K_GP_L=5", "--out", "fixed.csv"]) == 0
    plain, fixed = io.read_table("plain.csv"), io.read_table("fixed.csv")
    assert not np.array_equal(plain["peak_grip"], fixed["peak_grip"])
    single = cj.simulate(cj.make_params(K_GP=fixed["K_GP"][0], K_GP_L=5.0), "paper", T=0.1, check_dt=False).metrics
    assert float(single.peak_grip) == pytest.approx(fixed["peak_grip"][0], rel=1e-12)


def test_plot_sweep_draws_a_table_whose_metric_is_nan_everywhere(fresh_dir, capsys):
    pd.DataFrame(
        {"sample": [0, 1], "M_b": [1.0, 2.0], "min_grip": [np.nan, np.nan], "finite": [1, 1], "status": ["ok", "ok"]}
    ).to_csv("t.csv", index=False)
    assert cli.main(["plot-sweep", "t.csv", "--out", "p.png"]) == 0, capsys.readouterr().err
    assert os.path.getsize("p.png") > 10_000


def test_results_are_standard_json_with_null_for_what_is_not_finite(fresh_dir, capsys):
    assert cli.main(["analyze", "--alpha", "1", "--out", "a"]) == 0  # the gain margin is infinite here
    out = capsys.readouterr().out
    text = open("a.json").read()
    strict = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not standard JSON"))
    assert strict["margins"]["gain_margin"] is None and "null" in out


def test_analyze_says_so_when_the_loop_is_unstable(fresh_dir, capsys):
    assert cli.main(["analyze", "--alpha", "1", "--set", "K_GP=-5", "--out", "a"]) == 0
    out = capsys.readouterr().out
    assert "UNSTABLE: a mode grows" in out and "dt <= 0 s" not in out and "nan rad/s" not in out, out


@pytest.mark.slow
def test_simulate_records_what_a_short_or_long_run_can(fresh_dir, capsys):
    assert cli.main(["simulate", "--T", "0.005", "--out", "short.csv"]) == 0  # shorter than the default spacing
    assert len(pd.read_csv("short.csv")) == 6
    assert cli.main(["simulate", "--T", "200", "--dt", "2e-3", "--every", "10000", "--out", "long.csv"]) == 0
    assert len(pd.read_csv("long.csv")) == 11


def test_grad_through_the_hard_switch_under_plain_rk4_warns():
    f = lambda k: cj.simulate(cj.make_params(K_GP=k), "paper", integrator="rk4", T=0.05).metrics.peak_grip
    with pytest.warns(RuntimeWarning, match="integrator='filippov'"):
        jax.eval_shape(jax.grad(f), 0.5)  # the warning is given while tracing: nothing to compile


def _screen(raw: str) -> list[str]:
    """The lines a terminal shows for `raw` (carriage returns overwrite, ESC[K erases the rest)."""
    shown = []
    for line in raw.replace("\r\n", "\n").split("\n"):
        visible = ""
        for piece in line.split("\r"):
            if piece.startswith("\x1b[K"):
                visible = piece[3:]
            else:
                visible = piece + visible[len(piece) :]
        if visible.strip():
            shown.append(visible)
    return shown


def test_ctrl_c_during_a_sweep_with_its_progress_bar_on_a_terminal_is_one_line(tmp_path):
    import fcntl
    import pty
    import struct
    import termios

    command = [arg for arg in COMMANDS["sweep"] if arg != "--quiet"]
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # 100 columns, as a terminal has
    proc = subprocess.Popen(
        [sys.executable, "-m", "coopjax.cli", *command],
        cwd=tmp_path,
        stdin=follower,
        stdout=subprocess.DEVNULL,
        stderr=follower,
        preexec_fn=_restore_sigint,
    )
    os.close(follower)
    raw, deadline = b"", time.time() + 120
    while b"sample" not in raw and time.time() < deadline and proc.poll() is None:  # the bar is drawn
        raw += os.read(leader, 4096)
    assert b"sample" in raw, raw[-500:]
    proc.send_signal(signal.SIGINT)
    while True:
        try:
            chunk = os.read(leader, 4096)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        raw += chunk
    assert proc.wait(timeout=60) == 130
    shown = _screen(raw.decode(errors="replace"))
    assert len(shown) == 1 and shown[0].startswith("coopjax: interrupted; "), shown


def test_a_reader_that_leaves_early_is_not_an_error(tmp_path):
    done = subprocess.run(
        f"{sys.executable} -m coopjax.cli params | head -n 1; exit ${{PIPESTATUS[0]}}",
        shell=True,
        executable="/bin/bash",
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert done.returncode == 0 and done.stderr == "" and done.stdout.startswith("name"), done


def test_an_interrupt_names_only_files_that_are_still_there(fresh_dir, monkeypatch):
    from coopjax.cli import interrupts

    open("kept.csv", "w").close()
    monkeypatch.setattr(interrupts, "_report", [lambda: None])  # no command's own account: the files'
    monkeypatch.setattr(io, "WRITTEN", ["gone.ckpt", "kept.csv"])  # the run wrote, then removed, gone.ckpt
    assert interrupts.account() == "kept.csv was written before it"
    monkeypatch.setattr(io, "WRITTEN", ["gone.ckpt"])
    assert interrupts.account() is None  # "nothing was written"


def test_resume_into_a_parts_folder_it_cannot_write_is_one_line(fresh_dir, capsys, monkeypatch):
    os.mkdir("s.csv.parts")  # empty, and (as another user's, or read-only) not writable
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p).endswith("s.csv.parts") else real(p, mode))
    argv = COMMANDS["sweep"][:]
    argv[argv.index("48")] = "4"
    assert cli.main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "s.csv.parts" in err and "Traceback" not in err, err


def test_a_run_stopped_by_the_users_force_bound_says_so(fresh_dir, capsys):
    assert cli.main(["simulate", "--T", "0.2", "--force-bound", "5", "--out", "r.csv"]) == 1
    err = capsys.readouterr().err
    assert "passed --force-bound 5 N" in err and "smaller --dt" not in err, err


class _Planted:
    """A pickle whose loading runs code: it creates a file."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("content", ["pickle", "npy", "text"])
def test_a_planted_checkpoint_is_refused_in_one_line_and_nothing_in_it_runs(fresh_dir, capsys, content):
    import pickle

    marker = str(fresh_dir / "ran")
    with open("tuned.json.ckpt", "wb") as f:
        if content == "pickle":
            pickle.dump({"identity": {}, "log": _Planted(marker), "clock": []}, f)
        elif content == "npy":
            np.save(f, np.array([_Planted(marker)], dtype=object), allow_pickle=True)
        else:
            f.write(b"not a checkpoint\n")
    assert cli.main([*COMMANDS["tune"], "--resume"]) == 2
    captured = capsys.readouterr()
    err = captured.err
    assert err.count("\n") == 1 and "is not a coopjax tuning checkpoint" in err, err
    assert captured.out == ""  # refused before the run says anything
    assert not os.path.exists(marker)  # nothing in the file was executed
    assert sorted(os.listdir(fresh_dir)) == ["tuned.json.ckpt"]  # and nothing was written


@pytest.mark.slow
def test_ctrl_c_during_selection_or_judging_then_resume_gives_the_uninterrupted_answer(tmp_path):
    """Several interrupts at random moments after the selection starts (the start's background
    judging may still be running), each resumed: every resume ends, and with the same answer."""
    whole = subprocess.run(
        [sys.executable, "-m", "coopjax.cli", *COMMANDS["tune"]], cwd=tmp_path, capture_output=True, text=True
    )
    assert whole.returncode == 0, whole.stderr[-2000:]
    answer = json.load(open(tmp_path / "tuned.json"))["params"]
    rng = np.random.default_rng(int(time.time()))
    for trial in range(3):
        folder = tmp_path / f"trial-{trial}"
        folder.mkdir()
        proc = subprocess.Popen(
            [sys.executable, "-m", "coopjax.cli", *COMMANDS["tune"]],
            cwd=folder,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_restore_sigint,
        )
        for line in proc.stdout:
            if line.startswith("selecting"):
                break
        time.sleep(float(rng.uniform(0.0, 3.0)))
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
        if proc.returncode == 0:  # it finished first
            continue
        assert proc.returncode == 130
        resumed = subprocess.run(
            [sys.executable, "-m", "coopjax.cli", *COMMANDS["tune"], "--resume"],
            cwd=folder,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert resumed.returncode == 0, resumed.stderr[-2000:]
        assert json.load(open(folder / "tuned.json"))["params"] == answer
