"""``python -m lightplane`` runs the command line."""

from .cli import main

main()
