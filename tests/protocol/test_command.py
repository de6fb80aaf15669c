"""protocol/command.py: a usage mistake is one ``CommandArgumentError`` line, never a usage dump."""

from __future__ import annotations

import pytest

from protocol.command import CommandArgumentError, add_subcommand, command_parser, parse_size_px
from protocol.errors import UserError

DOC = """``egosurg thing``: a command.

Example::

    egosurg thing show FILE
"""


def _parser():
    parser = command_parser("egosurg thing", DOC)
    sub = parser.add_subparsers(dest="action", required=True)
    p = add_subcommand(sub, "show", "print a file", lambda args: 0)
    p.add_argument("file")
    p.add_argument("--every", type=int, default=1)
    add_subcommand(sub, "list", "list the files")
    return parser


def test_the_error_is_a_user_error_and_a_value_error():
    assert issubclass(CommandArgumentError, UserError)
    assert issubclass(CommandArgumentError, ValueError)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        ([], "required: {show,list} (see 'egosurg thing --help')"),
        (["show"], "required: file (see 'egosurg thing show --help')"),
        (["show", "f", "--every", "x"], "argument --every: invalid int value: 'x'"),
        (["nope"], "invalid choice: 'nope'"),
        (["list", "--bogus"], "unrecognized arguments: --bogus"),
    ],
)
def test_a_usage_mistake_is_one_line(argv, words, capsys):
    with pytest.raises(CommandArgumentError) as err:
        _parser().parse_args(argv)
    assert words in str(err.value) and "\n" not in str(err.value)
    assert capsys.readouterr().err == ""  # nothing printed: egosurg prints the one line


def test_help_shows_the_docstring_as_written_and_each_subcommand_summary(capsys):
    with pytest.raises(SystemExit) as done:
        _parser().parse_args(["--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "usage: egosurg thing [-h] {show,list} ..." in out
    assert "Example::\n\n    egosurg thing show FILE" in out
    assert "print a file" in out and "list the files" in out


def test_a_subcommand_runs_its_function():
    args = _parser().parse_args(["show", "f"])
    assert args.func(args) == 0 and args.file == "f"


@pytest.mark.parametrize(
    ("text", "kwargs", "words"),
    [
        ("960", {}, "--size '960': write it as WxH"),
        ("8x8", {}, "sides of 16 to 8192 px"),
        ("97x60", {"even": True}, "even sides of 16 to 8192 px"),
        ("4x4", {"min_px": 8, "max_px": None}, "sides of at least 8 px"),
    ],
)
def test_a_bad_size_names_the_option_and_the_rule(text, kwargs, words):
    with pytest.raises(CommandArgumentError, match=words):
        parse_size_px(text, "--size", **kwargs)


def test_a_size_is_width_then_height():
    assert parse_size_px("960X600", "--size") == (960, 600)
    assert parse_size_px("20000x8", "--size", min_px=8, max_px=None) == (20000, 8)
