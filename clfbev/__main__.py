"""``python -m clfbev``: the command line (what ``torchrun ... -m clfbev train`` runs on each rank)."""
import sys

from clfbev.run.cli import main

sys.exit(main())
