"""What every command shares: the parser, the flags built from `Config`, and the input helpers.

A mistake in the input is one line on stderr and exit code 2, with no traceback and no output file.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os

from coopjax.config import Config, choices_of
from coopjax.errors import InputError

EXIT_FAILED = 1
PLOT_FORMATS = ("png", "pdf", "svg")


class BadInput(InputError):
    """A mistake found by the command line itself (a flag's form, an output path)."""


class Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own mistakes: one line, exit 2
        raise BadInput(f"{message} (see `{self.prog} --help`)")


def flag_of(field: str) -> str:
    """The command-line spelling of an API name: `w_lag` -> `--w-lag`, `dt` -> `--dt`."""
    return "--" + field.replace("_", "-")


def config_arguments(parser: argparse.ArgumentParser, defaults: dict | None = None, skip=()) -> None:
    """The flags of every `Config` setting that has one, from its declaration (help, choices)."""
    defaults = defaults or {}
    group = parser.add_argument_group("run settings")
    for f in dataclasses.fields(Config):
        flag = f.metadata.get("flag")
        if f.name in skip:
            continue
        if f.name == "dtype":
            group.add_argument("--x64", action="store_true", help="float64 (default: float32)")
            continue
        if not flag:
            continue
        default = defaults.get(f.name, f.default)
        text = f.metadata["help"]
        if f.metadata.get("choices"):
            text += f"; one of: {', '.join(choices_of(f))}"
        if default is not None:
            text += f" (default: {default:g})" if isinstance(default, float) else f" (default: {default})"
        kind = float if isinstance(f.default, float) or f.name in ("T", "gamma_min") else str
        group.add_argument(
            flag,
            dest=f.name,
            type=kind,
            default=default,
            help=text,
            metavar=f.name.upper() if kind is str else "S" if f.name in ("dt", "T") else "X",
        )


def add_setting(p, field, dest: str, default=None, text: str | None = None) -> None:
    """A flag from a declared setting (`coopjax.config.setting`): its help, kind and choices."""
    m = field.metadata
    if m["kind"] is bool:  # a switch that sets the opposite of the default
        p.add_argument(
            m["flag"], dest=dest, action="store_const", const=not field.default, default=None, help=m["help"]
        )
        return
    unit = f", {m['unit']}" if m.get("unit") else ""
    shown = f" (default {field.default:g})" if isinstance(field.default, float) else f" (default {field.default})"
    p.add_argument(
        m["flag"],
        dest=dest,
        type=m["kind"] or type(field.default),
        default=default,
        choices=m["choices"],
        metavar=None if m["choices"] else m["flag"][2:].upper().replace("-", "_"),
        help=text or m["help"] + unit + (shown if field.default is not None else ""),
    )


def config_from(args) -> Config:
    """The `Config` the flags describe, validated."""
    values = {
        f.name: getattr(args, f.name)
        for f in dataclasses.fields(Config)
        if f.metadata.get("flag") and hasattr(args, f.name)
    }
    values["dtype"] = "float64" if getattr(args, "x64", False) else "float32"
    return Config(**values).validate()


def parse_assignment(text: str) -> tuple[str, float]:
    """`NAME=VALUE` -> (NAME, float(VALUE)), with a clear message otherwise."""
    name, sep, value = text.partition("=")
    if not sep or not name.strip() or not value.strip():
        raise BadInput(f"--set expects NAME=VALUE, got {text!r}")
    try:
        number = float(value)
    except ValueError:
        raise BadInput(f"--set {name}: {value!r} is not a number") from None
    if not math.isfinite(number):
        raise BadInput(f"--set {name}: {value!r} is not finite")
    return name.strip(), number


def assignments(items, flag: str = "--set") -> dict[str, float]:
    """Repeated `NAME=VALUE` flags as a dict; a name given twice is refused."""
    pairs = [parse_assignment(text) for text in items]
    names = [n for n, _ in pairs]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise BadInput(f"{flag} {repeated[0]} is given more than once: give each name once")
    return dict(pairs)


def check_output(path: str, what: str, extensions=None) -> None:
    """Refuse, before any work, an output whose folder is missing or whose extension is unknown."""
    if not path or os.path.basename(path) in ("", ".", ".."):
        raise BadInput(f"{what} {path!r}: give a file name")
    if os.path.basename(path).startswith(".") and extensions and os.path.basename(path)[1:].lower() in extensions:
        raise BadInput(f"{what} {path!r}: give a file name before the extension")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise BadInput(f"{what} {path!r}: folder {folder!r} does not exist")
    if os.path.isdir(path):
        raise BadInput(f"{what} {path!r} is a folder, not a file")
    if not os.access(folder, os.W_OK):
        raise BadInput(f"{what} {path!r}: folder {folder!r} is not writable")
    if os.path.exists(path) and not os.access(path, os.W_OK):
        raise BadInput(f"{what} {path!r} exists and is not writable")
    if extensions and path.rsplit(".", 1)[-1].lower() not in extensions:
        raise BadInput(f"{what} {path!r}: the file name must end in one of .{', .'.join(extensions)}")


def message(error: InputError, parser: argparse.ArgumentParser | None = None) -> str:
    """The one line for a mistake: an API name at the start of the message becomes its flag."""
    text = str(error)
    field = getattr(error, "field", None)
    if field and parser is not None and not isinstance(error, BadInput):
        flag = getattr(parser, "field_flags", {}).get(field, flag_of(field))
        known = {s for a in _all_actions(parser) for s in a.option_strings}
        if flag in known and (text.startswith(field + " ") or text.startswith(field + ":")):
            text = flag + text[len(field) :]
    return text


def _all_actions(parser):
    for action in parser._actions:
        yield action
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _all_actions(sub)
