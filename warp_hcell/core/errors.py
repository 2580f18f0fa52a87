"""What library code may raise for the user and what a command exits with: ``UserError`` and the
exit codes. The command-line plumbing (parsers, progress bars, status lines, ``run_main``) is
``warp_hcell.core.cli``, which only the command modules import.
"""

EXIT_USAGE = 2
"""Exit code for bad user input (argparse's own convention)."""
EXIT_INTERRUPTED = 130
"""Exit code of a command stopped by Ctrl-C or ``kill`` (128 + SIGINT, the shells' convention)."""


class UserError(Exception):
    """Bad input that the user can fix; a command reports it as one line with exit code 2."""
