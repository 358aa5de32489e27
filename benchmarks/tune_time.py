"""Where the README's first command spends its time: `python -m benchmarks.tune_time [--seed 0]`.

Runs `coopjax tune` (the default problem) twice, each in a fresh Python process: first with an
empty compile cache of its own, then again with what the first run cached. From JAX's own timers
(`jax.monitoring`) it reports, per program the run builds (in the order traced, with the thread
that built it), the seconds spent tracing it, lowering it to StableHLO and compiling it (or
loading it from the cache); and, per kind of the tuner's evaluations, how many ran and their
seconds. Programs that take under 0.1 s in every phase are summed in one row. Writes
benchmarks/tune_time.json.

`--python` measures the Python example of docs/tuning.md ("Tuning from Python") the same way, in a
fresh process with an empty cache and then cached: the seconds from the start of Python to its
first gradient, the first gradient's call itself, the 30 optax steps, and the first `tuning.judge`.
The script is run after `coopjax.use_cache()` on a folder of the benchmark's own, so that the second
run can load what the first compiled (the script itself keeps nothing).

The runs import coopjax and tuning as the calling process would, so another checkout of the project
is measured the same way with `PYTHONPATH=/path/to/checkout python -m benchmarks.tune_time --out
other.json`, run from this checkout (where `benchmarks` is found), for a before-and-after table of a
change.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = r"""
import collections, json, sys, threading, time
start = time.perf_counter()
from jax import monitoring
programs, current = [], {}
EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    "/jax/core/compile/backend_compile_duration": "compile",
    "/jax/compilation_cache/cache_retrieval_time_sec": "load",
}
def on(event, duration, fun_name=None, **_):
    phase, thread = EVENTS.get(event), threading.current_thread().name
    if phase is None:
        return
    if phase == "trace":
        current[thread] = dict(name=fun_name, thread=thread, trace=0.0, lower=0.0, compile=0.0, load=0.0)
        programs.append(current[thread])
    record = current.get(thread)
    if record is not None:
        record[phase] += duration
monitoring.register_event_duration_secs_listener(on)
from tuning import evaluate
runs = collections.defaultdict(list)
call = evaluate.Evaluator._call
def timed(self, key, fn, args, execute, *rest):
    t = time.perf_counter()
    out = call(self, key, fn, args, execute, *rest)
    if execute and key[0] == "runs":
        runs[str(key[2] or "values")].append(time.perf_counter() - t)
    return out
evaluate.Evaluator._call = timed
shared = evaluate.Evaluator._judge_program  # the values, where they run in the judge's program
def timed_shared(self, params, config, judged, execute, clock):
    t = time.perf_counter()
    out = shared(self, params, config, judged, execute, clock)
    if execute:
        runs["values"].append(time.perf_counter() - t)
    return out
evaluate.Evaluator._judge_program = timed_shared
from coopjax.cli import main
code = main(["tune", "--seed", sys.argv[1], "--out", sys.argv[2], "--quiet"])
print(json.dumps(dict(code=code, wall=time.perf_counter() - start, programs=programs, runs=runs)))
"""


# The docs' script, timed at its first gradient and its judge: the two lines it must contain are
# replaced by timed copies (a missing line is an error, so the script cannot drift from the docs').
TIMED = {
    "    grad, value = gradient_and_value(theta)\n": (
        "    _t = time.perf_counter()\n"
        "    grad, value = gradient_and_value(theta)\n"
        "    grad.block_until_ready()\n"
        "    times.setdefault('first_gradient_call', time.perf_counter() - _t)\n"
        "    times.setdefault('to_first_gradient', time.perf_counter() - start)\n"
    ),
    "verdict = tuning.judge(tuned, problem=problem)": (
        "times['steps'] = time.perf_counter() - start - times['to_first_gradient']\n"
        "_t = time.perf_counter()\n"
        "verdict = tuning.judge(tuned, problem=problem)\n"
        "times['first_judge'] = time.perf_counter() - _t"
    ),
}
PYTHON_CHILD = r"""
import contextlib, io, json, sys, time
start = time.perf_counter()
times = {}
import coopjax
coopjax.use_cache()  # $COOPJAX_CACHE: the empty folder, then what the first run kept
with contextlib.redirect_stdout(io.StringIO()):
    scope = {"__name__": "docs_example", "time": time, "times": times, "start": start}
    exec(compile(sys.argv[1], "docs/tuning.md", "exec"), scope)
