"""Floor 5, the command line: ``kf-train`` and its commands."""

from kf_train.cli.dispatch import COMMANDS, main, usage

__all__ = ['COMMANDS', 'main', 'usage']
