"""An ArgumentParser that says "did you mean" for a misspelt option or command.

Python's argparse (before 3.14) lists the choices of a wrong command but suggests none, and for an
unknown option says only "unrecognized arguments: --prety".
"""
from __future__ import annotations

import argparse
import difflib
import re
from typing import Iterable, Optional

_INVALID_CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)")


def did_you_mean(word: str, candidates: Iterable[str]) -> str:
    """" (did you mean '--pretty'?)" for the closest candidate, or "" when none is close."""
    close = difflib.get_close_matches(word, list(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


class SuggestingArgumentParser(argparse.ArgumentParser):
    """argparse.ArgumentParser whose errors about unknown options and invalid choices suggest the
    closest known one. Subcommands' parsers are of this class too (add_subparsers makes them so)."""

    def parse_args(self, args=None, namespace=None):
        known, extras = self.parse_known_args(args, namespace)
        if extras:
            parser = self._subcommand_parser(known) or self
            options = [s for action in parser._actions for s in action.option_strings]
            hints = "".join(did_you_mean(e.split("=", 1)[0], options) for e in extras if e.startswith("-"))
            parser.error(f"unrecognized arguments: {' '.join(extras)}{hints}")
        return known

    def error(self, message: str):
        match = _INVALID_CHOICE.search(message)
        if match:
            message += did_you_mean(match.group(1), re.findall(r"'([^']*)'", match.group(2)))
        super().error(message)

    def _subcommand_parser(self, namespace: argparse.Namespace) -> Optional[argparse.ArgumentParser]:
        """The parser of the subcommand that was chosen, whose options an unknown one misspells."""
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                chosen = action.choices.get(getattr(namespace, action.dest, None) or "")
                if isinstance(chosen, SuggestingArgumentParser):
                    return chosen._subcommand_parser(namespace) or chosen
        return None
