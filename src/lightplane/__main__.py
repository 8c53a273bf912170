"""``python -m lightplane`` runs the command line."""

from lightplane.cli import main

main()
