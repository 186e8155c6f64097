"""Every command's --help teaches: one vocabulary of placeholders, every default shown, an
example that names the command (gateway/cli.py: PLACEHOLDERS, EXAMPLES, _HelpFormatter)."""

from __future__ import annotations

import argparse
import importlib
import re

import pytest

from gateway import cli
from gateway.core.cliopts import add_common_options

WORDS = {"FILE", "DIR", "SECONDS", "N", "HOST", "PORT", "ADDRESS", "NAME", "LEVEL", "URL", "MAP"}


def parser_of(command: str) -> argparse.ArgumentParser:
    module = importlib.import_module(cli.COMMANDS[command][0])
    parser = cli._OneLineParser(prog=f"cdpr-gateway {command}")
    module.configure_parser(command, parser)
    add_common_options(parser)
    cli._teach(command, parser)
    return parser


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_help_teaches(command):
    parser = parser_of(command)
    text = parser.format_help()
    assert re.search(rf"^  cdpr-gateway {re.escape(command)}\b", text, re.M), text
    for action in parser._actions:
        if not action.option_strings or action.nargs == 0 or action.choices:
            continue
        assert action.metavar in WORDS, (command, action.option_strings, action.metavar)
        if action.default not in (None, False, argparse.SUPPRESS):
            help_line = parser._get_formatter()._expand_help(action)
            assert "default" in help_line, (command, action.option_strings, help_line)
    assert "--seconds-limit" not in text


def test_every_command_has_an_example():
    assert set(cli.EXAMPLES) == set(cli.COMMANDS)
