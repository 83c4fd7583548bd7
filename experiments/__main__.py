"""`python -m experiments` is the `walkerslam` command."""

from experiments.cli import app

app(prog_name="walkerslam")
