"""`python -m experiments` is the `walkerslam` command."""

import sys

from experiments.cli import main

sys.exit(main())
