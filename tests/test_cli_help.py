"""Every `prt` subcommand's ``--help`` prints its help and exits 0.

argparse %-formats each help string, so a literal '%' in a text (the transfer registry's
``--epsilon`` said "≤ 1%") made ``prt precompute --help`` fail with a TypeError: this formats every
parser's help, the root's and each subcommand's, as ``--help`` would."""

import pytest

from prt_torch.cli import COMMANDS, build_parser


def _subparsers():
    parser = build_parser()
    return parser, parser._subparsers._group_actions[0].choices  # noqa: SLF001 (argparse has no public accessor)


def test_root_help_formats():
    parser, _ = _subparsers()
    assert "precompute" in parser.format_help()


@pytest.mark.parametrize("command", COMMANDS)
def test_subcommand_help_formats(command):
    _, subs = _subparsers()
    if command not in subs:
        pytest.skip(f"{command} is not part of this build")
    text = subs[command].format_help()
    assert text.startswith("usage: prt " + command)


def test_precompute_help_exits_zero(capsys):
    from prt_torch.cli import main
    with pytest.raises(SystemExit) as e:
        main(["precompute", "--help"])
    assert e.value.code == 0
    assert "--epsilon" in capsys.readouterr().out
