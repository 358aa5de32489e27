"""Problem files: a `Problem` as TOML (the standard library's `tomllib`), read and written.

    scenario = "carry"                  # a registered scenario, or a list of them
    tune = "all"                        # gains | per-robot | all | a list of names
    [bounds]                            # a tuned name's search box, "LOW:HIGH" in its unit
    [fixed]                             # a parameter held at a value
    [uncertain]                         # a box the answer must hold over: "loguniform:LOW:HIGH" | "uniform:LOW:HIGH"
    [[minimise]]                        # metric, over (max | mean | cvar:ALPHA), weight, scenario (optional)
    [[require]]                         # metric, at_least or at_most (a number or a parameter's name), scenario
    [training]                          # the settings `Problem` declares with key "training.NAME"

A bad file is one `InputError`: the file, the key and its line.
"""

from __future__ import annotations

import math
import os
import re
import stat
import tomllib

from coopjax.errors import InputError
from coopjax.params import PARAMETERS, split_name
from tuning import design

MAX_BYTES = 1 << 20  # a problem file is a page of TOML: anything larger is not one

MINIMISE = ("metric", "over", "weight", "scenario")
REQUIRE = ("metric", "at_least", "at_most", "scenario")


class _Where:
    """Locates a key's line in the file's text, for the messages."""

    def __init__(self, path: str, text: str):
        self.path, self.lines = path, text.splitlines()

    def line(self, table: str | None, key: str | None = None, index: int = 0) -> int | None:
        current, seen = None, -1
        for number, raw in enumerate(self.lines, 1):
            line = raw.split("#", 1)[0].strip()
            header = re.fullmatch(r"\[\[?\s*([A-Za-z0-9_\-]+)\s*\]\]?", line)
            if header:
                current = header.group(1)
                if current == table:
                    seen += 1
                    if key is None and seen == index:
                        return number
                continue
            if key is not None and current == table and (table is None or seen == index):
                if re.match(rf"^\"?{re.escape(key)}\"?\s*=", line):
                    return number
        return None

    def error(self, message: str, table: str | None = None, key: str | None = None, index: int = 0) -> InputError:
        line = self.line(table, key, index) or (self.line(table, None, index) if table else None)
        if table is None:
            name = key or ""
        else:
            name = f"[[{table}]] #{index + 1}" if table in ("minimise", "require") else f"[{table}]"
            name += f" {key}" if key else ""
        at = f", line {line}" if line else ""
        return InputError(f"{self.path}{at}: {name + ': ' if name else ''}{message}", key or table or "problem")


def read(path: str, keys: dict[str, tuple[str, ...]]) -> tuple[dict, "_Where"]:
    """A problem file's fields, as `Problem`'s keywords (types and names checked; the rest is
    `Problem.validate`'s), and where its keys are (for `locate`); `keys` gives the file's keys, as
    `Problem` declares them: the top-level ones under None, each table's under its name."""
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):  # a FIFO or a device would block or never end
            raise InputError(f"{path}: not a regular file; a problem file is a TOML file on disk", "problem")
        if info.st_size > MAX_BYTES:
            raise InputError(
                f"{path}: {info.st_size:,} bytes; a problem file is at most {MAX_BYTES:,} bytes of TOML", "problem"
            )
        with open(path, "rb") as f:
            raw = f.read(MAX_BYTES + 1)
    except OSError as error:
        raise InputError(f"{path}: cannot read the problem file ({error.strerror or error})", "problem") from None
    try:
        text = raw.decode("utf-8")
        data = tomllib.loads(text)
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text (UTF-8) file", "problem") from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"{path}: not valid TOML: {error}", "problem") from None
    except RecursionError:
        raise InputError(f"{path}: nested too deeply to be a problem file", "problem") from None
    where = _Where(path, text)
    return parse(data, where, keys), where


