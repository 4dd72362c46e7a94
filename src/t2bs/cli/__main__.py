"""`python -m t2bs.cli ...`: the `t2bs` command."""

from t2bs.cli import main

main()
