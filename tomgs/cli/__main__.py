"""`python -m tomgs.cli`: the `tomgs` command."""

from tomgs.cli import main

main()
