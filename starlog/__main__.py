"""Allow ``python -m starlog``."""

from starlog.cli import main

main()
