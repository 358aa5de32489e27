"""`coopjax sweep`: many parameter sets (Monte-Carlo, grid or a table), one row of results each."""

from __future__ import annotations

import os
import shutil
import time

import jax
import numpy as np

from coopjax import devices, objectives, sweeps
from coopjax.status import Status
from coopjax.cli import interrupts, supervise
from coopjax.cli.common import BadInput, assignments, check_output, config_arguments, config_from
from coopjax.config import step_size_note
from coopjax.errors import InputError
from coopjax.io import read_table, write_table

NAME = "sweep"


def column_help() -> str:
    units = sweeps.column_units()
    return "; ".join(f"{n} [{u}]" for n, u in units.items() if n != "sample")


def add_parser(sub):
    p = sub.add_parser(
        NAME,
        help="run many parameter sets (Monte-Carlo, grid or a table) and write one row of results each",
        description="Sweep the closed loop over parameter sets, sharded over this machine's CPU cores, in resumable "
        "chunks. DIST is uniform:a:b, loguniform:a:b, normal:mean:sd, choice:v1,v2,... or grid:a:b:k (grid axes form "
        "a full factorial and imply --n). Table columns: sample; the varied parameters (units: `coopjax params`); "
        + column_help()
        + ".",
    )
    p.add_argument("--n", type=int, default=None, help="number of samples (implied by grid axes or --from)")
    p.add_argument("--vary", action="append", default=[], metavar="NAME=DIST", help="a varied parameter (repeatable)")
    p.add_argument(
        "--from",
        dest="from_file",
        default=None,
        metavar="TABLE",
        help="parameter sets from a CSV or Parquet table, one row each (a sweep's own table works)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="fix a parameter, e.g. --set G_e=500 (repeatable; a per-robot name wins over the shared one)",
    )
    config_arguments(p)
    p.add_argument(
        "--check-step",
        action="store_true",
        help="run every row again at dt/2 and mark rows whose min grip, peak or lag move by more than the "
        "accuracy tolerances (0.05 N, 2 %%, 2 %%) as status step_artefact, with a step_error column; "
        "triples the cost",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--chunk", type=int, default=16384, help="samples per saved chunk (default 16384)")
    p.add_argument("--devices", type=int, default=None, help="CPU devices to shard over (default: one per core)")
    p.add_argument("--out", default="sweep.csv", help="sweep.csv or sweep.parquet (default sweep.csv)")
    p.add_argument("--resume", action="store_true", help="finish an interrupted sweep with the same options")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--coordinator",
        default=os.environ.get("COOPJAX_COORDINATOR"),
        metavar="HOST:PORT",
        help="jax.distributed coordinator (or COOPJAX_COORDINATOR)",
    )
    p.add_argument("--num-processes", type=int, default=None, help="number of processes (or COOPJAX_NUM_PROCESSES)")
    p.add_argument("--process-id", type=int, default=None, help="this process, 0 to N-1 (or COOPJAX_PROCESS_ID)")
    p.add_argument(
        "--timeout",
        type=int,
        default=120,
        metavar="S",
        help="with --coordinator: seconds to wait for every process to join, and for a silent partner "
        "before giving up (default 120)",
    )
    return p


def _env_int(flag, value, name):
    """A flag's value, else the environment variable's, which must then be a whole number."""
    if value is not None or not os.environ.get(name):
        return value
    text = os.environ[name].strip()
    if not text.isdigit():
        raise BadInput(f"{name}={text!r} (for {flag}) is not a whole number")
    return int(text)


def _parse_vary(items) -> dict[str, str]:
    out = {}
    for text in items:
        name, sep, dist = text.partition("=")
        if not sep or not name.strip() or not dist.strip():
            raise BadInput(f"--vary expects NAME=DIST, got {text!r}")
        if name.strip() in out:
            raise BadInput(f"--vary {name.strip()} is given more than once: give each name once")
        out[name.strip()] = dist.strip()
    return out


