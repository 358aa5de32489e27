"""`python -m coopjax.cli`: the same as the `coopjax` command."""

from coopjax.cli import entry

entry()
