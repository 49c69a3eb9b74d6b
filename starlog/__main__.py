"""``python -m starlog`` and the ``starlog`` console script.

The command line is imported here, so that a Ctrl-C while it loads ends the process as a Ctrl-C
ends a command (quietly, of the signal), not with a traceback.
"""

from __future__ import annotations


def main() -> None:
    """Import the command line and run it."""
    try:
        from starlog.cli import main as run_command
    except KeyboardInterrupt:
        import signal

        from starlog.replay.lifeline import die_of

        die_of(signal.SIGINT)
    run_command()


if __name__ == "__main__":
    main()
