"""Every option of every pixloc command says what it does, and shows its default."""

import argparse

from workflows.cli import build_parser


def _parsers(parser, prefix=("pixloc",)):
    yield " ".join(prefix), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, prefix + (name,))


def test_every_option_has_help_and_shows_its_default():
    """Before: --rgbd-points, --device, --query-sequences, the demo's options, evaluate-model's
    --output and --seed had no help; --workers, --batch-size, --chunk-rows showed no default."""
    bare, hidden = [], []
    commands = list(_parsers(build_parser()))
    assert len(commands) > 15  # the walk reached the benchmarks too
    for command, parser in commands:
        text = parser.format_help()
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction, argparse._VersionAction)):
                continue
            if not action.help:
                bare.append(f"{command} {'/'.join(action.option_strings) or action.dest}")
            elif action.option_strings and action.default not in (None, False, [], ()) and \
                    "default" not in parser._get_formatter()._get_help_string(action):
                hidden.append(f"{command} {action.option_strings[0]}")
        assert text.startswith("usage:")
    assert not bare, f"options without help: {bare}"
    assert not hidden, f"options whose default is not shown: {hidden}"


def test_demo_refuses_too_few_references_with_the_reason(capsys):
    """Before: 'pixloc demo --references 12' failed with 'The model has no 3D points'."""
    from workflows.cli import main
    assert main(["demo", "--references", "12", "--output", "unused"]) == 2
    assert "needs at least 18" in capsys.readouterr().err
