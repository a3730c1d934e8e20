"""The `greyfit` command line: `main` parses the arguments and runs the command (cli/commands.py), one
module per group of commands beside it. `greyfit = "greyfit.service.cli:main"` (the installed
script) and `python -m greyfit.service.cli` both start here."""
from greyfit.service.cli.commands import main

__all__ = ["main"]