times["wall"] = time.perf_counter() - start
print(json.dumps(times))
"""


def docs_script() -> str:
    """The Python example of docs/tuning.md, with its first gradient and its judge timed."""
    text = open(os.path.join(os.path.dirname(__file__), "..", "docs", "tuning.md")).read()
    script = text.split("## Tuning from Python", 1)[1].split("```python", 1)[1].split("```", 1)[0]
    for line, timed in TIMED.items():
        if line not in script:
            sys.exit(f"docs/tuning.md's Python example no longer has the line {line.strip()!r}")
        script = script.replace(line, timed)
    return script


def python_example(folder: str, cache: str) -> dict:
    env = {**os.environ, "COOPJAX_CACHE": cache}
    done = subprocess.run(
        [sys.executable, "-c", PYTHON_CHILD, docs_script()], env=env, cwd=folder, capture_output=True, text=True
    )
    if done.returncode != 0:
        sys.exit(f"the docs' Python example failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def one(seed: int, folder: str, cache: str) -> dict:
    env = {**os.environ, "COOPJAX_CACHE": cache}
    out = os.path.join(folder, "tuned.json")
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(seed), out], env=env, cwd=folder, capture_output=True, text=True, check=False
    )
    if done.returncode not in (0, 3):
        sys.exit(f"coopjax tune failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def table(result: dict) -> str:
    lines = ["| program (thread) | trace [s] | lower [s] | compile or load [s] |", "|---|---|---|---|"]
    small = dict(count=0, trace=0.0, lower=0.0, compile=0.0)
    for p in result["programs"]:
        if max(p["trace"], p["lower"], p["compile"]) < 0.1:
            small["count"] += 1
            for k in ("trace", "lower", "compile"):
                small[k] += p[k]
            continue
        lines.append(f"| {p['name']} ({p['thread']}) | {p['trace']:.2f} | {p['lower']:.2f} | {p['compile']:.2f} |")
    lines.append(
        f"| {small['count']} smaller ones | {small['trace']:.2f} | {small['lower']:.2f} | {small['compile']:.2f} |"
    )
    total = {k: sum(p[k] for p in result["programs"]) for k in ("trace", "lower", "compile", "load")}
    lines.append(
        f"| all {len(result['programs'])} | {total['trace']:.2f} | {total['lower']:.2f} | {total['compile']:.2f} "
        f"(of which loading {total['load']:.2f}) |"
    )
    lines += ["", "| evaluations | count | seconds | median [s] |", "|---|---|---|---|"]
    for kind, times in result["runs"].items():
        median = sorted(times)[len(times) // 2]
        lines.append(f"| {kind} | {len(times)} | {sum(times):.2f} | {median:.3f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "tune_time.json"))
    parser.add_argument("--python", action="store_true", help="time the Python example of docs/tuning.md instead")
    args = parser.parse_args(argv)
    import jax

    report = {"jax": jax.__version__, "cores": os.cpu_count()}
    if args.python:
        return python_main(args, report)
    with tempfile.TemporaryDirectory() as folder:
        cache = os.path.join(folder, "cache")
        for label in ("empty cache", "cached"):
            result = one(args.seed, folder, cache)
            report[label] = result
            print(f"\n## {label}: {result['wall']:.1f} s from the start of Python to the end (exit {result['code']})\n")
            print(table(result), flush=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"\nwrote {args.out} (jax {report['jax']}, {report['cores']} cores, one device per core)")


def python_main(args, report) -> None:
    with tempfile.TemporaryDirectory() as folder:
        cache = os.path.join(folder, "cache")
        print(
            "| docs' Python example | to the first gradient [s] | its call [s] | 30 steps after it [s] | "
            "first judge [s] | in all [s] |\n|---|---|---|---|---|---|"
        )
        for label in ("empty cache", "cached"):
            t = report[label] = python_example(folder, cache)
            print(
                f"| {label} | {t['to_first_gradient']:.1f} | {t['first_gradient_call']:.1f} | {t['steps']:.1f} | "
                f"{t['first_judge']:.1f} | {t['wall']:.1f} |",
                flush=True,
            )
    out = args.out if args.out.endswith("python.json") else args.out.replace(".json", "_python.json")
    with open(out, "w") as f:
        json.dump(report, f, indent=1)
    print(f"\nwrote {out} (jax {report['jax']}, {report['cores']} cores, one device per core)")


if __name__ == "__main__":
    main()
