"""Studies that run many tuning sessions: the race of every tuner (`race`, `coopjax tune --compare`)
and the Pareto front over a weight (`pareto`, `coopjax tune --pareto`). Each runs `tuning.session`."""
