"""`python -m rvt2cli ...` (also what `torchrun -m rvt2cli train ...` runs)."""

import sys

from rvt2cli.cli import main

sys.exit(main())