def run(args) -> int:
    args.num_processes = _env_int("--num-processes", args.num_processes, "COOPJAX_NUM_PROCESSES")
    args.process_id = _env_int("--process-id", args.process_id, "COOPJAX_PROCESS_ID")
    distributed = [args.coordinator, args.num_processes, args.process_id]
    if any(v is not None for v in distributed) and not all(v is not None for v in distributed):
        raise BadInput("--coordinator, --num-processes and --process-id go together")
    if args.num_processes is not None and not (args.num_processes >= 1 and 0 <= args.process_id < args.num_processes):
        raise BadInput(
            f"--process-id {args.process_id} must be between 0 and --num-processes - 1 = {args.num_processes - 1}"
        )
    if args.coordinator is not None:
        host, sep, port = args.coordinator.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise BadInput(f"--coordinator {args.coordinator!r}: give HOST:PORT, e.g. 10.0.0.1:1234")
    if args.timeout < 1:
        raise BadInput(f"--timeout is {args.timeout}: it must be at least 1 s")
    if args.devices is not None and args.devices < 1:
        raise BadInput(f"--devices is {args.devices}: it must be at least 1")
    if args.chunk < 1:
        raise BadInput(f"--chunk is {args.chunk}: it must be at least 1")
    vary, fixed = _parse_vary(args.vary), assignments(args.set)
    check_output(args.out, "--out", ("csv", "parquet"))
    if args.out.lower().endswith(".parquet"):
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise BadInput(
                "writing Parquet needs pyarrow: pip install 'coopjax[sweep]', or use --out sweep.csv"
            ) from None

    # Set here, before anything creates an array: JAX fixes the device count when its backend starts
    # (a caller that already started it keeps its own). No file is touched yet.
    try:
        devices.request_devices(args.devices or None)  # before jax.distributed; not warned about
    except InputError:  # the backend is already up with another count: it keeps its devices
        pass
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    table = None
    if args.from_file:
        table = read_table(args.from_file, "--from")
        for name in sweeps.result_columns():  # a previous sweep's table: its results are not parameters
            table.pop(name, None)
        if not table:
            raise BadInput(f"--from {args.from_file!r} has no parameter columns (`coopjax params` lists the names)")
        for name, column in table.items():
            if column.dtype.kind != "f":
                raise BadInput(f"--from {args.from_file!r}: column {name!r} holds values that are not numbers")
    config = config_from(args)
    parts = args.out + ".parts"
    created = not os.path.exists(parts)
    if all(v is not None for v in distributed) and not supervise.supervised():
        # The work runs in a child whose native abort (a lost partner) becomes one line here.
        return supervise.run(
            args.argv,
            args.out + ".distributed.log",
            lambda: kept(parts, created) if args.process_id == 0 else "process 0 keeps the finished chunks",
        )
    if all(v is not None for v in distributed):  # before anything starts JAX's backend
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(
                args.coordinator,
                args.num_processes,
                args.process_id,
                initialization_timeout=args.timeout,
                heartbeat_timeout_seconds=args.timeout,
            )
        except Exception as error:  # XLA's runtime errors carry pages of detail; the first line says it
            first = str(error).strip().splitlines()[0][:200] if str(error).strip() else type(error).__name__
            raise BadInput(
                f"--coordinator {args.coordinator}: the {args.num_processes} processes did not all join within "
                f"--timeout {args.timeout} s ({first})"
            ) from None
    spec = sweeps.make_spec(
        config, n=args.n, vary=vary, fixed=fixed, seed=args.seed, table=table, check_step=args.check_step
    )
    if jax.process_count() > 1:
        _same_sweep_everywhere(spec, args.chunk)
    interrupts.report_with(lambda: kept(parts, created))
    start = time.perf_counter()
    try:
        columns = sweeps.run(spec, chunk=args.chunk, parts=parts, resume=args.resume, progress=not args.quiet)
    except Exception as error:  # noqa: BLE001 (re-raised unless it is a failed exchange between processes)
        if jax.process_count() > 1 and supervise.supervised() and supervise.is_lost(error):
            supervise.lost(error)
        raise
    if jax.process_index() == 0:
        write_table(args.out, columns)
        shutil.rmtree(parts, ignore_errors=True)
        interrupts.report_with(lambda: None)
        report(spec, columns, time.perf_counter() - start)
        print(f"wrote {args.out}")
    return 0


def _same_sweep_everywhere(spec, chunk: int) -> None:
    """Every process must run the same sweep: compare fingerprints of the options before any work
    (a fixed-size exchange, so different options cannot make the collective itself fail)."""
    import hashlib

    from jax.experimental import multihost_utils

    digest = hashlib.sha256((spec.to_json() + f"|chunk={chunk}").encode()).digest()
    mine = np.frombuffer(digest[:8], np.int64)
    with jax.enable_x64(True):
        every = np.asarray(multihost_utils.process_allgather(mine, tiled=False)).reshape(-1)
    differ = [i for i, h in enumerate(every) if h != every[0]]
    if differ:
        raise BadInput(
            f"process {differ[0]} runs a different sweep from process 0 (other --n, --vary, --set, --seed, "
            "--chunk or settings): start every process with the same options"
        )


def kept(parts: str, created: bool) -> str:
    """What an interrupted (or full-disk) sweep keeps, said truthfully; an empty parts folder that
    this run made is removed, so that the same command can start again."""
    finished = sweeps.finished_parts(parts)
    if finished:
        return (
            f"{finished} finished chunk{'s' if finished > 1 else ''} kept in {parts}; add --resume to the same "
            "command to continue"
        )
    if created:
        shutil.rmtree(parts, ignore_errors=True)
        return "no chunk had finished, so nothing was kept"
    return f"no chunk had finished in this session; {parts} is as it was (add --resume to continue)"


def report(spec, columns, elapsed) -> None:
    status = np.asarray(columns["status"])
    trusted = status == Status.OK.label
    flagged = ", ".join(
        f"{int((status == s.label).sum())} {s.label}" for s in list(Status)[1:] if (status == s.label).any()
    )
    print(
        f"coopjax sweep: {spec.n} samples of {spec.config.scenario} in {elapsed:.1f} s on {jax.device_count()} "
        f"device(s) x {jax.process_count()} process(es); {int(trusted.sum())} ok"
        + (f", flagged: {flagged} (see the status column)" if flagged else "")
    )
    for name in spec.config.metrics:
        v = np.asarray(columns[name])[trusted]
        v = v[np.isfinite(v)]
        if v.size:
            unit = objectives.METRICS[name].unit
            print(f"  {name:<10} [{unit:>3}] min {v.min():10.4g}  median {np.median(v):10.4g}  max {v.max():10.4g}")
    note = step_size_note(spec.config)
    if note:
        print(note)
