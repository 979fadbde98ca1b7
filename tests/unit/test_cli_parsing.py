"""Usage errors of every ``artrack`` command: one line naming the option and what it takes, one ``--help`` hint."""

from __future__ import annotations

import pytest

from services.cli import main, parser
from services.cli.parsing import usage_error
from services.cli.run import _run_parser


def error_lines(parse, capsys) -> list[str]:
    with pytest.raises(SystemExit) as stopped:
        parse()
    assert stopped.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    return captured.err.splitlines()


def test_a_bad_choice_of_a_generated_flag_is_one_line_naming_the_flag_and_its_choices(capsys):
    run, _, _ = _run_parser("capture")
    lines = error_lines(lambda: run.parse_args(["--source", "synthetic:markers", "--stamps", "nope"]), capsys)
    assert lines == ["artrack run capture: --stamps: 'nope' is not one of wall, source",
                     "(`artrack run capture --help` lists the options)"]


@pytest.mark.parametrize(("argv", "first"), [
    (["control", "replay", "jump"], "artrack control: command: 'jump' is not one of pause, resume, step, status"),
    (["eval", "a.txt", "b.txt", "--align", "rigid"], "artrack eval: --align: 'rigid' is not one of se3, sim3, none"),
    (["target", "add", "poster.png"], "artrack target add: the following arguments are required: --width"),
    (["bodies", "define", "wand", "--from", "r.mcap", "--at", "soon"],
     "artrack bodies define: --at: invalid float value: 'soon'"),
    (["nosuch"], "artrack: COMMAND: 'nosuch' is not one of "),
])
def test_every_subcommand_errs_in_one_line_and_a_hint(capsys, argv, first):
    lines = error_lines(lambda: parser().parse_args(argv), capsys)
    assert len(lines) == 2 and lines[0].startswith(first), lines
    assert lines[1] == f"(`{first.split(':')[0]} --help` lists the options)"


@pytest.mark.parametrize(("argv", "command"), [
    (["export", "r.mcap", "--format", "foxglove", "-o", "f.mcap"], "artrack export"),
    (["eval", "a.txt", "b.txt"], "artrack eval"),
    (["target", "add", "poster.png", "--width", "0.2"], "artrack target add"),
    (["demo"], "artrack demo"),
])
def test_an_option_no_command_takes_is_refused_by_the_command_given(capsys, argv, command):
    lines = error_lines(lambda: main([*argv, "--stamps", "nope"]), capsys)
    assert lines == [f"{command}: unrecognized arguments: --stamps nope", f"(`{command} --help` lists the options)"]


def test_a_message_over_several_lines_is_put_on_one():
    assert usage_error("artrack x", "argument --y: first\n  second") == "artrack x: --y: first second"
