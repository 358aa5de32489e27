"""`coopjax tune`: the race of every registered tuner, and a full disk at the end. (A file of its own
so that the two test workers share the tuning tests evenly.)"""

import pytest

from coopjax import cli
from tuning import driver, session
from tuning.studies import race
from tuning.tuners import TUNERS

from test_tuning import BASE, PROBLEM, THETA, TUNER


# The smallest tune that still trains, selects and judges: every plain-run test uses it.
SMALL_TUNE = (
    "--starts 2 --train-masses 2 --held-out 2 --polish 2 --params gains "
    "--masses loguniform:0.8:4.5 --margin 0 --fixed-masses"
).split()


# The plain runs end to end (screen-SLP and the gradient tuner, tuned.json against a fresh judgement)
# are tests/test_examples.py's, on the shipped problem files.


def test_the_help_of_every_setting_renders(capsys):
    """argparse formats each help text with %: one setting's help with a bare % breaks `tune --help`."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(["tune", "--help"])
    assert exit_.value.code == 0
    assert "--polish" in capsys.readouterr().out


@pytest.mark.slow  # every registered tuner on one clock: CMA-ES and random search are exercised here
def test_the_race_gives_each_tuner_the_reference_clock_and_validates_their_choices():
    tuners = {name: (TUNER if name == TUNER.name else cls()) for name, cls in TUNERS.items()}
    options = session.Options(starts=len(THETA))
    sessions = {name: session.prepare(PROBLEM, t, options, BASE, driver.Budget(1)) for name, t in tuners.items()}
    result = race.run(sessions, TUNER.name, seeds=[3], log=lambda s: None)
    for row in result["per_seed"]:
        assert row["evaluations"][TUNER.name] == TUNER.steps * len(THETA)
        for name in TUNERS:
            assert row["evaluations"][name] > 0
            times = [t for t, _ in row["curves"][name]]
            values = [v for _, v in row["curves"][name]]
            assert times == sorted(times) and values == sorted(values, reverse=True)  # running minima
            assert all(t <= row["budget_s"] + 5.0 for t in times)  # nobody ran far past the shared clock
    assert set(result["summary"]) >= set(TUNERS)


@pytest.mark.slow
def test_a_full_disk_at_the_end_keeps_the_checkpoint_and_resume_writes_the_results(fresh_dir, capsys, monkeypatch):
    import errno

    from tuning import cli as tune_cli

    args = [
        "tune",
        "--steps",
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
        "--masses",
        "loguniform:0.8:4.5",
        "--margin",
        "0",
        "--quiet",
    ]

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:
        patch.setattr(tune_cli, "write_json", full)
        assert cli.main(args) == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("coopjax")]
    assert len(lines) == 1 and "no space left" in lines[0] and "--resume" in lines[0], err
    assert sorted(p.name for p in fresh_dir.iterdir()) == ["tuned.json.ckpt"]  # no result, no figure
    assert cli.main(args + ["--resume"]) == 0
    assert sorted(p.name for p in fresh_dir.iterdir()) == ["tuned.json", "tuned_history.png", "tuned_traces.png"]
