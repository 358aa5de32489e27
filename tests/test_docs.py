"""What the docs quote is true of the code: every file they name exists, every `coopjax.` and
`tuning.` name they give resolves, every command they show parses, and every `python -m` module is
there. (The defaults the README's synopsis quotes are checked in test_mistakes.py.)"""

import glob
import importlib
import os
import re
import shlex

import pytest

from coopjax import cli

ROOT = os.path.join(os.path.dirname(__file__), "..")
DOCS = [os.path.join(ROOT, "README.md")] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
TEXT = {os.path.relpath(p, ROOT): open(p, encoding="utf-8").read() for p in DOCS}


def _quoted(pattern):
    return sorted({(doc, m) for doc, text in TEXT.items() for m in re.findall(pattern, text)})


@pytest.mark.parametrize("doc, path", _quoted(r"`((?:coopjax|tuning|tests|benchmarks|docs)/[\w/.\-]*\w)"))
def test_every_file_the_docs_name_exists(doc, path):
    path = path.split("::")[0]
    assert os.path.exists(os.path.join(ROOT, path)), f"{doc} names {path}, which is not there"


ENTRY_POINT_GROUPS = {"coopjax.commands"}  # names of the packaging metadata, not of the code


def _resolves(dotted: str) -> bool:
    if dotted in ENTRY_POINT_GROUPS:
        return True
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for name in parts[cut:]:
                obj = getattr(obj, name)
        except AttributeError:
            return False
        return True
    return False


@pytest.mark.parametrize("doc, name", _quoted(r"`((?:coopjax|tuning)\.[A-Za-z_][\w.]*\w)"))
def test_every_name_the_docs_give_resolves(doc, name):
    assert _resolves(name), f"{doc} names {name}, which does not resolve"


def _commands():
    out = set()
    for doc, text in TEXT.items():
        for block in re.findall(r"```(?:bash|sh)?\n(.*?)```", text, re.S):
            for line in block.splitlines():
                line = line.split("#")[0].strip()
                for part in line.split("&&"):
                    part = part.strip()
                    if part.startswith("coopjax ") and "[" not in part and "..." not in part:
                        out.add((doc, part))
    return sorted(out)


@pytest.mark.parametrize("doc, command", _commands())
def test_every_command_the_docs_show_parses(doc, command):
    parser = cli.build_parser()
    words = shlex.split(command)[1:]
    if words[-1].endswith("\\"):
        pytest.skip("continued on the next line")
    try:
        parser.parse_args(words)
    except SystemExit as error:
        if error.code:  # --help exits 0
            raise AssertionError(f"{doc}: `{command}` does not parse") from error


def _flags():
    """Every `coopjax` flag the docs name in running text, with the command it follows (if any)."""
    out = set()
    for doc, text in TEXT.items():
        for quote in re.findall(r"`([^`\n]*--[a-z][^`\n]*)`", text):
            command = re.match(r"coopjax (\S+)", quote)
            if not command:  # a bare flag may be a benchmark's: only a quoted coopjax command is checked
                continue
            for flag in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", quote):
                out.add((doc, command.group(1), flag))
    return sorted(out, key=str)


@pytest.mark.parametrize("doc, command, flag", _flags())
def test_every_flag_the_docs_name_is_a_flag(doc, command, flag):
    sub = next(a for a in cli.build_parser()._actions if a.dest == "command").choices
    known = lambda p: {s for a in p._actions for s in a.option_strings}
    assert command in sub, f"{doc}: there is no coopjax {command}"
    assert flag in known(sub[command]), f"{doc}: coopjax {command} has no {flag}"


@pytest.mark.parametrize("doc, module", _quoted(r"python -m (benchmarks(?:\.\w+)?)"))
def test_every_benchmark_the_docs_run_is_there(doc, module):
    path = os.path.join(ROOT, *module.split(".")) + (".py" if "." in module else "")
    assert os.path.exists(path), f"{doc} runs python -m {module}, which is not there"


def test_the_problem_files_training_keys_are_the_declared_ones():
    from tuning.problem import Problem

    row = next(line for line in TEXT["docs/tuning.md"].splitlines() if line.startswith("| `[training]` |"))
    quoted = re.findall(r"`(\w+)`", row.split("|")[2])
    assert quoted == [f.metadata["key"].split(".", 1)[1] for f in Problem.settings("training")]
