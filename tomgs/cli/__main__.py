"""`python -m tomgs.cli`: the `tomgs` command."""

from tomgs.cli.app import main

main()
