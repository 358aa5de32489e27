"""The command line: real runs, and bad input as one line with exit code 2 and no file."""

import os
import subprocess
import sys

import numpy as np
import pytest

from coopjax import cli

REQUIRED = "t,F_L,F_R,gamma_L,gamma_R,x_r_L,x_r_R,x_o,x_ref_L,x_ref_R".split(",")


def test_simulate_writes_csv_and_plot(fresh_dir, capsys):
    code = cli.main(["simulate", "--scenario", "paper", "--x64", "--out", "run.csv", "--plot", "fig.png"])
    assert code == 0
    header = open("run.csv").readline().strip().split(",")
    assert set(REQUIRED) <= set(header)
    data = np.loadtxt("run.csv", delimiter=",", skiprows=1)
    F_L = data[:, header.index("F_L")]
    assert data[-1, 0] == pytest.approx(3.0) and F_L.max() > 10.0
    assert os.path.getsize("fig.png") > 10_000
    out = capsys.readouterr().out
    assert "wrote run.csv and fig.png" in out
    assert "lag" not in out  # the paper scenario has no lag window: no lag is reported


def test_real_process_exit_code_and_no_traceback(fresh_dir):
    run = subprocess.run(
        [sys.executable, "-m", "coopjax.cli", "simulate", "--set", "M_b=-1"], capture_output=True, text=True
    )
    assert run.returncode == 2
    assert run.stderr.strip() == "coopjax: error: M_b is -1 kg: it must be positive (body mass)"
    assert os.listdir(fresh_dir) == []
