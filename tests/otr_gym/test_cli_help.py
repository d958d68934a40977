"""``otr --help`` and every command's ``--help``: each argument says what it is, its default and,
for a number, its unit or what it counts.

The rule for numbers: the help of an ``int`` or ``float`` argument names a unit (m, mm, s, Hz,
N·m, rad, …, in the text or in parentheses) or a word that says what the number counts
(``number``, ``iterations``, ``frames``, ``envs``, ``seed``, ``fraction``, ``×`` …). "--width
(default: 640)" is not enough: 640 what?
"""

from __future__ import annotations

import argparse
import re

import pytest

from otr_gym import cli

#: Units a numeric option may be in; matched as whole tokens (not the "s" of "the clip's").
UNITS = ("m", "mm", "cm", "metres", "s", "ms", "us", "µs", "seconds", "microseconds", "min", "minutes", "h", "hours",
         "Hz", "rad", "rad/s", "deg", "degrees", "°", "N", "N·m", "kg", "fps", "px", "pixels", "%", "m/s", "MiB", "GiB")
#: Words that say what a unitless number counts, or that it is a ratio or a name (an id, a port).
COUNTING = ("number", "count", "iteration", "step", "frame", "env", "seed", "fraction", "share", "ratio", "×", "times",
            "bin", "sample", "thread", "worker", "process", "gpu", "checkpoint", "draw", "factor", "std", "per",
            "cycle", "id", "port", "priority")

_UNIT = re.compile(r"(?<![\w'’])(" + "|".join(re.escape(u) for u in sorted(UNITS, key=len, reverse=True))
                   + r")(?![\w'’])")
_COUNTING = re.compile(r"(?<![\w'’])(" + "|".join(re.escape(w) for w in COUNTING) + ")", re.IGNORECASE)
_DEFAULT_WORD = re.compile(r"(?<!the )(?<!its )(?<!a )\bdefault\b", re.IGNORECASE)
_VALUE_ACTIONS_WITHOUT_VALUE = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._StoreConstAction,
                                argparse._AppendConstAction, argparse._CountAction)


def _name(prog: str, action: argparse.Action) -> str:
    return f"{prog} {'/'.join(action.option_strings) or action.dest}"


def help_problems(parser: argparse.ArgumentParser) -> list[str]:
    """What ``--help`` leaves unsaid about ``parser``'s arguments and those of its sub-commands,
    one line each (empty: nothing)."""
    problems: list[str] = []
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        name = _name(parser.prog, action)
        if isinstance(action, argparse._SubParsersAction):
            helped = {choice.dest for choice in action._choices_actions if (choice.help or "").strip()}
            problems += [f"{parser.prog} {choice}: no help" for choice in action.choices if choice not in helped]
            for sub in dict.fromkeys(action.choices.values()):  # aliases share one parser
                problems += help_problems(sub)
            continue
        text = action.help or ""
        if text == argparse.SUPPRESS:
            continue  # deliberately hidden (internal options)
        if not text.strip():
            problems.append(f"{name}: no help")
            continue
        takes_value = not isinstance(action, _VALUE_ACTIONS_WITHOUT_VALUE)
        default = action.default
        if takes_value and _has_default(default) and not _mentions_default(text, default):
            problems.append(f"{name}: default {default!r} not shown")
        numeric = getattr(action.type, "__name__", None) in ("int", "float")  # int, float, cli.int_at_least(…)
        if takes_value and numeric and not _names_unit_or_count(text):
            problems.append(f"{name}: a number without a unit or what it counts")
    return problems


def _has_default(default) -> bool:
    """A value the option takes when not given (0 and 0.0 are defaults; None, [] and SUPPRESS are not)."""
    if default is None or default is False or default == argparse.SUPPRESS:
        return False
    return not (isinstance(default, (list, tuple)) and not default)


def _mentions_default(text: str, default) -> bool:
    """``%(default)s``, the value itself (as a token: not the 0 of 500), or the word "default" as a
    label ("default: the clip's fps"; not "the default pose")."""
    values = {str(default)}
    if isinstance(default, float):
        values.add(f"{default:g}")
    if isinstance(default, (list, tuple)):
        values.add(" ".join(map(str, default)))
    return ("%(default)" in text or _DEFAULT_WORD.search(text) is not None
            or any(re.search(rf"(?<![\w.]){re.escape(v)}(?![\w.])", text) for v in values if v))


def _names_unit_or_count(text: str) -> bool:
    text = re.sub(r"%\(default\)[-#0 +.\d]*[a-z]", "", text).replace("%%", "%")  # not the s of %(default)s
    return bool(_UNIT.search(text) or _COUNTING.search(text))


def command_parser(command: str) -> argparse.ArgumentParser:
    """The parser of ``otr COMMAND`` with its arguments configured."""
    parser = cli.build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


@pytest.mark.parametrize("command", sorted(cli.COMMANDS))
def test_every_argument_of_every_command_has_help_with_its_default_and_unit(command):
    if not cli._available(cli.COMMANDS[command][0]):
        pytest.skip(f"{cli.COMMANDS[command][0]} is not importable here")
    assert help_problems(command_parser(command)) == []


def test_an_option_without_help_is_reported():
    p = argparse.ArgumentParser(prog="otr play")
    p.add_argument("--width", type=int, default=640)  # today's otr play --width
    assert help_problems(p) == ["otr play --width: no help"]


def test_a_number_without_its_unit_or_its_default_is_reported():
    p = argparse.ArgumentParser(prog="otr play")
    p.add_argument("--width", type=int, default=640, help="video width (default: %(default)s)")
    p.add_argument("--fps", type=float, default=30.0, help="video frame rate")
    p.add_argument("--clearance-m", type=float, default=0.01, help="height above the ground (m, default %(default)s)")
    assert help_problems(p) == ["otr play --width: a number without a unit or what it counts",
                                "otr play --fps: default 30.0 not shown"]


def test_the_s_of_a_possessive_is_not_a_unit():
    assert not _names_unit_or_count("the clip's rate (default: %(default)s)")
    assert _names_unit_or_count("ramp time (s; default: %(default)s)")


def test_sub_commands_are_walked():
    p = argparse.ArgumentParser(prog="otr runs")
    sub = p.add_subparsers(dest="action")
    sub.add_parser("latest", help="print the latest checkpoint").add_argument("run")
    sub.add_parser("policy-only")
    assert help_problems(p) == ["otr runs policy-only: no help", "otr runs latest run: no help"]


def test_help_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    listed = set(re.findall(r"^ {4}(\S+)(?: |$)", out, flags=re.MULTILINE))  # a long name stands on its own line
    available = {name for name, (module, _) in cli.COMMANDS.items() if cli._available(module)}
    assert available <= listed and "eval" not in listed


def test_the_old_eval_command_names_its_two_successors(capsys):
    assert cli.main(["eval", "ref.npz", "--demo", "demo.npz"]) == 2
    err = capsys.readouterr().err
    assert "otr eval was renamed" in err and "otr score" in err and "otr evaluate" in err


def test_score_and_evaluate_say_which_they_judge():
    assert "reference" in cli.COMMANDS["score"][1] and "policy" in cli.COMMANDS["evaluate"][1]