def parse(data: dict, where: _Where, keys: dict[str, tuple[str, ...]]) -> dict:
    """`Problem`'s keywords from a parsed file. `tune` stays as written (a shorthand is expanded by
    `Problem.from_toml`); `minimise` and `require` entries are plain tuples."""
    for key in data:
        if key not in keys[None]:
            raise where.error(f"unknown key; a problem file has {', '.join(keys[None])}", None, key)
    fields: dict = {}
    if "scenario" in data:
        fields["scenarios"] = _names(data["scenario"], where, None, "scenario")
    if "tune" in data:
        tune = data["tune"]
        fields["names"] = tune if isinstance(tune, str) else _names(tune, where, None, "tune")
        for n in [] if isinstance(tune, str) else fields["names"]:
            _parameter(n, where, None, "tune")
    for table in ("bounds", "fixed", "uncertain", "training"):
        if table in data and not isinstance(data[table], dict):
            raise where.error("expected a table of NAME = VALUE", None, table)
    bounds = []
    for name, value in data.get("bounds", {}).items():
        _parameter(name, where, "bounds", name)
        parts = value.split(":") if isinstance(value, str) else []
        try:
            low, high = (float(x) for x in parts)
        except ValueError:
            raise where.error(f'{value!r}: expected "LOW:HIGH"', "bounds", name) from None
        if not (math.isfinite(low) and math.isfinite(high) and 0 < low < high):
            raise where.error(f"{value!r}: tuned names are searched in log space: need 0 < LOW < HIGH", "bounds", name)
        bounds.append((name, low, high))
    fields["bounds"] = tuple(bounds)
    fixed = []
    for name, value in data.get("fixed", {}).items():
        _parameter(name, where, "fixed", name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise where.error(f"{value!r}: expected a number in {_unit(name)}", "fixed", name)
        fixed.append((name, float(value)))
    fields["fixed"] = tuple(fixed)
    if "uncertain" in data:
        items = []
        for name, value in data["uncertain"].items():
            _parameter(name, where, "uncertain", name)
            try:
                items.append(design.uncertain(name, value))
            except InputError as error:
                text = str(error).removeprefix("uncertain: ").removeprefix(f"vary {name}={value}: ")
                raise where.error(text, "uncertain", name) from None
        fields["uncertain"] = tuple(items)
    if "minimise" in data:
        fields["minimise"] = tuple(_objective(e, i, where) for i, e in enumerate(_entries(data, "minimise", where)))
    if "require" in data:
        fields["require"] = tuple(_requirement(e, i, where) for i, e in enumerate(_entries(data, "require", where)))
    for key, value in data.get("training", {}).items():
        if key not in keys["training"]:
            raise where.error(f"unknown key; [training] has {', '.join(keys['training'])}", "training", key)
        fields[key] = value
    return fields


def _entries(data, table, where):
    entries = data[table]
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise where.error(f"write it as [[{table}]] tables", None, table)
    return entries


def _objective(entry: dict, index: int, where: _Where) -> tuple:
    for key in entry:
        if key not in MINIMISE:
            raise where.error(f"unknown key; [[minimise]] has {', '.join(MINIMISE)}", "minimise", key, index)
    if "metric" not in entry:
        raise where.error("give the metric to minimise", "minimise", None, index)
    over, weight = entry.get("over", "max"), entry.get("weight", 1.0)
    if not isinstance(over, str):
        raise where.error(f"{over!r}: max, mean or cvar:ALPHA", "minimise", "over", index)
    if isinstance(weight, bool) or not isinstance(weight, (int, float)):
        raise where.error(f"{weight!r}: a positive number", "minimise", "weight", index)
    scenarios = _names(entry["scenario"], where, "minimise", "scenario", index) if "scenario" in entry else None
    return (str(entry["metric"]), over, float(weight), scenarios)


def _requirement(entry: dict, index: int, where: _Where) -> tuple:
    for key in entry:
        if key not in REQUIRE:
            raise where.error(f"unknown key; [[require]] has {', '.join(REQUIRE)}", "require", key, index)
    if "metric" not in entry:
        raise where.error("give the metric required", "require", None, index)
    kinds = [k for k in ("at_least", "at_most") if k in entry]
    if len(kinds) != 1:
        raise where.error(
            "give one of at_least and at_most"
            if not kinds
            else "at_least and at_most both given: a requirement "
            "is one bound (write two [[require]] tables for a band)",
            "require",
            "at_least" if kinds else None,
            index,
        )
    bound = entry[kinds[0]]
    if isinstance(bound, str):
        _parameter(bound, where, "require", kinds[0], index)
    elif isinstance(bound, bool) or not isinstance(bound, (int, float)) or not math.isfinite(bound):
        raise where.error(
            f"{bound!r}: a number in the metric's unit, or a parameter's name", "require", kinds[0], index
        )
    scenarios = _names(entry["scenario"], where, "require", "scenario", index) if "scenario" in entry else None
    return (str(entry["metric"]), kinds[0], bound, scenarios)


def _names(value, where, table, key, index=0) -> tuple[str, ...]:
    items = [value] if isinstance(value, str) else value
    if not isinstance(items, list) or not items or not all(isinstance(x, str) for x in items):
        raise where.error(f"{value!r}: a name or a list of names", table, key, index)
    return tuple(items)


def _parameter(name, where, table, key, index=0) -> None:
    try:
        split_name(name)
    except InputError as error:
        raise where.error(str(error), table, key, index) from None


def _unit(name: str) -> str:
    return PARAMETERS[split_name(name)[0]].unit or "its unit"


def locate(error: InputError, where: _Where) -> InputError:
    """A `Problem.validate` error, with the line of the key it is about where one can be found."""
    key = error.field
    for table in (None, "training", "bounds", "fixed", "uncertain"):
        line = where.line(table, {"names": "tune", "scenario": "scenario", "n_draws": "n_draws"}.get(key, key))
        if line:
            return InputError(f"{where.path}, line {line}: {error}", key)
    for table in ("minimise", "require"):
        for i in range(len(where.lines)):
            if where.line(table, None, i) is None:
                break
            if any(re.search(rf"\b{re.escape(str(key))}\b", x) for x in _section(where, table, i)):
                return InputError(f"{where.path}, line {where.line(table, None, i)}: {error}", key)
    return InputError(f"{where.path}: {error}", key)


def _section(where: _Where, table: str, index: int) -> list[str]:
    start = where.line(table, None, index)
    out = []
    for raw in where.lines[start:]:
        if raw.strip().startswith("["):
            break
        out.append(raw.split("#", 1)[0])
    return out


def _value(x) -> str:
    if isinstance(x, str):
        return f'"{x}"'
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, (tuple, list)):
        return "[" + ", ".join(_value(v) for v in x) + "]"
    return repr(float(x)) if isinstance(x, float) else str(x)


