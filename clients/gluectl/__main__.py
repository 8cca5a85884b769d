"""`python -m clients.gluectl`: the same command line as the installed `gluectl`."""

from clients.gluectl.cli import main

main()
