"""`coopjax tune` end to end: tuned.json against a fresh judgement, its bad flags, and the race.
(A file of its own so that the two test workers share the tuning tests evenly.)"""

import dataclasses
import json

import numpy as np
import pytest

from coopjax import cli
from tuning import objective as obj
from tuning import optimize as opt

from test_tuning import BASE, CONFIG


def test_cli_writes_tuned_json_whose_after_matches_a_fresh_hard_evaluation(fresh_dir, capsys):
    code = cli.main(["tune", "--steps", "2", "--starts", "2", "--train-masses", "2", "--held-out", "2", "--params", "gains",
                     "--masses", "loguniform:0.8:4.5", "--margin", "0", "--fixed-masses", "--mode", "forward",
                     "--out", "tuned.json", "--quiet"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "holds >= F_lim" in out
    result = json.load(open("tuned.json"))
    assert set(result["params"]) == {"K_GP", "K_GI", "tau", "G_e"}
    assert result["judge"]["dt"] == obj.JUDGE_DT and result["judge"]["integrator"] == "filippov"
    # The same two sets through the Python API, in one batch as the CLI does: Table 1's gains lose
    # the grip, and a released body's impacts amplify rounding differences between batch shapes.
    paper, fresh = obj.judge([dict(opt.PAPER_GAINS), result["params"]], np.asarray(result["held_out_masses"]),
                             w_lag=result["config"]["problem"]["w_lag"])
    for key in ("min_grip", "peak_grip", "rms_lag", "objective"):
        assert result["after"][key] == pytest.approx(getattr(fresh, key), rel=1e-12), key
        assert result["before"][key] == pytest.approx(getattr(paper, key), rel=1e-12), key
    assert (fresh_dir / "tuned_history.png").stat().st_size > 10_000
    assert (fresh_dir / "tuned_traces.png").stat().st_size > 10_000
    assert not (fresh_dir / "tuned.json.ckpt.npz").exists()


@pytest.mark.parametrize(
    "args, message",
    [
        (["--mode", "sideways"], "--mode must be one of auto, forward, reverse"),
        (["--masses", "normal:1:2"], "--masses expects"),
        (["--masses", "loguniform:5:0.5"], "0 < LOW < HIGH"),
        (["--params", "K_XX"], "unknown parameter 'K_XX'"),
        (["--params", "M_b"], "not a controller parameter"),
        (["--params", "K_GP,K_GP"], "named twice"),
        (["--params", "K_GP,K_GP_L"], "both named"),
        (["--starts", "0"], "--starts is 0"),
        (["--steps", "0"], "--steps is 0"),
        (["--train-masses", "1"], "--train-masses is 1"),
        (["--switch", "soft"], "--switch must be one of"),
        (["--aggregate", "median"], "--aggregate must be one of"),
        (["--out", "tuned.txt"], "must end in one of .json"),
        (["--lr", "-1"], "--lr is -1"),
        (["--w-lag", "-1"], "--w-lag is -1"),
        (["--set", "K_GP=0.2"], "both tuned (--params) and fixed"),
        (["--set", "M_c=3", "--set", "M_c=4"], "names a parameter twice"),
        (["--held-out", "1"], "at least 2 masses"),
        (["--pareto", "--lag-weights", "a,b"], "not a comma-separated list"),
        (["--compare", "--seeds", "1,1"], "names a value twice"),
        (["--compare", "--pareto"], "choose one"),
        (["--resume"], "no tuned.json.ckpt.npz to continue"),
        (["--judge-dt", "0"], "--judge-dt is 0"),
        (["--dt", "0.05"], "too large"),
    ],
)
def test_bad_flags_give_one_line_and_exit_2(fresh_dir, capsys, args, message):
    code = cli.main(["tune"] + args)
    err = capsys.readouterr().err
    assert code == 2
    assert message in err, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert list(fresh_dir.iterdir()) == []


@pytest.mark.slow  # 28 s, for the suite's 5-minute budget; CMA-ES and random search are tested only here
def test_the_race_gives_each_tuner_the_gradient_tuners_clock_and_validates_their_choices():
    from tuning import race

    config = dataclasses.replace(CONFIG, steps=2)
    result = race.run(config, BASE, seeds=[3], log=lambda s: None)
    for row in result["per_seed"]:
        assert row["evaluations"]["gradient"] == 2 * config.starts
        for name in race.TUNERS:
            assert row["evaluations"][name] > 0
            times = [t for t, _ in row["curves"][name]]
            values = [v for _, v in row["curves"][name]]
            assert times == sorted(times) and values == sorted(values, reverse=True)  # running minima
            assert all(t <= row["budget_s"] + 5.0 for t in times)  # nobody ran far past the shared clock
    s = result["summary"]
    assert set(s) >= set(race.TUNERS) and s["CMA-ES"]["time_to_cma_final_median"] <= s["budget_s_median"] + 5.0