def dump(problem) -> str:
    """The problem as a file that `load` reads back to the same problem."""
    p = problem
    lines = [
        '# A coopjax tuning problem: `coopjax tune --problem FILE` (docs/tuning.md, "Problem files").',
        f"scenario = {_value(p.scenarios[0] if len(p.scenarios) == 1 else list(p.scenarios))}",
        f"tune = {_value(list(p.names))}",
    ]
    if p.bounds:
        lines += ["", "[bounds]                # search boxes, LOW:HIGH (defaults: `coopjax tune --help`)"]
        lines += [f'{n} = "{design.shortest(low)}:{design.shortest(high)}"' for n, low, high in p.bounds]
    if p.fixed:
        lines += ["", "[fixed]"] + [f"{n} = {_value(v)}" for n, v in p.fixed]
    lines += ["", "[uncertain]             # what the answer must hold for"]
    lines += [f'{u.name} = "{u.text}"' for u in p.uncertain]
    for o in p.minimise:
        lines += ["", "[[minimise]]", f'metric = "{o.metric}"', f'over = "{o.over}"', f"weight = {_value(o.weight)}"]
        if o.scenarios:
            lines.append(f"scenario = {_value(list(o.scenarios))}")
    for r in p.require:
        lines += ["", "[[require]]", f'metric = "{r.metric}"', f"{r.kind} = {_value(r.bound)}"]
        if r.scenarios:
            lines.append(f"scenario = {_value(list(r.scenarios))}")
    lines += ["", "[training]"]
    for field in p.settings("training"):
        value = getattr(p, field.name)
        if value is not None:
            lines.append(f"{field.metadata['key'].split('.', 1)[1]} = {_value(value)}")
    return "\n".join(lines) + "\n"
